"""The command line: demo on the sample cubes, simulate, info, and clear errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np

from hsiffc.cli import main
from hsiffc.io import read_sweep
from dataclasses import replace
import pytest
from hsiffc.calibrate import calibrate
from hsiffc.io import read_sweep, write_sweep
from hsiffc.io._metadata import parse_mosaic
from hsiffc.data.mosaic import Mosaic


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
    assert re.search(r"band 1 \(r\dc\d [\d.]+ nm\): train at", out) and "[" in out
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
    # by wavelength, numbered as every table numbers bands
    assert re.search(r"training exposure per band: band 1 [\d.]+ ms, band 2 [\d.]+ ms, ",
                     capsys.readouterr().out)
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


# -- mosaics written width x height and checked against the calibration by every command

@pytest.fixture(scope="module")
def world(sample_cubes, tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_fixes")
    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    cal = root / "cal.npz"
    calibrate(sweep).save(cal)
    other = root / "mosaic4x4.tif"  # the same frames declared with another mosaic
    write_sweep(other, replace(sweep, mosaic=Mosaic.square(4)))
    toml = root / "dark.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n')
    return {"sweep": sample_cubes / "sweep_2900K.tif", "cal": cal, "other": other,
            "toml": toml, "root": root}


def test_a_tile_is_written_width_x_height_as_mosaic_takes_it():
    # "2x4" named two different tiles: the simulator's 2 rows x 4 columns and --mosaic 2x4
    # (2 wide, 4 high); every display now says W x H
    wide = Mosaic.rectangular(2, 4)
    given, _ = parse_mosaic("4x2")
    assert wide == given and wide.describe() == given.describe() == "4x2 (W x H)"
    assert parse_mosaic("2x4")[0].tile_shape == (4, 2)
    assert Mosaic.square(5, name="IMEC 5x5 NIR").describe() == "5x5 (W x H) IMEC 5x5 NIR"
    legacy = Mosaic(wide.pattern, name="2x4")  # a file written before: name not repeated
    assert legacy.describe() == "4x2 (W x H)"


def test_info_prints_the_tile_as_width_x_height(world, capsys):
    assert main(["info", str(world["sweep"])]) == 0
    assert "mosaic 4x2 (W x H)" in capsys.readouterr().out  # 2 rows of 4 bands


def test_uniformity_refuses_a_sweep_of_another_mosaic(world, tmp_path, capsys):
    assert main(["uniformity", str(world["other"]), "--calibration", str(world["cal"]),
                 "--json", str(tmp_path / "u.json")]) == 2
    err = capsys.readouterr().err
    assert str(world["other"]) in err and "mosaic 4x4 (W x H) differs" in err
    assert not (tmp_path / "u.json").exists()


def test_fit_refuses_training_frames_of_two_mosaics(world, tmp_path, capsys):
    out = tmp_path / "p.npz"
    assert main(["fit", str(world["toml"]), str(world["sweep"]), str(world["other"]), "-o",
                 str(out)]) == 2
    assert "mosaic 4x4 (W x H), but" in capsys.readouterr().err and not out.exists()


def test_fit_refuses_an_output_that_is_not_npz_before_reading_inputs(world, tmp_path, capsys):
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"not a tiff")
    assert main(["fit", str(world["toml"]), str(garbage), "-o", str(tmp_path / "p.tif")]) == 2
    err = capsys.readouterr().err
    assert "ends in .npz" in err and "garbage" not in err
