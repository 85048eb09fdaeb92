"""The command line: demo on the sample cubes, simulate, info, and clear errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from hsiffc.cli import main
from hsiffc.io import read_sweep


def test_demo_on_sample_cubes_shows_dynamic_saturation(sample_cubes, tmp_path, capsys):
    assert main(["demo", str(sample_cubes), "-o", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "level off below full scale" in out
    summary = json.loads((tmp_path / "demo" / "demo_summary.json").read_text())
    assert (tmp_path / "demo" / "dynamic_saturation.png").stat().st_size > 10_000
    fs = summary["full_scale_dn"]
    for band in summary["bands"]:
        assert band["plateau_dn"] < fs - 50  # levels off below full scale ...
        assert abs(band["saturation_dn"] - band["plateau_dn"]) < 5  # ... where the model says
        assert band["rms_dn"] < 2.0 < band["rms_linear_dn"]
    alpha = np.array(summary["alpha_percent"], dtype=float)
    assert np.all(np.diff(alpha, axis=0) >= -1e-9)  # alpha grows with exposure in every band


def test_demo_without_samples_says_how_to_fix(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # the default output folder ./hsiffc-demo is under tmp_path
    (tmp_path / "hsiffc-demo").mkdir()
    (tmp_path / "hsiffc-demo" / "notes.txt").write_text("not the demo's")
    (tmp_path / "empty").mkdir()
    assert main(["demo", "empty"]) == 2
    err = capsys.readouterr().err
    # the missing inputs are named first, even though the output folder is taken as well
    assert "sweep_2900K.tif" in err and "make_samples.py" in err and "already holds" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "hsiffc-demo"]


def test_simulate_then_info(tmp_path, capsys):
    out = tmp_path / "sim.tif"
    assert main(["simulate", str(out), "--exposures-ms", "5", "10", "--shape", "16", "24",
                 "--frames", "2", "--lamp", "2200K", "--seed", "3"]) == 0
    sw = read_sweep(out)
    assert sw.data.shape == (8, 16, 24) and sw.bit_depth == 10
    assert sw.exposure_ms.tolist() == [5.0] * 4 + [10.0] * 4
    assert main(["simulate", str(out), "--exposures-ms", "5"]) == 2  # no silent overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["info", str(out), "--json", str(tmp_path / "info.json")]) == 0
    info = json.loads((tmp_path / "info.json").read_text())
    assert info["n_frames"] == 8 and len(info["steps"]) == 4


def test_info_on_a_bad_file_names_it(tmp_path, capsys):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff")
    assert main(["info", str(bad)]) == 2
    assert "bad.tif" in capsys.readouterr().err


def test_console_entry_point_runs():
    res = subprocess.run([sys.executable, "-m", "hsiffc", "--version"], capture_output=True,
                         text=True, check=True)
    assert res.stdout.startswith("hsiffc ")


def test_calibrate_then_select(sample_cubes, tmp_path, capsys):
    cal = tmp_path / "cal.npz"
    assert main(["calibrate", str(sample_cubes / "sweep_2900K.tif"), "-o", str(cal),
                 "--json", str(tmp_path / "cal.json")]) == 0
    out = capsys.readouterr().out
    assert "hsiffc calibration (joint)" in out and "wrote" in out
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert doc["sample_counts"]["n_valid"] > 0
    assert 0.005 < doc["parameters"]["b_per_dn"]["median"] < 0.03
    assert main(["select", str(sample_cubes / "training_2900K.tif"), "--calibration", str(cal),
                 "--threshold", "12", "--json", str(tmp_path / "sel.json")]) == 0
    out = capsys.readouterr().out
    assert "band 1: train at" in out and "[" in out
    sel = json.loads((tmp_path / "sel.json").read_text())
    assert len(sel["selected_ms"]) == 8
    assert all(s in (19.35, 25.8) for s in sel["selected_ms"])
    # a calibration for other data is refused with the reason
    other = tmp_path / "other.tif"
    assert main(["simulate", str(other), "--exposures-ms", "5", "--shape", "8", "8"]) == 0
    assert main(["select", str(other), "--calibration", str(cal), "--threshold", "12"]) == 2
    assert "does not fit calibration" in capsys.readouterr().err


def test_calibrate_rejects_a_wrong_suffix(sample_cubes, tmp_path, capsys):
    assert main(["calibrate", str(sample_cubes / "sweep_2900K.tif"), "-o",
                 str(tmp_path / "cal.txt")]) == 2
    assert ".npz" in capsys.readouterr().err


def test_stages_lists_builtins_and_the_plugin(tmp_path, capsys):
    assert main(["stages", "--json", str(tmp_path / "stages.json")]) == 0
    out = capsys.readouterr().out
    assert "two_point_ffc" in out and "hsiffc (built-in)" in out
    rows = json.loads((tmp_path / "stages.json").read_text())
    plugin = [r for r in rows if r["name"] == "hot_pixel_repair"]
    assert plugin and plugin[0]["source"].startswith("hsiffc-hotpixel") and plugin[0]["status"] == "ok"


def test_fit_a_pipeline_from_toml(sample_cubes, tmp_path, capsys):
    cal = tmp_path / "cal.npz"
    assert main(["calibrate", str(sample_cubes / "sweep_2900K.tif"), "-o", str(cal)]) == 0
    toml = tmp_path / "p.toml"
    toml.write_text('[[step]]\nstage = "dark"\n\n[[step]]\nname = "ffc"\n'
                    'stage = "two_point_ffc"\ncalibration = "cal.npz"\n')
    out = tmp_path / "p.npz"
    assert main(["fit", str(toml), str(sample_cubes / "training_2900K.tif"),
                 str(sample_cubes / "darks.tif"), "-o", str(out)]) == 0
    assert "training exposure per band" in capsys.readouterr().out
    from hsiffc.stages import Pipeline

    assert [n for n, _ in Pipeline.load(out).steps] == ["dark", "ffc"]


def test_uniformity_summary_ranges_follow_the_bit_depth(tmp_path, capsys):
    """The summary's signal ranges are fractions of full scale: a 10-bit sweep whose steps end
    near 100 DN still lands in the first range (the 8-bit ranges in DN left most steps of such a
    sweep in none)."""
    import json

    sweep, cal, out = tmp_path / "u.tif", tmp_path / "c.npz", tmp_path / "u.json"
    assert main(["simulate", str(sweep), "--exposures-ms", "4", "8", "12", "16", "24", "32",
                 "--frames", "2", "--shape", "32", "32", "--irradiance-w-m2", "0.05"]) == 0
    assert main(["calibrate", str(sweep), "-o", str(cal)]) == 0
    capsys.readouterr()
    assert main(["uniformity", str(sweep), "--calibration", str(cal), "--json", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    assert [r["signal_range_dn"] for r in summary] == [[20, 120], [120, 401], [401, 802],
                                                       [802, 1023]]
    assert summary[0]["n_steps"] >= 2 and "20-120" in capsys.readouterr().out
