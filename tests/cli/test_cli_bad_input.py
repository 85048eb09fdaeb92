"""Bad input, bad parameters, bad environment: one line on stderr naming the file or parameter,
the problem and the fix, exit status 2, never a traceback (issue 13, one test per case)."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from checks import one_line as _one_line

from hsiffc.cli import main
from hsiffc.io import read_sweep, write_sweep
import logging
import struct
import tifffile
from hsiffc.errors import DataFormatError
from hsiffc.io import open_source, read_sweep, read_sweep_tiff, write_sweep
from hsiffc.io.corrected import is_corrected_file
from hsiffc.files.limits import ReadLimits
from hsiffc.data.sweep import Sweep


def _error(capsys, *names) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_input")
    sweep = root / "s.tif"
    assert main(["simulate", str(sweep), "--exposures-ms", "2", "4", "8", "16", "--shape", "8",
                 "8"]) == 0
    assert main(["simulate", str(root / "nodark.tif"), "--exposures-ms", "2", "4", "--shape",
                 "8", "8", "--no-darks"]) == 0
    assert main(["simulate", str(root / "big.tif"), "--exposures-ms", "2", "4", "--shape", "16",
                 "16"]) == 0
    assert main(["calibrate", str(sweep), "-o", str(root / "cal.npz")]) == 0
    s = read_sweep(sweep)
    light_min = s.exposure_ms[s.kind == "light"].min()
    write_sweep(root / "zero.tif", replace(s, meta={}, exposure_ms=np.where(
        s.exposure_ms == light_min, 0.0, s.exposure_ms)))
    d = s.data.astype(np.float32)
    d[3, 2, 2] = -np.inf
    write_sweep(root / "ninf.tif", replace(s, meta={}, data=d))
    write_sweep(root / "nan.tif", replace(s, meta={}, data=np.full(d.shape, np.nan, np.float32)))
    return root


def _toml(root, name, text):
    path = root / name
    path.write_text(text)
    return path


DARK_FFC = ('[[step]]\nname = "dark"\nstage = "dark"\n'
            '[[step]]\nname = "ffc"\nstage = "two_point_ffc"\n')


# -- parameters ---------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, name", [
    (["simulate", "x.tif", "--exposures-ms", "-5"], "--exposures-ms"),
    (["simulate", "x.tif", "--exposures-ms", "5", "--frames", "0"], "--frames"),
    (["select", "s.tif", "--calibration", "c.npz", "--threshold", "nan"], "--threshold"),
    (["select", "s.tif", "--calibration", "c.npz", "--threshold", "-3"], "--threshold"),
    (["diagnose", "s.tif", "--pixels", "0"], "--pixels"),
    (["correct", "s.tif", "--calibration", "c.npz", "-o", "o", "--workers", "0"], "--workers"),
    (["correct", "s.tif", "--calibration", "c.npz", "-o", "o", "--threshold", "inf"],
     "--threshold"),
    (["paper", "out", "--threshold", "twelve"], "--threshold"),
])
def test_bad_parameter_is_one_line_naming_it(tmp_path, capsys, monkeypatch, argv, name):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    line = _error(capsys, name, "--help")
    assert line.startswith(f"hsiffc {argv[0]}: error:")
    assert not list(tmp_path.iterdir())  # nothing was written


def test_unknown_option_is_one_line(capsys):
    assert main(["info", "--no-such-option", "x.tif"]) == 2
    _error(capsys, "--no-such-option")


def test_unreachable_scheduler_fails_fast(data, tmp_path, capsys):
    t0 = time.perf_counter()
    assert main(["correct", str(data / "s.tif"), "--calibration", str(data / "cal.npz"), "-o",
                 str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert time.perf_counter() - t0 < 10  # a short connection check, not distributed's 30 s
    _error(capsys, "--scheduler", "tcp://127.0.0.1:9", "cannot connect")
    assert main(["correct", str(data / "s.tif"), "--calibration", str(data / "cal.npz"), "-o",
                 str(tmp_path / "o"), "--scheduler", "not an address"]) == 2
    _error(capsys, "--scheduler", "tcp://HOST:PORT")


def test_fit_on_mixed_frame_shapes(data, tmp_path, capsys):
    toml = _toml(tmp_path, "p.toml", DARK_FFC)
    assert main(["fit", str(toml), str(data / "s.tif"), str(data / "big.tif"), "-o",
                 str(tmp_path / "p.npz")]) == 2
    _error(capsys, "big.tif", "16 x 16", "8 x 8")


def test_fit_with_frames_of_another_shape_than_the_calibration(data, tmp_path, capsys):
    toml = _toml(tmp_path, "p.toml", '[[step]]\nname = "dark"\nstage = "dark"\n'
                 f'[[step]]\nname = "mask"\nstage = "alpha_mask"\n'
                 f'calibration = "{data / "cal.npz"}"\n')
    assert main(["fit", str(toml), str(data / "big.tif"), "-o", str(tmp_path / "p.npz")]) == 2
    _error(capsys, "(16, 16)", "(8, 8)")


# -- fit --------------------------------------------------------------------------------------
def test_fit_without_darks(data, tmp_path, capsys):
    toml = _toml(tmp_path, "p.toml", DARK_FFC)
    assert main(["fit", str(toml), str(data / "nodark.tif"), "-o", str(tmp_path / "p.npz")]) == 2
    _error(capsys, "dark")
    assert not (tmp_path / "p.npz").exists()



def test_fit_with_duplicate_step_names(data, tmp_path, capsys):
    toml = _toml(tmp_path, "p.toml", '[[step]]\nname = "dark"\nstage = "dark"\n' * 2)
    assert main(["fit", str(toml), str(data / "s.tif"), "-o", str(tmp_path / "p.npz")]) == 2
    _error(capsys, "p.toml", "unique")



def test_fit_with_a_calibration_that_is_not_a_path(data, tmp_path, capsys):
    toml = _toml(tmp_path, "p.toml", '[[step]]\nname = "mask"\nstage = "alpha_mask"\n'
                 'calibration = 5\n')
    assert main(["fit", str(toml), str(data / "s.tif"), "-o", str(tmp_path / "p.npz")]) == 2
    _error(capsys, "calibration")



@pytest.mark.parametrize("content", [b"garbage", b"PK\x03\x04 not a zip"])
def test_malformed_pipeline_file(data, tmp_path, capsys, content):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(content)
    assert main(["correct", str(data / "s.tif"), "--calibration", str(data / "cal.npz"),
                 "--pipeline", str(bad), "-o", str(tmp_path / "o")]) == 2
    _error(capsys, "bad.npz")



def test_pipeline_load_on_a_malformed_manifest(tmp_path):
    from hsiffc.errors import HsiffcError
    from hsiffc.stages import Pipeline

    bad = tmp_path / "bad.npz"
    np.savez(bad, **{"manifest.json": np.frombuffer(b"{not json", np.uint8)})
    with pytest.raises(HsiffcError, match="bad.npz"):
        Pipeline.load(bad)


# -- degenerate data --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["zero.tif", "ninf.tif"])
def test_calibrate_with_a_zero_exposure_or_an_inf_pixel(data, tmp_path, capsys, name):
    """Either refused with one line naming the file, or calibrated with finite parameters."""
    out = tmp_path / "cal.npz"
    code = main(["calibrate", str(data / name), "-o", str(out)])
    if code == 2:
        _error(capsys, name)
        return
    assert code == 0
    from hsiffc.calibrate import Calibration

    cal = Calibration.load(out)
    for key in ("responsivity", "a_dn_per_ms", "b_per_dn"):
        v = np.asarray(cal[key], float)
        assert np.isfinite(v).mean() > 0.9, key  # one bad sample does not spoil the fit


@pytest.mark.parametrize("name", ["zero.tif", "ninf.tif", "nan.tif"])
def test_diagnose_never_prints_nan(data, capsys, name):
    code = main(["diagnose", str(data / name), "--pixels", "32"])
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    assert " nan " not in out.out.lower() and " inf " not in out.out.lower(), out.out
    if code != 0:
        assert code == 2 and len(out.err.strip().splitlines()) == 1 and name in out.err


def test_all_nan_sweep_does_not_calibrate(data, tmp_path, capsys):
    out = tmp_path / "cal.npz"
    assert main(["calibrate", str(data / "nan.tif"), "-o", str(out)]) == 2
    _error(capsys, "nan.tif", "non-finite")
    assert not out.exists()


def test_correct_never_writes_its_json_over_an_input_found_in_a_folder(data, tmp_path, capsys):
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "a.tif").write_bytes((data / "s.tif").read_bytes())
    before = (raw / "a.tif").read_bytes()
    code = main(["correct", str(raw), "--calibration", str(data / "cal.npz"), "-o",
                 str(tmp_path / "out"), "-q", "--json", str(raw / "a.tif"), "--overwrite"])
    assert code == 2
    _error(capsys, "a.tif", "input of this command")
    assert (raw / "a.tif").read_bytes() == before


# -- bad arguments and damaged or odd files: one clear line, never an internal error

# -- 1. hsiffc simulate: bad arguments ------------------------------------------------------------
@pytest.mark.parametrize("extra, name", [
    (["--lamp", "bogus"], "--lamp"),
    (["--lamp", "0K"], "--lamp"),
    (["--lamp", "1K"], "--lamp"),            # too cold to emit on the sensor's grid
    (["--seed", "-1"], "--seed"),
    (["--vignetting", "-0.5"], "--vignetting"),
    (["--vignetting", "1"], "--vignetting"),  # all light lost at the corners
    (["--vignetting", "2"], "--vignetting"),
    (["--irradiance-w-m2", "1e300"], "--irradiance-w-m2"),
])
def test_simulate_bad_argument_is_one_line_usage_error(tmp_path, capsys, extra, name):
    out = tmp_path / "s.tif"
    argv = ["simulate", str(out), "--exposures-ms", "1", "--shape", "8", "8"] + extra
    assert main(argv) == 2
    _one_line(capsys, name)
    assert not out.exists()


def test_simulate_lamp_checked_up_front_gives_the_same_frames(tmp_path):
    out = tmp_path / "s.tif"
    assert main(["simulate", str(out), "--exposures-ms", "1", "4", "--shape", "8", "8",
                 "--lamp", "D65", "--vignetting", "0.3", "--seed", "5"]) == 0
    from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

    ref = MosaicSensor((8, 8), seed=5).sweep([1.0, 4.0], "D65",
                                             irradiance_w_m2=PAPER_LIGHT_W_M2["training"],
                                             vignetting=0.3)
    got = read_sweep_tiff(out)
    assert np.array_equal(got.data, ref.data)
    assert list(got.illumination) == list(ref.illumination)


# -- 2. ENVI headers ------------------------------------------------------------------------------
def _envi(tmp_path, name="a", **keys):
    head = {"samples": "4", "lines": "3", "bands": "1", "data type": "12", "interleave": "bsq",
            "exposure time": "5", "bit depth": "12"}
    head.update({k.replace("_", " "): v for k, v in keys.items()})
    (tmp_path / f"{name}.raw").write_bytes(np.arange(12, dtype="<u2").tobytes())
    hdr = tmp_path / f"{name}.hdr"
    hdr.write_text("ENVI\n" + "".join(f"{k} = {v}\n" for k, v in head.items()))
    return hdr


@pytest.mark.parametrize("key, value", [("header_offset", "-4"), ("bands", "0"),
                                        ("lines", "0"), ("samples", "0"),
                                        ("byte_order", "2"), ("byte_order", "-1")])
def test_envi_bad_geometry_key_is_refused_naming_file_and_key(tmp_path, key, value):
    hdr = _envi(tmp_path, **{key: value})
    with pytest.raises(DataFormatError) as exc:
        read_sweep(hdr)
    text = str(exc.value)
    assert "a.hdr" in text and key.replace("_", " ") in text and "\n" not in text


def test_envi_negative_header_offset_is_exit_2_not_internal_error(tmp_path, capsys):
    hdr = _envi(tmp_path, header_offset="-4")
    assert main(["info", str(hdr)]) == 2
    _one_line(capsys, "a.hdr", "header offset")


def test_envi_byte_order_1_still_reads_big_endian(tmp_path):
    hdr = _envi(tmp_path, byte_order="1")
    (tmp_path / "a.raw").write_bytes(np.arange(12, dtype=">u2").tobytes())
    assert read_sweep(hdr).data.ravel().tolist() == list(range(12))


def test_read_limits_refuse_a_header_stating_no_frames(tmp_path):
    with pytest.raises(DataFormatError, match="no frames"):
        ReadLimits().check_frames(path=tmp_path / "x", n_frames=0, shape=(4, 4), itemsize=2)


# -- 3. FITS headers and data ---------------------------------------------------------------------
def _fits(path, data, **cards):
    fits = pytest.importorskip("astropy.io.fits")
    hdu = fits.PrimaryHDU(data)
    hdu.header["EXPTIME"] = 0.01
    for key, value in cards.items():
        hdu.header[key] = value
    hdu.writeto(path, overwrite=True)
    return path


@pytest.mark.parametrize("key, value", [("EXPTIME", "abc"), ("EXPTIME", True),
                                        ("BITDEPTH", "x"), ("BITDEPTH", 12.5),
                                        ("GAIN", "high")])
def test_fits_non_numeric_keyword_is_refused_naming_file_and_keyword(tmp_path, key, value):
    path = _fits(tmp_path / "k.fits", np.zeros((4, 4), np.uint16), **{key: value})
    with pytest.raises(DataFormatError) as exc:
        read_sweep(path, bit_depth=12)
    assert "k.fits" in str(exc.value) and key in str(exc.value)


def test_fits_non_numeric_exptime_is_exit_2(tmp_path, capsys):
    path = _fits(tmp_path / "k.fits", np.zeros((4, 4), np.uint16), EXPTIME="abc")
    assert main(["info", str(path)]) == 2
    _one_line(capsys, "k.fits", "EXPTIME")


@pytest.mark.parametrize("cut", [1000, 2880 + 50])  # inside the header; inside the data
def test_fits_truncated_file_is_one_line_without_astropy_warnings(tmp_path, capsys, cut):
    good = _fits(tmp_path / "good.fits", np.arange(64, dtype=np.uint16).reshape(8, 8))
    bad = tmp_path / "cut.fits"
    bad.write_bytes(good.read_bytes()[:cut])
    assert main(["info", str(bad), "--bit-depth", "16"]) == 2
    line = _one_line(capsys, "cut.fits")
    assert "WARNING" not in line


def test_fits_uint32_is_read_exactly(tmp_path):
    values = np.array([[0, 2 ** 24 + 1], [2 ** 32 - 1, 2 ** 31 + 3]], dtype=np.uint32)
    path = _fits(tmp_path / "u32.fits", values)
    sweep = read_sweep(path, bit_depth=32)
    assert sweep.data.dtype == np.uint32
    assert sweep.data[0].tolist() == values.tolist()


def test_fits_image_extension_takes_the_primary_headers_keywords(tmp_path):
    # the common camera layout: metadata in an empty primary HDU, the image in extension 1;
    # the exposure was reported missing
    fits = pytest.importorskip("astropy.io.fits")
    primary = fits.PrimaryHDU()
    primary.header["EXPTIME"] = 0.025
    primary.header["IMAGETYP"] = "Dark Frame"
    primary.header["GAIN"] = 2.5
    image = fits.ImageHDU(np.arange(64, dtype=np.uint16).reshape(8, 8))
    image.header["BITDEPTH"] = 12
    fits.HDUList([primary, image]).writeto(tmp_path / "ext.fits")
    with open_source(tmp_path / "ext.fits") as src:
        assert src.bit_depth == 12 and src.meta.get("gain") == 2.5
        origins = src.describe()
    sweep = read_sweep(tmp_path / "ext.fits")
    assert sweep.exposure_ms.tolist() == [25.0] and sweep.kind.tolist() == ["dark"]
    assert "primary header" in origins
    image.header["INHERIT"] = False  # the extension declines the primary's keywords
    fits.HDUList([primary, image]).writeto(tmp_path / "own.fits")
    with pytest.raises(DataFormatError, match="exposure"):
        read_sweep(tmp_path / "own.fits")


# -- 4. sidecar bit_shift, exposures that are not finite times ------------------------------------
def _tiff_with_sidecar(tmp_path, toml: str, data=None):
    data = np.arange(64, dtype=np.uint16).reshape(8, 8) * 16 if data is None else data
    tifffile.imwrite(tmp_path / "a.tif", data)
    (tmp_path / "hsiffc.toml").write_text(toml)
    return tmp_path / "a.tif"


@pytest.mark.parametrize("value", ["-1", "32", "40", "1.5"])
def test_sidecar_bit_shift_out_of_range_names_sidecar_and_key(tmp_path, capsys, value):
    path = _tiff_with_sidecar(tmp_path, f"[defaults]\nexposure_ms = 5\nbit_depth = 12\n"
                                        f"bit_shift = {value}\n")
    with pytest.raises(DataFormatError) as exc:
        read_sweep(path)
    assert "hsiffc.toml" in str(exc.value) and "bit_shift" in str(exc.value)
    assert "whole number 0..31" in str(exc.value) or "whole number" in str(exc.value)
    assert main(["info", str(path)]) == 2
    _one_line(capsys, "hsiffc.toml", "bit_shift")


def test_bit_shift_on_float_frames_is_refused(tmp_path, capsys):
    path = _tiff_with_sidecar(tmp_path, "[defaults]\nexposure_ms = 5\nbit_depth = 12\n"
                                        "bit_shift = 4\n",
                              data=np.full((8, 8), 16.0, np.float32))
    assert main(["info", str(path)]) == 2
    _one_line(capsys, "a.tif", "bit_shift", "float32")


@pytest.mark.parametrize("value", ["nan", "inf", "-2.0"])
def test_sidecar_exposure_not_a_finite_time_is_refused_by_info(tmp_path, capsys, value):
    path = _tiff_with_sidecar(tmp_path, f"[defaults]\nexposure_ms = {value}\n"
                                        "bit_depth = 12\n")
    assert main(["info", str(path)]) == 2
    _one_line(capsys, "hsiffc.toml", "exposure_ms")


@pytest.mark.parametrize("value", ["nan", "-3", "inf"])
def test_envi_header_exposure_not_a_finite_time_is_refused_by_info(tmp_path, capsys, value):
    hdr = _envi(tmp_path, exposure_time=value)
    assert main(["info", str(hdr)]) == 2
    _one_line(capsys, "a.hdr", "exposure_ms", "exposure time")


# -- 5. pipeline TOML -----------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["step = [1, 2]\n", 'step = [{stage = "dark"}, "ffc"]\n'])
def test_pipeline_toml_step_that_is_not_a_table_is_refused(tmp_path, text):
    from hsiffc.stages.pipeline import Pipeline

    path = tmp_path / "p.toml"
    path.write_text(text)
    with pytest.raises(DataFormatError) as exc:
        Pipeline.from_toml(path)
    assert "p.toml" in str(exc.value) and "[[step]]" in str(exc.value)


# -- 6. import of signed integers -----------------------------------------------------------------
def test_import_int16_tiff_keeps_negative_values(tmp_path, capsys):
    values = np.array([[-5, 3], [-32768, 32767]], dtype=np.int16)
    tifffile.imwrite(tmp_path / "s.tif", values)
    out = tmp_path / "out.tif"
    assert main(["import", str(tmp_path / "s.tif"), "-o", str(out), "--exposure-ms", "3",
                 "--bit-depth", "16"]) == 0
    got = read_sweep_tiff(out)
    assert got.data.dtype == np.int16 and got.data[0].tolist() == values.tolist()


def test_write_sweep_round_trips_signed_frames(tmp_path):
    data = np.array([[[-100, 0], [7, 2 ** 20]]], dtype=np.int32)
    write_sweep(tmp_path / "s.tif", Sweep(data, [1.0], "light", 24))
    got = read_sweep_tiff(tmp_path / "s.tif")
    assert got.data.dtype == np.int32 and np.array_equal(got.data, data)


def test_import_int64_is_refused_in_one_line_naming_the_input(tmp_path, capsys):
    hdr = _envi(tmp_path, data_type="14", bit_depth="16")
    (tmp_path / "a.raw").write_bytes(np.arange(12, dtype="<i8").tobytes())
    assert main(["import", str(hdr), "-o", str(tmp_path / "o.tif")]) == 2
    _one_line(capsys, "a.hdr", "int64")
    assert not (tmp_path / "o.tif").exists()


# -- 7. probing odd files for the corrected format is quiet ------------------------------------
def test_is_corrected_file_does_not_log_tifffile_errors(tmp_path, caplog):
    odd = tmp_path / "odd.tif"  # a TIFF header whose only IFD has no strip offsets or counts
    odd.write_bytes(b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
                    + struct.pack("<HHII", 256, 3, 1, 10) + struct.pack("<I", 0))
    with caplog.at_level(logging.DEBUG):
        assert is_corrected_file(odd) is False
    assert not [r for r in caplog.records if r.name.startswith("tifffile")], caplog.text


def test_open_source_still_reads_valid_sidecar_values(tmp_path):
    path = _tiff_with_sidecar(tmp_path, "[defaults]\nexposure_ms = 5\nbit_depth = 12\n"
                                        "bit_shift = 4\nphotons = nan\n")
    with open_source(path) as src:
        assert src.bit_shift == 4 and src.bit_depth == 12
