"""One band numbering wherever users read a band (issue 54): a warning, a table, the ENVI band
names and ``hsiffc quicklook --bands`` name the same band the same way, ``"band 3 (r1c0 600
nm)"``: counted from 1 by wavelength, with the band's tile position and wavelength beside it.

The mosaic's pattern order differs from its wavelength order on purpose (as the IMEC sensors'
does), so that a numbering by pattern position would fail every check."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hsiffc.cli import main
from hsiffc.cubes import Cube, quicklook, read_cube, write_cube
from hsiffc.data.frame import Frame
from hsiffc.data.mosaic import Mosaic, band_labels, band_numbers, mosaic_band_labels
from hsiffc.reflectance import target_report
from hsiffc.stages import create
from hsiffc.stages.refchecks import DarkAboveFlatWarning, check_flats

#: 2 x 2 tile: r0c0 700 nm, r0c1 500 nm, r1c0 600 nm, r1c1 550 nm (pattern = band index)
MOSAIC = Mosaic.rectangular(2, 2, [700.0, 500.0, 600.0, 550.0])
SHAPE = (8, 12)
#: band index 3 (pattern r1c1, 550 nm) is the second-shortest wavelength: band 2, where the
#: pattern order would say 4 and the file's 0-based order 1
INDEX, LABEL = 3, "band 2 (r1c1 550 nm)"


def _frame(level, **meta) -> Frame:
    data = np.asarray(level, np.float32)[MOSAIC.band_map(SHAPE)]
    return Frame.from_raw(data, exposure_ms=10.0, bit_depth=12, mosaic=MOSAIC, **meta)


def test_labels_number_bands_by_wavelength_with_their_tile_position():
    assert band_numbers(4, MOSAIC.wavelengths_nm) == [4, 1, 3, 2]
    assert mosaic_band_labels(MOSAIC) == ["band 4 (r0c0 700 nm)", "band 1 (r0c1 500 nm)",
                                          "band 3 (r1c0 600 nm)", LABEL]
    assert _frame([1, 2, 3, 4]).band_labels()[INDEX] == LABEL
    assert band_labels(2) == ["band 1", "band 2"]  # nothing known: the index, from 1
    assert all("," not in name for name in mosaic_band_labels(MOSAIC))  # ENVI lists use commas


def test_warning_table_envi_names_and_quicklook_agree(tmp_path, capsys):
    # a warning: the dark is above the flat in one band
    dark = np.full(SHAPE, 100.0, np.float32)
    flat = _frame([400.0, 400.0, 400.0, 90.0]).dark_subtracted(dark)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_flats("ffc", [flat], flat.data)
    (warning,) = [w.message for w in caught if isinstance(w.message, DarkAboveFlatWarning)]
    assert f"{LABEL} -10.0 DN" in str(warning)
    assert warning.figures["bands"] == [LABEL]

    # a table (hsiffc reflectance check's): rows by wavelength, the band's row carries its label
    values = np.asarray([0.9, 0.3, 0.6, 0.45], np.float32)[MOSAIC.band_map(SHAPE)]
    rep = target_report(values[None], np.zeros((1,) + SHAPE, np.uint32), MOSAIC.band_map(SHAPE),
                        4, [0.9, 0.3, 0.6, 0.45])
    rows = rep.to_text(MOSAIC.wavelengths_nm, mosaic_band_labels(MOSAIC)).splitlines()[2:]
    assert [row.split(" (")[0] for row in rows] == ["band 1", "band 2", "band 3", "band 4"]
    assert rows[1].startswith(LABEL) and " 0.4500 " in rows[1]

    # the ENVI band names of the pipeline's cube, read with SPy
    spectral = pytest.importorskip("spectral")
    stage = create("reconstruct", resolution="tile").fit([])
    cube = Cube.from_frame(stage.transform(_frame([1.0, 2.0, 3.0, 4.0])))
    write_cube(cube, tmp_path / "c.hdr")
    names = spectral.open_image(str(tmp_path / "c.hdr")).metadata["band names"]
    assert names[1] == LABEL and names == read_cube(tmp_path / "c.hdr").band_names()
    assert np.asarray(spectral.open_image(str(tmp_path / "c.hdr")).load())[0, 0, 1] == 4.0

    # quicklook --bands takes that number and titles its panel with that label
    fig = quicklook(tmp_path / "c.hdr", bands=[2])
    assert LABEL in [ax.get_title() for ax in fig.axes]
    assert main(["quicklook", str(tmp_path / "c.hdr"), "-o", str(tmp_path / "q.png"),
                 "--bands", "2"]) == 0
    capsys.readouterr()
    assert main(["quicklook", str(tmp_path / "c.hdr"), "-o", str(tmp_path / "r.png"),
                 "--bands", "0"]) == 2
    assert "numbered 1..4 by wavelength" in capsys.readouterr().err
