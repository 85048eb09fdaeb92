"""``hsiffc correct`` review fixes: ENVI outputs are never replaced behind the user's back nor
read back as inputs, ``--json`` cannot take an output's name, and a summary of files with
different band counts is printed, not a crash."""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pytest

from hsiffc.batch.plan import discover_inputs, is_batch_output
from hsiffc.batch.summary import BatchSummary
from hsiffc.calibrate import calibrate
from hsiffc.cli import main
from hsiffc.io import write_sweep
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

LIGHT = PAPER_LIGHT_W_M2["training"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A calibration of a simulated 16 x 20 sensor and one 4-frame and one 1-frame cube."""
    root = tmp_path_factory.mktemp("batch_fixes")
    sensor = MosaicSensor((16, 20), seed=5)
    sweep = sensor.sweep(np.linspace(2, 40, 10), "lamp A", irradiance_w_m2=LIGHT, n_frames=2,
                         seed=2)
    cal = root / "cal.npz"
    calibrate(sweep).save(cal)
    raw = root / "raw"
    raw.mkdir()
    cube = sensor.sweep([10.0, 30.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=2, darks=False,
                        seed=7)
    write_sweep(raw / "multi.tif", replace(cube, meta={}))
    one = sensor.sweep([20.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=1, darks=False, seed=8)
    write_sweep(raw / "single.tif", replace(one, meta={}))
    return {"root": root, "cal": cal, "raw": raw}


def _correct(world, inputs, out, *extra):
    return main(["correct", *map(str, inputs), "--calibration", str(world["cal"]), "-o",
                 str(out), "--format", "envi", "-q", *extra])


def _envi(out):
    return sorted(p for p in out.rglob("*") if p.suffix in (".hdr", ".img"))


def test_envi_cubes_of_skipped_outputs_are_left_alone_on_a_rerun(world, tmp_path, capsys):
    out = tmp_path / "out"
    assert _correct(world, [world["raw"]], out) == 0
    cubes = _envi(out)
    # 4 frames -> _f0000.._f0003, 1 frame -> no index; each: data + DQ + alpha (the default
    # pipeline computes alpha), header + data file
    assert len(cubes) == 4 * 6 + 6
    assert any(p.name == "multi.corrected_f0003.dq.img" for p in cubes)
    assert any(p.name == "multi.corrected_f0003.alpha.hdr" for p in cubes)
    assert any(p.name == "single.corrected.hdr" for p in cubes)
    stamps = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in cubes}
    capsys.readouterr()
    assert _correct(world, [world["raw"]], out) == 0
    assert "wrote ENVI cubes" not in capsys.readouterr().out
    assert {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in cubes} == stamps


def test_envi_cubes_missing_for_a_skipped_output_are_written(world, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["correct", str(world["raw"]), "--calibration", str(world["cal"]), "-o",
                 str(out), "-q"]) == 0
    assert not _envi(out)
    assert _correct(world, [world["raw"]], out) == 0
    assert len(_envi(out)) == 30


def test_a_file_hsiffc_did_not_write_at_an_envi_name_is_kept(world, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "multi.corrected_f0001.hdr"
    mine.write_text("ENVI\ndescription = {my own cube}\n")
    capsys.readouterr()
    assert _correct(world, [world["raw"]], out) == 1  # that file's cubes failed, rest done
    err = capsys.readouterr().err
    assert "multi.corrected_f0001.hdr" in err and "--overwrite" in err
    assert mine.read_text() == "ENVI\ndescription = {my own cube}\n"
    assert (out / "single.corrected.hdr").exists()
    assert _correct(world, [world["raw"]], out, "--overwrite") == 0
    assert "hsiffc corrected frame 1" in mine.read_text()


def test_envi_outputs_in_the_input_folder_are_not_read_back(world, tmp_path, capsys):
    folder = tmp_path / "data"
    shutil.copytree(world["raw"], folder)
    assert _correct(world, [folder], folder) == 0
    before = sorted(p.name for p in folder.iterdir())
    capsys.readouterr()
    assert _correct(world, [folder], folder) == 0
    printed = capsys.readouterr().out
    assert "2 files: 0 done, 2 skipped, 0 failed" in printed
    assert sorted(p.name for p in folder.iterdir()) == before
    pairs, ignored = discover_inputs([folder])
    assert sorted(p.name for p, _ in pairs) == ["multi.tif", "single.tif"]
    assert all(is_batch_output(p) for p in ignored) and len(ignored) == 2 + 15


@pytest.mark.parametrize("name", ["single.corrected.tif", "multi.corrected_f0000.dq.hdr",
                                  ".hsiffc.lock"])
def test_json_may_not_take_the_name_of_an_output(world, tmp_path, capsys, name):
    # the summary is written last: it replaced the corrected file the run had just written,
    # or was refused at the end, after the whole batch, on the folder's lock file
    out = tmp_path / "out"
    assert _correct(world, [world["raw"]], out, "--json", str(out / name)) == 2
    err = capsys.readouterr().err
    assert "give the summary another name" in err and str(out / name) in err
    assert not out.exists()


def test_json_onto_an_input_found_in_a_folder_is_refused_before_the_batch(world, tmp_path,
                                                                          capsys):
    # it was refused only when the summary was written, after the whole batch had run
    target = world["raw"] / "single.tif"
    before = target.read_bytes()
    out = tmp_path / "out"
    assert _correct(world, [world["raw"]], out, "--json", str(target), "--overwrite") == 2
    assert "input of this command" in capsys.readouterr().err
    assert not out.exists() and target.read_bytes() == before


def test_summary_of_files_with_different_band_counts():
    def result(name, bands):
        return {"status": "done", "rel": name, "output": name, "frames": 1, "bytes": 10,
                "warnings": [], "light_frames": 1, "uniformity_before": [1.0] * bands,
                "uniformity_after": [0.5] * bands}

    summary = BatchSummary([result("a", 16), result("b", 25)], 1.0, "out", {}, {})
    assert summary.uniformity() is None
    assert "not pooled, the files have 16 and 25 bands" in summary.to_text()
    assert summary.to_dict()["uniformity_before"] is None
    same = BatchSummary([result("a", 16), result("b", 16)], 1.0, "out", {}, {})
    before, after = same.uniformity()
    assert before.shape == (16,) and np.allclose(after, 0.5)


def test_local_workers_keep_dask_chatter_off_stderr(world, tmp_path):
    # distributed sets its loggers to INFO when imported: --workers 2 printed ~30
    # "INFO distributed.scheduler ..." lines on every run
    import subprocess
    import sys

    # a cluster even for this small input (hsiffc.batch.workers would run it in-process)
    code = ("import sys, hsiffc.batch.workers as w; w.STARTUP_S = 0.0; "
            "from hsiffc.cli import main; sys.exit(main(sys.argv[1:]))")
    run = subprocess.run([sys.executable, "-c", code, "correct", str(world["raw"]),
                          "--calibration", str(world["cal"]), "-o", str(tmp_path / "o"),
                          "--workers", "2", "-q"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "2 files: 2 done" in run.stdout
    assert "INFO" not in run.stderr and "distributed" not in run.stderr, run.stderr
