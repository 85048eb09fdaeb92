"""hsiffc reads its own exports back (issue 54): ``read_cube``, ``hsiffc info`` and
``hsiffc quicklook`` on the ENVI, OME-TIFF and netCDF cubes ``write_cube`` and
``hsiffc correct --format`` write give the same data, wavelengths, DQ and provenance as
written; the metadata users' tools read (OME ``EmissionWavelength``, netCDF numeric and indexed
coordinates)."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest

from hsiffc.cli import main
from hsiffc.cubes import Cube, read_cube, to_xarray, write_cube
from hsiffc.data.dq import DQ
from hsiffc.errors import DataFormatError
from hsiffc.io import write_sweep
from hsiffc.io.corrected import read_provenance
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

FORMATS = {"envi": ("c.hdr", "ENVI"), "ome": ("c.ome.tif", "OME-TIFF"),
           "netcdf": ("c.nc", "netCDF"), "tiff": ("c.tif", "hsiffc TIFF")}
SUFFIX = {"envi": ".hdr", "ome": ".ome.tif", "netcdf": ".nc"}


def _needs(fmt):
    if fmt == "netcdf":
        pytest.importorskip("xarray")


def _cube() -> Cube:
    """Bands out of wavelength order, a virtual band, flagged values, alpha, a history and
    attributes of every kind (numpy numbers among them, as a Frame's metadata gives them)."""
    rng = np.random.default_rng(3)
    data = rng.normal(100, 10, (5, 6, 4)).astype(np.float32)
    dq = np.zeros(data.shape, np.uint32)
    dq[1, 2, 0] = DQ.SATURATED | DQ.LEAKAGE
    dq[3, 3, 2] = DQ.DEAD
    history = [{"name": "dark", "stage": "dark", "params": {"average": "median"}},
               {"name": "cube", "stage": "reconstruct", "params": {"method": "bilinear"}}]
    attrs = {"exposure_ms": np.float32(12.5), "frame": np.int64(3), "kind": "light",
             "source": "scene.corrected.tif", "reconstruction": {"method": "bilinear"},
             "flag": True}
    return Cube(data, dq, data / 50, [700.0, 500.0, 650.0, 600.0], [10.0, 11.0, 12.0, 13.0],
                [(0, 0), (0, 1), None, (1, 1)], unit="DN", history=history, attrs=attrs)


def _assert_same(back: Cube, cube: Cube) -> None:
    want = cube.sorted()
    np.testing.assert_array_equal(back.data, want.data)
    np.testing.assert_array_equal(back.dq, want.dq)
    assert back.dq.dtype == np.uint32
    if want.alpha is None:
        assert back.alpha is None
    else:
        np.testing.assert_allclose(back.alpha, want.alpha)
    assert back.wavelengths_nm == want.wavelengths_nm
    assert back.fwhm_nm == want.fwhm_nm
    assert back.positions == want.positions
    assert back.band_index == want.band_index
    assert back.unit == want.unit
    assert json.loads(json.dumps(list(back.history))) == \
        json.loads(json.dumps(list(want.history), default=str))
    expected = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in want.attrs.items()}
    assert back.attrs == expected


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_write_cube_reads_back_as_written(tmp_path, fmt, capsys):
    _needs(fmt)
    name, label = FORMATS[fmt]
    cube = _cube()
    write_cube(cube, tmp_path / name)
    _assert_same(read_cube(tmp_path / name), cube)

    capsys.readouterr()
    assert main(["info", str(tmp_path / name), "--json", str(tmp_path / "info.json")]) == 0
    text = capsys.readouterr().out
    assert f"{label} cube, 5 x 6 px, 4 bands" in text
    assert "band 1 (r0c1 500 nm)" in text and "SATURATED 1, LEAKAGE 1, DEAD 1" in text
    assert "pipeline dark -> cube" in text and "exposure_ms 12.5" in text
    doc = json.loads((tmp_path / "info.json").read_text())
    assert doc["format"] == fmt and doc["shape"] == [5, 6, 4]
    assert [b["wavelength_nm"] for b in doc["bands"]] == [500.0, 600.0, 650.0, 700.0]
    assert [b["label"] for b in doc["bands"]] == [
        "band 1 (r0c1 500 nm)", "band 2 (r1c1 600 nm)", "band 3 (650 nm)", "band 4 (r0c0 700 nm)"]
    assert doc["dq_counts"]["DEAD"] == 1 and doc["flagged_values"] == 2
    assert doc["attrs"]["frame"] == 3


def test_info_refuses_the_dq_file_with_the_file_to_give(tmp_path, capsys):
    write_cube(_cube(), tmp_path / "c.hdr")
    assert main(["info", str(tmp_path / "c.dq.hdr")]) == 2
    assert "give the cube's own header" in capsys.readouterr().err


@pytest.fixture(scope="module")
def corrected(tmp_path_factory):
    """A small simulated scene, a fitted dark + flat pipeline, and ``hsiffc correct --cube
    bilinear`` exports in every format."""
    root = tmp_path_factory.mktemp("roundtrip")
    sensor = MosaicSensor((24, 32), seed=4)
    light = PAPER_LIGHT_W_M2["training"] * 0.8

    def save(path, sweep):
        write_sweep(path, replace(sweep, meta={}))

    save(root / "dark.tif", sensor.sweep([10.0], None, n_frames=2, seed=1))
    save(root / "flat.tif", sensor.sweep([10.0], "lamp A", irradiance_w_m2=light, n_frames=2,
                                         darks=False, seed=2))
    (root / "scene").mkdir()
    save(root / "scene" / "scene.tif", sensor.sweep([10.0], "lamp A", irradiance_w_m2=light / 2,
                                                     n_frames=1, darks=False, seed=3))
    (root / "p.toml").write_text('[[step]]\nname = "dark"\nstage = "dark"\n\n[[step]]\n'
                                 'name = "ffc"\nstage = "two_point_ffc"\nexposure_ms = 10.0\n')
    assert main(["fit", str(root / "p.toml"), "--dark", str(root / "dark.tif"), "--flat",
                 str(root / "flat.tif"), "-o", str(root / "p.npz")]) == 0
    return root


@pytest.mark.parametrize("fmt", list(SUFFIX))
def test_correct_exports_read_back_by_read_cube_info_and_quicklook(corrected, tmp_path, fmt,
                                                                   capsys):
    _needs(fmt)
    out = tmp_path / "out"
    argv = ["correct", "--pipeline", str(corrected / "p.npz"), "--cube", "bilinear",
            str(corrected / "scene"), "-o", str(out), "-q"]
    assert main(argv + ["--format", f"{fmt},tiff"]) == 0
    export = out / f"scene.corrected{SUFFIX[fmt]}"
    ref = read_cube(out / "scene.corrected.tif")  # the same frames, as the hsiffc TIFF holds them
    assert ref.attrs["source"] == "scene.corrected.tif" and ref.history
    back = read_cube(export)
    prov = back.attrs.pop("provenance")
    assert back.attrs.pop("source") == "scene.tif"  # the input it was corrected from
    ref.attrs.pop("source")
    _assert_same(back, ref)
    assert [s["stage"] for s in back.history] == ["dark", "two_point_ffc", "reconstruct"]
    whole = read_provenance(out / "scene.corrected.tif")  # the provenance, in every format
    for key in ("input", "calibration", "pipeline", "run", "warnings", "hsiffc_version"):
        assert prov[key] == whole[key], key
    assert prov["exposure"] == whole["exposure"] and prov["frame"] == 0

    # the format alone: only its files, and a rerun finds them complete
    alone = tmp_path / "alone"
    assert main(argv[:-3] + ["-o", str(alone), "-q", "--format", fmt]) == 0
    assert not list(alone.glob("*.tif")) or fmt == "ome"
    assert not (alone / "scene.corrected.tif").exists()
    capsys.readouterr()
    assert main(argv[:-3] + ["-o", str(alone), "-q", "--format", fmt]) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out

    capsys.readouterr()
    assert main(["info", str(export)]) == 0
    text = capsys.readouterr().out
    assert f"{FORMATS[fmt][1]} cube, 24 x 32 px, 8 bands" in text
    assert "pipeline dark -> ffc" in text
    assert main(["quicklook", str(export), "-o", str(tmp_path / "look.png")]) == 0
    assert (tmp_path / "look.png").stat().st_size > 1000


def test_ome_channels_carry_their_emission_wavelength_in_nm(tmp_path):
    import tifffile

    write_cube(_cube(), tmp_path / "c.ome.tif")
    with tifffile.TiffFile(tmp_path / "c.ome.tif") as tf:
        xml = tf.ome_metadata
    channels = re.findall(r"<Channel [^>]*>", xml)
    assert len(channels) == 12  # data, DQ and alpha: 4 channels each
    for k, channel in enumerate(channels):
        wl = float(re.search(r'EmissionWavelength="([^"]+)"', channel)[1])
        assert wl == [500.0, 600.0, 650.0, 700.0][k % 4]
        assert 'EmissionWavelengthUnit="nm"' in channel
    # a cube without wavelengths writes none (OME's value must be a positive number)
    write_cube(replace(_cube(), wavelengths_nm=None, fwhm_nm=None), tmp_path / "n.ome.tif")
    with tifffile.TiffFile(tmp_path / "n.ome.tif") as tf:
        assert "EmissionWavelength" not in tf.ome_metadata


def test_netcdf_coordinates_are_numeric_and_indexed(tmp_path):
    xr = pytest.importorskip("xarray")
    write_cube(_cube(), tmp_path / "c.nc")
    with xr.open_dataset(tmp_path / "c.nc") as ds:
        # numbered from 1 by wavelength, as every table, warning and band name numbers bands
        assert "band" in ds.indexes and ds["band"].values.tolist() == [1, 2, 3, 4]
        assert ds["band"].dtype.kind == "i" and ds["wavelength"].dtype.kind == "f"
        assert ds["band_index"].values.tolist() == [1, 3, 2, 0]
        assert isinstance(ds.attrs["exposure_ms"], (float, np.floating))
        assert isinstance(ds.attrs["frame"], (int, np.integer))
        assert ds.sel(band=3)["wavelength"].item() == 650.0
        # the file keeps no index on a coordinate that is not a dimension: one line adds it
        near = ds.set_xindex("wavelength").sel(wavelength=640.0, method="nearest")
        assert near["band"].item() == 3
        np.testing.assert_array_equal(near["data"].values, _cube().data[:, :, 2])
    # in memory, to_xarray gives the wavelength index at once
    mem = to_xarray(_cube())
    assert mem.sel(wavelength=600.0)["band_index"].item() == 3


def test_envi_reflectance_cube_says_its_scale_factor(tmp_path):
    import spectral

    write_cube(replace(_cube(), unit="reflectance factor"), tmp_path / "r.hdr")
    img = spectral.open_image(str(tmp_path / "r.hdr"))
    assert img.metadata["data units"] == "reflectance factor"
    assert float(img.metadata["reflectance scale factor"]) == 1.0 and img.scale_factor == 1.0
    assert read_cube(tmp_path / "r.hdr").unit == "reflectance factor"
    write_cube(_cube(), tmp_path / "dn.hdr")  # DN: no reflectance scale factor
    assert "reflectance scale factor" not in (tmp_path / "dn.hdr").read_text()


def test_envi_header_from_another_tool_reads_without_hsiffc_keys(tmp_path):
    """A header whose band keys no longer fit the cube (a tool kept them when it wrote a
    subset) reads without them; history that is not hsiffc's JSON is refused by name."""
    write_cube(_cube(), tmp_path / "c.hdr")
    hdr = tmp_path / "c.hdr"
    text = hdr.read_text()
    hdr.write_text(text.replace("hsiffc band index = {1, 3, 2, 0}", "hsiffc band index = {1, 3}"))
    back = read_cube(hdr)
    assert back.positions is None and back.band_index == (0, 1, 2, 3)
    assert back.attrs["frame"] == 3
    hdr.write_text(re.sub(r"hsiffc history = .*", "hsiffc history = [oops", text))
    with pytest.raises(DataFormatError, match="hsiffc history"):
        read_cube(hdr)


def test_correct_compresses_the_dq_planes_by_default_and_none_on_request(corrected, tmp_path):
    """--compression auto (the default): the DQ plane with a codec the format's readers have
    (zstd in the hsiffc TIFF, deflate in the OME-TIFF and netCDF), the float planes raw;
    --compression none: nothing compressed; ENVI never."""
    import tifffile

    pytest.importorskip("xarray")
    import h5py

    argv = ["correct", "--pipeline", str(corrected / "p.npz"), "--cube", "bilinear",
            str(corrected / "scene"), "-q", "--format", "tiff,ome,netcdf"]
    for option, want in (("auto", ("zstd", "deflate", "gzip")), ("none", (None, None, None))):
        out = tmp_path / option
        assert main(argv + ["-o", str(out), "--compression", option]) == 0
        with tifffile.TiffFile(out / "scene.corrected.tif") as tf:  # data, dq pages
            codecs = [p.compression.name for p in tf.pages[:2]]
        assert codecs == ["NONE", "NONE" if want[0] is None else want[0].upper()]
        with tifffile.TiffFile(out / "scene.corrected.ome.tif") as tf:
            data, dq = tf.series[0].pages[0], tf.series[1].pages[0]
            assert data.compression.name == "NONE"
            assert dq.compression.name == ("NONE" if want[1] is None else "ADOBE_DEFLATE")
        with h5py.File(out / "scene.corrected.nc", "r") as h5:
            assert h5["data"].compression is None and h5["dq"].compression == want[2]
        back = read_cube(out / "scene.corrected.ome.tif")
        np.testing.assert_array_equal(back.dq, read_cube(out / "scene.corrected.tif").sorted().dq)
