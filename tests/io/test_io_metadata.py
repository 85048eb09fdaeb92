"""Metadata from options, the file and a sidecar (in that order), missing-metadata errors, and
the layout quirks of camera files."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import tifffile

from hsiffc.errors import DataFormatError
from hsiffc.io import (LayoutWarning, MetadataConflictWarning, Overrides, open_source,
                       read_sweep)

RNG = np.random.default_rng(3)


def plain(path, data, **kw):
    tifffile.imwrite(path, data, photometric="minisblack", compression="lzw", **kw)
    return path


def test_sidecar_toml_maps_globs_to_fields(tmp_path):
    data = RNG.integers(0, 255, (4, 10, 10), dtype=np.uint8)
    plain(tmp_path / "dark_1.tif", data[0])
    plain(tmp_path / "dark_2.tif", data[1])
    plain(tmp_path / "white_1.tif", data[2:])
    (tmp_path / "hsiffc.toml").write_text(
        '[defaults]\nbit_depth = 8\nmosaic = "5x2"\n\n'
        '[[files]]\nmatch = "dark_*.tif"\nkind = "dark"\nexposure_ms = 20.0\n\n'
        '[[files]]\nmatch = "white_*.tif"\nkind = "light"\nexposure_ms = [10.0, 30.0]\n'
        'illumination = "halogen"\n')
    with open_source(tmp_path) as src:
        assert src.kind.tolist() == ["dark", "dark", "light", "light"]
        assert src.exposure_ms.tolist() == [20.0, 20.0, 10.0, 30.0]
        assert src.illumination.tolist() == ["", "", "halogen", "halogen"]
        assert src.bit_depth == 8 and src.mosaic.tile_shape == (2, 5)
        assert src.origins["exposure_ms"] == "sidecar hsiffc.toml"
        np.testing.assert_array_equal(src.to_sweep().data, data)


def test_sidecar_csv(tmp_path):
    data = RNG.integers(0, 4095, (2, 6, 6), dtype=np.uint16)
    plain(tmp_path / "a.tif", data[0])
    plain(tmp_path / "b.tif", data[1])
    (tmp_path / "hsiffc.csv").write_text(
        "# metadata\nfile,kind,exposure_ms,bit_depth\n*.tif,light,5,12\nb.tif,dark,,\n")
    sweep = read_sweep(tmp_path)
    assert sweep.kind.tolist() == ["light", "dark"] and sweep.exposure_ms.tolist() == [5, 5]
    assert sweep.meta["metadata_origins"]["bit_depth"] == "sidecar hsiffc.csv"


def test_options_then_file_then_sidecar(tmp_path):
    path = tmp_path / "t.tif"
    tifffile.imwrite(path, np.zeros((4, 4), np.uint16), extratags=[(33434, 5, 1, (1, 100), True)])
    (tmp_path / "hsiffc.toml").write_text("[defaults]\nexposure_ms = 50.0\nbit_depth = 10\n")
    with pytest.warns(MetadataConflictWarning) as record:
        src = open_source(path)
    assert src.exposure_ms[0] == pytest.approx(10.0)     # the file's own tag beats the sidecar
    assert [w.message.args[0].split(": ")[1].split()[0] for w in record] == ["exposure_ms"]
    src.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # what the user asks for: no warning
        src = open_source(path, exposure_ms=70.0, bit_depth=12, kind="dark")
    assert src.exposure_ms[0] == pytest.approx(70.0)     # the option beats the file's tag
    assert src.bit_depth == 12                           # and the sidecar
    assert src.kind[0] == "dark"                         # only the option gives it
    assert src.origins["kind"] == "--kind"
    assert src.origins["exposure_ms"].startswith("--exposure-ms (overrides file")
    assert "sidecar hsiffc.toml 50.0" in src.origins["exposure_ms"]
    assert src.origins["bit_depth"] == "--bit-depth (overrides sidecar hsiffc.toml 10)"
    src.close()


def test_explicit_sidecar_option(tmp_path):
    plain(tmp_path / "x.tif", np.zeros((3, 3), np.uint8))
    side = tmp_path / "meta" / "my.toml"
    side.parent.mkdir()
    side.write_text('[defaults]\nexposure_ms = 2.0\nbit_depth = 8\nkind = "dark"\n')
    assert read_sweep(tmp_path / "x.tif", sidecar=side).kind.tolist() == ["dark"]


@pytest.mark.parametrize("text,hint", [
    ("[defaults]\nexposure = 3\n", "unknown field 'exposure'"),
    ("[defaults]\nbit_depth = 'twelve'\n", "bit_depth = 'twelve'"),
    ("[[files]]\nkind = 'dark'\n", "needs match"),
    ("[defaults\n", "not valid TOML"),
    ("[other]\nx = 1\n", "unknown tables"),
    ("[defaults]\nkind = 'bright'\nexposure_ms = 1\n", "'bright'"),
])
def test_bad_sidecar_names_the_sidecar(tmp_path, text, hint):
    plain(tmp_path / "x.tif", np.zeros((3, 3), np.uint8))
    (tmp_path / "hsiffc.toml").write_text(text)
    with pytest.raises(DataFormatError) as excinfo:
        open_source(tmp_path / "x.tif", bit_depth=8)
    assert hint in str(excinfo.value)


def test_missing_exposure_names_file_field_and_three_ways(tmp_path):
    path = plain(tmp_path / "frame.tif", np.zeros((3, 3), np.uint8))
    with pytest.raises(DataFormatError) as excinfo:
        open_source(path, bit_depth=8)
    msg = str(excinfo.value)
    for part in ("frame.tif", "exposure_ms", "in the file itself", "hsiffc.toml",
                 "--exposure-ms"):
        assert part in msg, msg


def test_missing_bit_depth_for_float_frames(tmp_path):
    path = plain(tmp_path / "f.tif", np.zeros((3, 3), np.float32))
    with pytest.raises(DataFormatError) as excinfo:
        open_source(path, exposure_ms=1)
    assert "bit_depth" in str(excinfo.value) and "--bit-depth" in str(excinfo.value)


def test_info_lists_missing_fields_and_how_to_give_them(tmp_path, capsys):
    """``hsiffc info`` describes a file that other commands refuse: each missing field is
    listed with the ways to give it, the frames are still summarised, exit 0."""
    from hsiffc.cli import main

    path = plain(tmp_path / "f.tif", np.full((2, 4, 6), 0.25, np.float32))
    assert main(["info", str(path), "--json", str(tmp_path / "info.json")]) == 0
    out = capsys.readouterr().out
    assert "exposure_ms   MISSING" in out and "--exposure-ms 10" in out
    assert "bit_depth     MISSING" in out and "--bit-depth 12" in out
    assert "missing: bit_depth, exposure_ms" in out
    import json
    doc = json.loads((tmp_path / "info.json").read_text())
    assert doc["missing"] == ["bit_depth", "exposure_ms"] and doc["n_frames"] == 2
    assert doc["steps"][0]["n_frames"] == 2  # NaN exposures still form one step
    # given on the command line: nothing missing, the origin says so
    assert main(["info", str(path), "--exposure-ms", "3", "--bit-depth", "12"]) == 0
    out = capsys.readouterr().out
    assert "MISSING" not in out and "exposure_ms   from --exposure-ms" in out
    # every other command still refuses the file, naming the field
    with pytest.raises(DataFormatError, match="exposure_ms"):
        open_source(path, bit_depth=12)


def test_bad_overrides_are_refused():
    for kw, hint in ((dict(exposure_ms=-1), "exposure_ms"), (dict(bit_depth=40), "1..32"),
                     (dict(kind="bright"), "kind"), (dict(bit_shift=20), "0..15")):
        with pytest.raises(DataFormatError, match=hint):
            Overrides(**kw)


# -- quirks ----------------------------------------------------------------------------------
def test_bit_depth_from_dtype_warns(tmp_path):
    path = plain(tmp_path / "f.tif", RNG.integers(0, 4095, (5, 5), dtype=np.uint16) | 1)
    with pytest.warns(LayoutWarning, match="full scale"):
        src = open_source(path, exposure_ms=1)
    assert src.bit_depth == 16 and "assumed" in src.origins["bit_depth"]


@pytest.mark.parametrize("bits", [10, 12])
def test_left_aligned_samples_detected(tmp_path, bits):
    data = RNG.integers(0, 2 ** bits, (3, 20, 20), dtype=np.uint16)
    path = plain(tmp_path / "l.tif", data << (16 - bits))
    with pytest.warns(LayoutWarning, match=f"shifted right by {16 - bits}"):
        sweep = read_sweep(path, exposure_ms=1)
    assert sweep.bit_depth == bits
    np.testing.assert_array_equal(sweep.data, data)
    # with the bit depth given, the shift is found without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read_sweep(path, exposure_ms=1, bit_depth=bits).data, data)
    # --bit-shift 0 turns detection off: the values then exceed the stated depth
    with pytest.raises(DataFormatError, match="exceed the stated bit depth"):
        read_sweep(path, exposure_ms=1, bit_depth=bits, bit_shift=0)


def test_wrong_bit_shift_is_an_error(tmp_path):
    path = plain(tmp_path / "l.tif", np.array([[16, 33], [48, 64]], np.uint16))
    with pytest.raises(DataFormatError, match="not multiples of 16"):
        read_sweep(path, exposure_ms=1, bit_shift=4)


@pytest.mark.parametrize("channels", [3, 4])
def test_equal_channel_mosaic_takes_one_channel(tmp_path, channels):
    mono = RNG.integers(0, 255, (12, 15), dtype=np.uint8)
    img = np.repeat(mono[:, :, None], channels, axis=2)
    if channels == 4:
        img[:, :, 3] = 255                                # opaque alpha
    cv2.imwrite(str(tmp_path / "m.png"), img)
    with open_source(tmp_path / "m.png", exposure_ms=1, bit_depth=8) as src:
        assert src.frame_shape == (12, 15) and any("equal channels" in n for n in src.notes)
        np.testing.assert_array_equal(src.read(0), mono)


def test_colour_image_refused(tmp_path):
    img = RNG.integers(0, 255, (12, 15, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "c.png"), img)
    with pytest.raises(DataFormatError, match="colour image"):
        open_source(tmp_path / "c.png", exposure_ms=1, bit_depth=8)


def test_imec_active_area_crop(tmp_path, imec_xml):
    full = RNG.integers(0, 1023, (2, 1088, 2048), dtype=np.uint16)
    path = plain(tmp_path / "sensor.tif", full)
    with open_source(path, exposure_ms=1, bit_depth=10, mosaic=str(imec_xml)) as src:
        assert src.frame_shape == (1080, 2045) and src.mosaic.offset == (0, 0)
        assert src.mosaic.n_bands == 25 and len(src.mosaic.wavelengths_nm) == 25
        assert any("active area" in n for n in src.notes)
        np.testing.assert_array_equal(src.read(1), full[1, 3:1083, 0:2045])
    # frames already cropped to the filter area are taken as they are
    cropped = plain(tmp_path / "cropped.tif", full[:, 3:1083, :2045])
    with open_source(cropped, exposure_ms=1, bit_depth=10, mosaic=str(imec_xml)) as src:
        assert src.frame_shape == (1080, 2045) and not src.notes
    small = plain(tmp_path / "small.tif", full[:, :100, :100])
    with pytest.raises(DataFormatError, match="filter area"):
        open_source(small, exposure_ms=1, bit_depth=10, mosaic=str(imec_xml))


def test_files_that_disagree_are_refused(tmp_path):
    plain(tmp_path / "a.tif", np.zeros((4, 4), np.uint8))
    plain(tmp_path / "b.tif", np.zeros((5, 4), np.uint8))
    with pytest.raises(DataFormatError, match="different shapes"):
        open_source(tmp_path, exposure_ms=1, bit_depth=8)


def test_cli_prints_each_warning_once_on_one_line(tmp_path, capsys):
    from hsiffc.cli import main

    path = plain(tmp_path / "u8.tif", np.zeros((2, 4, 6), np.uint8))
    assert main(["info", str(path), "--exposure-ms", "1"]) == 0
    err = capsys.readouterr().err.splitlines()
    warned = [line for line in err if "assuming 8 bits" in line]
    assert len(warned) == 1 and warned[0].startswith("hsiffc info: warning: ")
    assert not any("source.py" in line or line.startswith("  ") for line in err), err


def test_info_shows_what_an_option_overrode(tmp_path, capsys):
    from hsiffc.cli import main

    path = tmp_path / "t.tif"   # EXIF ExposureTime 1/100 s in the file, 70 ms on the command line
    tifffile.imwrite(path, np.zeros((4, 4), np.uint16), extratags=[(33434, 5, 1, (1, 100), True)])
    assert main(["info", str(path), "--exposure-ms", "70", "--bit-depth", "12"]) == 0
    out = capsys.readouterr().out
    line = next(s for s in out.splitlines() if s.strip().startswith("exposure_ms"))
    assert "--exposure-ms (overrides file" in line and "10.0" in line
    assert " 70 " in out                                  # the steps table uses the option's value
