"""Bad input, bad parameters, bad environment: one line on stderr naming the file or parameter,
the problem and the fix, exit status 2, never a traceback (issue 13, one test per case)."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from hsiffc.cli import main
from hsiffc.io import read_sweep, write_sweep


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
