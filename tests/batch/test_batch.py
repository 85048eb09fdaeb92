"""``hsiffc correct``: batch correction that streams, resumes, never touches its inputs and
reports every bad input with its reason while the rest of the batch carries on."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tifffile

from hsiffc import batch
from hsiffc.files.folderlock import FolderLockedError, folder_lock
from hsiffc.calibrate import Calibration, calibrate
from hsiffc.cli import main
from hsiffc.cli.pipeline import Progress
from hsiffc.data.dq import DQ
from hsiffc.errors import DataFormatError
from hsiffc.data.frame import Frame
from hsiffc.io import read_sweep, write_sweep
from hsiffc.io.corrected import CorrectedWriter, read_corrected, read_provenance
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create
import shutil
from hsiffc.batch.plan import discover_inputs, is_batch_output
from hsiffc.batch.summary import BatchSummary
from hsiffc.calibrate import calibrate
from hsiffc.io import write_sweep

SHAPE = (32, 48)
LIGHT = PAPER_LIGHT_W_M2["training"]
VOLATILE = ("seconds", "created", "run")


def _clean(sweep):
    return replace(sweep, meta={})


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A calibration of a simulated 32 x 48 sensor and five good 4-frame cubes."""
    root = tmp_path_factory.mktemp("batch")
    sensor = MosaicSensor(SHAPE, seed=3)
    sweep = sensor.sweep(np.linspace(2, 40, 12), "lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2[
        "training"], n_frames=2, seed=1)
    cal_path = root / "cal.npz"
    calibrate(sweep).save(cal_path)
    raw = root / "raw"
    (raw / "day2").mkdir(parents=True)
    good = []
    for i in range(5):
        cube = sensor.sweep([10.0, 30.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=2,
                            darks=False, seed=10 + i)
        path = raw / ("day2" if i >= 3 else "") / f"cube_{i}.tif"
        write_sweep(path, _clean(cube))
        good.append(path)
    return {"root": root, "sensor": sensor, "cal": cal_path, "raw": raw, "good": good}


def _run(*args) -> int:
    return main(["correct", *map(str, args)])


def _digest(paths) -> dict:
    return {str(p): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths}


def _outputs(outdir: Path) -> dict:
    """Arrays and provenance (without timing) of every output below ``outdir``."""
    out = {}
    for p in sorted(outdir.rglob("*.corrected.tif")):
        c = read_corrected(p)
        prov = {k: v for k, v in c.provenance.items() if k not in VOLATILE}
        out[p.relative_to(outdir).as_posix()] = (c.data, c.dq, c.alpha, prov)
    return out


def _assert_same(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key in a:
        for x, y in zip(a[key][:3], b[key][:3]):
            np.testing.assert_array_equal(x, y, err_msg=key)
        assert a[key][3] == b[key][3], key


def _no_leftovers(outdir: Path):
    assert not [p for p in outdir.rglob("*") if p.name.endswith(".part")]


@pytest.fixture(scope="module")
def clean_run(world):
    out = world["root"] / "clean"
    assert _run(world["raw"], "--calibration", world["cal"], "-o", out) == 0
    return out, _outputs(out)


# -- correctness -------------------------------------------------------------------------------

def test_output_equals_the_in_python_pipeline_and_reads_with_tifffile(world, clean_run):
    out, outputs = clean_run
    assert sorted(outputs) == ["cube_0.corrected.tif", "cube_1.corrected.tif",
                               "cube_2.corrected.tif", "day2/cube_3.corrected.tif",
                               "day2/cube_4.corrected.tif"]
    pipe = batch.default_pipeline(world["cal"], threshold_percent=12.0)
    for src in world["good"]:
        rel = src.relative_to(world["raw"])
        path = out / batch.output_name(rel)
        data, dq, alpha, prov = outputs[batch.output_name(rel)]
        frames = Frame.list_from_sweep(read_sweep(src))
        assert data.shape == (len(frames),) + SHAPE
        for k, frame in enumerate(frames):
            expect = pipe.transform(frame)
            np.testing.assert_array_equal(data[k], expect.data)
            np.testing.assert_array_equal(dq[k], expect.dq)
            np.testing.assert_array_equal(alpha[k], expect.alpha)
        # the documented tifffile reading: three series, or every third page
        np.testing.assert_array_equal(tifffile.imread(path), data)
        np.testing.assert_array_equal(tifffile.imread(path, series=1), dq)
        np.testing.assert_array_equal(tifffile.imread(path, series=2), alpha)
        np.testing.assert_array_equal(tifffile.imread(path, key=slice(2, None, 3)), alpha)
        cal_id = Calibration.load(world["cal"]).identity
        assert prov["status"] == "complete" and prov["format"] == "hsiffc-corrected"
        assert prov["calibration"]["identity"] == cal_id
        assert [s["stage"] for s in prov["pipeline"]["steps"]] == ["dark", "alpha_mask", "model_ffc"]
        assert prov["pipeline"]["steps"][1]["params"]["threshold_percent"] == 12.0
        assert prov["input"]["sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()
        assert prov["exposure"] == [10.0, 10.0, 30.0, 30.0]
        assert prov["hsiffc_version"]
        assert len(prov["frames"]["uniformity_after"][0]) == 8
    assert (dq & DQ.LEAKAGE).any()  # the 30 ms frames leak in some pixels


def test_fitted_pipeline_file_is_applied_as_in_python(world, tmp_path):
    s = world["sensor"]
    train = (Frame.list_from_sweep(s.sweep([10.0, 25.0], None, n_frames=3, seed=2))
             + Frame.list_from_sweep(s.sweep([10.0], "lamp A", irradiance_w_m2=LIGHT,
                                             n_frames=3, darks=False, seed=3)))
    pipe = Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=str(world["cal"]))),
                     ("ffc", create("two_point_ffc", exposure_ms=10.0,
                                    normalisation="mean_gain"))]).fit(train)
    pipe.save(tmp_path / "pipe.npz")
    out = tmp_path / "out"
    assert _run(world["good"][0], "--calibration", world["cal"], "--pipeline",
                tmp_path / "pipe.npz", "-o", out) == 0
    c = read_corrected(out / "cube_0.corrected.tif")
    loaded = Pipeline.load(tmp_path / "pipe.npz")
    for k, frame in enumerate(Frame.list_from_sweep(read_sweep(world["good"][0]))):
        expect = loaded.transform(frame)
        np.testing.assert_array_equal(c.data[k], expect.data)
        np.testing.assert_array_equal(c.dq[k], expect.dq)
    assert c.provenance["pipeline"]["kind"] == "file"
    assert [s["name"] for s in c.provenance["pipeline"]["steps"]] == ["dark", "mask", "ffc"]


def test_pipeline_fitted_with_another_calibration_is_refused(world, tmp_path, capsys):
    other = tmp_path / "other.npz"
    s2 = MosaicSensor(SHAPE, seed=99)
    calibrate(s2.sweep(np.linspace(2, 40, 8), "lamp A", irradiance_w_m2=LIGHT * 2,
                       n_frames=2, seed=1)).save(other)
    pipe = Pipeline([("mask", create("alpha_mask", calibration=str(other)))])
    pipe.steps[0][1].fit([])
    pipe.save(tmp_path / "pipe.npz")
    assert _run(world["good"][0], "--calibration", world["cal"], "--pipeline",
                tmp_path / "pipe.npz", "-o", tmp_path / "out") == 2
    assert "uses calibration" in capsys.readouterr().err


# -- bad inputs --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bad_folder(world):
    """Good cubes plus one of each bad input."""
    d = world["root"] / "mixed"
    d.mkdir()
    s = world["sensor"]
    write_sweep(d / "good_a.tif", _clean(s.sweep([10.0], "lamp A", irradiance_w_m2=LIGHT,
                                                 n_frames=3, darks=False, seed=5)))
    write_sweep(d / "good_b.tif", _clean(s.sweep([12.0], "lamp A", irradiance_w_m2=LIGHT,
                                                 n_frames=2, darks=False, seed=6)))
    (d / "unreadable.tif").write_bytes(b"this is not a TIFF file at all" * 10)
    whole = (d / "good_a.tif").read_bytes()
    (d / "truncated.tif").write_bytes(whole[: len(whole) * 2 // 3])
    small = MosaicSensor((16, 48), seed=3)
    write_sweep(d / "wrong_shape.tif", _clean(small.sweep([10.0], "lamp A",
                                                          irradiance_w_m2=LIGHT, n_frames=2,
                                                          darks=False)))
    cube = _clean(s.sweep([10.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=2, darks=False))
    write_sweep(d / "wrong_bits.tif", replace(cube, bit_depth=12))
    tifffile.imwrite(d / "plain_no_metadata.tif", cube.data, photometric="minisblack",
                     metadata=None)
    doc = {"format": "hsiffc", "exposure_unit": "ms", "bit_depth": 10, "kind": "light"}
    tifffile.imwrite(d / "no_exposure.tif", cube.data, photometric="minisblack",
                     metadata=None, description=json.dumps(doc))
    nan = cube.data.astype(np.float32)
    nan[1, 3:5, 7] = np.nan
    nan[0, 0, 0] = np.inf
    write_sweep(d / "with_nan.tif", replace(cube, data=nan))
    return d


def test_each_bad_input_is_reported_with_its_reason_and_the_rest_carries_on(world, bad_folder,
                                                                          tmp_path, capsys):
    before = _digest(bad_folder.iterdir())
    out = tmp_path / "out"
    code = _run(bad_folder, "--calibration", world["cal"], "-o", out, "--json",
                tmp_path / "summary.json")
    cap = capsys.readouterr()
    text = cap.out
    assert code == 1  # something failed
    summary = json.loads((tmp_path / "summary.json").read_text())
    status = {Path(r["input"]).name: r for r in summary["results"]}
    expected_failures = {
        "unreadable.tif": "not a readable TIFF",
        "truncated.tif": "truncated",
        "wrong_shape.tif": "frame shape (16, 48)",
        "wrong_bits.tif": "bit depth 12",
        "plain_no_metadata.tif": "no exposure_ms for this file",
        "no_exposure.tif": "has no 'exposure'",
    }
    for name, reason in expected_failures.items():
        assert status[name]["status"] == "failed", name
        assert reason in status[name]["reason"], (name, status[name]["reason"])
        assert f"{name}: " in text and reason in text
        assert not (out / batch.output_name(name)).exists()
    for name in ("good_a.tif", "good_b.tif", "with_nan.tif"):
        assert status[name]["status"] == "done", status[name]
        assert (out / batch.output_name(name)).exists()
    assert summary["counts"] == {"done": 3, "skipped": 0, "failed": 6}
    assert "3 done, 0 skipped, 6 failed" in text
    # NaN: done, pixels flagged NONFINITE (set to 0 DN), counted in a warning and the provenance
    # (printed with the file's name as it comes, counted by class in the summary)
    assert ("hsiffc correct: warning: with_nan.tif: 3 NaN/inf pixels in 2 frames flagged "
            "NONFINITE") in cap.err
    assert "NonFiniteInputWarning: 1 file (with_nan.tif)" in text
    c = read_corrected(out / "with_nan.corrected.tif")
    assert c.dq[1, 3, 7] & DQ.NONFINITE and c.dq[0, 0, 0] & DQ.NONFINITE
    assert np.isfinite(c.data).all()
    assert c.provenance["frames"]["nonfinite_pixels"] == [1, 2]
    _no_leftovers(out)
    assert _digest(bad_folder.iterdir()) == before  # inputs byte-identical, even the bad ones


def test_nan_fail_policy_fails_the_file(world, bad_folder, tmp_path, capsys):
    code = _run(bad_folder / "with_nan.tif", bad_folder / "good_b.tif", "--calibration",
                world["cal"], "-o", tmp_path, "--nan", "fail")
    assert code == 1
    assert "NaN/inf pixels (--nan fail)" in capsys.readouterr().out
    assert not (tmp_path / "with_nan.corrected.tif").exists()
    assert (tmp_path / "good_b.corrected.tif").exists()


def test_data_above_the_bit_depth_fail_the_file(world, tmp_path):
    cube = _clean(world["sensor"].sweep([10.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=2,
                                        darks=False))
    data = cube.data.copy()
    data[1, 0, 0] = 4000
    doc = {"format": "hsiffc", "exposure": 10.0, "exposure_unit": "ms", "bit_depth": 10,
           "mosaic": cube.mosaic.to_dict()}
    tifffile.imwrite(tmp_path / "over.tif", data, photometric="minisblack", metadata=None,
                     description=json.dumps(doc))
    summary = batch.correct_batch([tmp_path / "over.tif"], tmp_path / "out", world["cal"])
    (res,) = summary.results
    assert res["status"] == "failed" and "exceed the stated bit depth" in res["reason"]
    assert summary.exit_status == 1
    _no_leftovers(tmp_path / "out")


# -- resume, overwrite, never touching inputs --------------------------------------------------

def test_inputs_stay_byte_identical(world, tmp_path):
    before = _digest(world["good"])
    stat = {p: os.stat(p).st_mtime_ns for p in world["good"]}
    assert _run(world["raw"], "--calibration", world["cal"], "-o", tmp_path) == 0
    assert _run(world["raw"], "--calibration", world["cal"], "-o", tmp_path, "--overwrite") == 0
    assert _digest(world["good"]) == before
    assert {p: os.stat(p).st_mtime_ns for p in world["good"]} == stat


def test_rerun_skips_complete_outputs_and_overwrite_redoes_them(world, tmp_path, clean_run):
    out = tmp_path / "out"
    first = batch.correct_batch([world["raw"]], out, world["cal"])
    assert len(first.done) == 5
    inodes = {p: os.stat(p).st_ino for p in out.rglob("*.corrected.tif")}
    again = batch.correct_batch([world["raw"]], out, world["cal"])
    assert len(again.skipped) == 5 and not again.done and again.exit_status == 0
    assert {p: os.stat(p).st_ino for p in out.rglob("*.corrected.tif")} == inodes
    redo = batch.correct_batch([world["raw"]], out, world["cal"], overwrite=True)
    assert len(redo.done) == 5
    assert all(os.stat(p).st_ino != ino for p, ino in inodes.items())  # replaced by rename
    _assert_same(_outputs(out), clean_run[1])


def test_stale_or_damaged_outputs_are_redone(world, tmp_path):
    out = tmp_path / "out"
    src = tmp_path / "cube_0.tif"  # a copy: its modification time changes below
    src.write_bytes(world["good"][0].read_bytes())
    batch.correct_batch([src], out, world["cal"])
    target = out / "cube_0.corrected.tif"
    # other parameters: another job, refused before anything is written; --overwrite redoes
    before = target.read_bytes()
    with pytest.raises(batch.BatchError, match="already written by another job"):
        batch.correct_batch([src], out, world["cal"], threshold_percent=5.0)
    assert target.read_bytes() == before
    res = batch.correct_batch([src], out, world["cal"], threshold_percent=5.0,
                              overwrite=True).results[0]
    assert res["status"] == "done" and res["redone"] is None
    assert read_provenance(target)["pipeline"]["steps"][1]["params"]["threshold_percent"] == 5.0
    # a damaged output under the final name (e.g. cut by a copy tool): redone
    whole = target.read_bytes()
    target.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(DataFormatError):
        read_provenance(target)
    res = batch.correct_batch([src], out, world["cal"], threshold_percent=5.0).results[0]
    assert res["status"] == "done" and "not a complete corrected file" in res["redone"]
    # a newer input (modification time): redone; otherwise skipped
    assert batch.correct_batch([src], out, world["cal"],
                               threshold_percent=5.0).results[0]["status"] == "skipped"
    st = os.stat(src)
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    res = batch.correct_batch([src], out, world["cal"], threshold_percent=5.0).results[0]
    assert res["status"] == "done" and "another version of the input" in res["redone"]


def test_interrupted_run_resumes_to_the_clean_result(world, tmp_path, clean_run, monkeypatch):
    """Ctrl-C (KeyboardInterrupt) in the middle of the third file, then a rerun."""
    out = tmp_path / "out"
    calls = {"n": 0}
    original = Frame.from_raw

    def interrupting(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2 * 4 + 3:  # third frame of the third file
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(Frame, "from_raw", staticmethod(interrupting))
    with pytest.raises(KeyboardInterrupt):
        batch.correct_batch([world["raw"]], out, world["cal"])
    monkeypatch.undo()
    assert sorted(p.name for p in out.rglob("*.corrected.tif")) == ["cube_0.corrected.tif",
                                                                   "cube_1.corrected.tif"]
    _no_leftovers(out)
    resumed = batch.correct_batch([world["raw"]], out, world["cal"])
    assert [r["status"] for r in resumed.results] == ["skipped"] * 2 + ["done"] * 3
    _assert_same(_outputs(out), clean_run[1])


def test_killed_process_leaves_no_partial_output_and_resumes(world, tmp_path, clean_run):
    """SIGKILL a slowed-down run mid-batch; the rerun removes its temporary file and finishes."""
    out = tmp_path / "out"
    slow = (
        "import sys, time\n"
        "from hsiffc.data.frame import Frame\n"
        "orig = Frame.from_raw\n"
        "def slow(*a, **k):\n"
        "    time.sleep(0.15)\n"
        "    return orig(*a, **k)\n"
        "Frame.from_raw = staticmethod(slow)\n"
        "from hsiffc.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n")
    cmd = [sys.executable, "-c", slow, "correct", str(world["raw"]), "--calibration",
           str(world["cal"]), "-o", str(out), "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if len(list(out.rglob("*.corrected.tif"))) >= 2:
                break
            time.sleep(0.02)
        time.sleep(0.2)  # inside the next file
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finished = list(out.rglob("*.corrected.tif"))
    assert 2 <= len(finished) < 5
    assert [p for p in out.rglob("*") if p.name.endswith(".part")]  # killed inside a file
    for p in finished:  # whatever is under a final name is complete
        read_provenance(p)
    assert _run(world["raw"], "--calibration", world["cal"], "-o", out) == 0
    _no_leftovers(out)
    _assert_same(_outputs(out), clean_run[1])


# the first run of the test below: every frame after the first waits until the file named by
# HSIFFC_TEST_GO exists (at most 120 s), so the run holds its folder, with a file started,
# until the test lets it go, however loaded the machine (a fixed delay per frame let a slow
# second process start after the first had finished)
_HELD = (
    "import os, sys, time\n"
    "from pathlib import Path\n"
    "from hsiffc.data.frame import Frame\n"
    "orig = Frame.from_raw\n"
    "go = Path(os.environ['HSIFFC_TEST_GO'])\n"
    "calls = []\n"
    "def held(*a, **k):\n"
    "    end = time.monotonic() + 120\n"
    "    while calls and not go.exists() and time.monotonic() < end:\n"
    "        time.sleep(0.02)\n"
    "    calls.append(1)\n"
    "    return orig(*a, **k)\n"
    "Frame.from_raw = staticmethod(held)\n"
    "from hsiffc.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n")


def test_second_run_on_one_folder_refuses_and_keeps_the_first_runs_files(world, tmp_path,
                                                                          clean_run):
    """Two ``hsiffc correct`` processes on one output folder: the second names the first (pid,
    host, start time) and exits 2 without touching its temporary files; the first finishes."""
    out = tmp_path / "out"
    args = ["correct", str(world["raw"]), "--calibration", str(world["cal"]), "-o", str(out),
            "-q"]
    go = tmp_path / "go"
    first = subprocess.Popen([sys.executable, "-c", _HELD, *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "HSIFFC_TEST_GO": str(go)})
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not list(out.rglob("*.part")):
            time.sleep(0.02)
        parts = list(out.rglob("*.part"))
        assert parts, "the first run never started a file"
        second = subprocess.run([sys.executable, "-m", "hsiffc", *args], capture_output=True,
                                text=True, timeout=120, check=False)
        assert second.returncode == 2, (second.stdout, parts, first.poll())
        err = second.stderr.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err
        assert f"pid {first.pid}" in err and "started" in err and str(out) in err
        assert first.poll() is None  # still running: it held the lock all along
    finally:
        go.touch()
        assert first.wait(timeout=120) == 0, first.stderr.read()
    _no_leftovers(out)
    _assert_same(_outputs(out), clean_run[1])


def test_second_run_can_wait_for_the_first(world, tmp_path):
    out = tmp_path / "out"
    with folder_lock(out), pytest.raises(FolderLockedError, match=f"pid {os.getpid()}"):
        batch.correct_batch([world["good"][0]], out, world["cal"], wait_s=0.3)
    assert batch.correct_batch([world["good"][0]], out, world["cal"],
                               wait_s=5).done  # free again


def test_symlink_at_an_output_name_is_never_written_through(world, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.tif"
    victim.write_bytes(b"precious")
    link = out / "cube_0.corrected.tif"
    link.symlink_to(victim)
    res = batch.correct_batch([world["good"][0]], out, world["cal"]).results[0]
    assert res["status"] == "failed" and "symbolic link" in res["reason"]
    assert victim.read_bytes() == b"precious" and link.is_symlink()
    res = batch.correct_batch([world["good"][0]], out, world["cal"], overwrite=True).results[0]
    assert res["status"] == "done" and not link.is_symlink()
    assert victim.read_bytes() == b"precious"
    read_provenance(link)


def test_a_foreign_file_at_an_output_name_is_kept_without_overwrite(world, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    foreign = out / "cube_0.corrected.tif"
    foreign.write_bytes(b"someone else's file")
    res = batch.correct_batch([world["good"][0]], out, world["cal"]).results[0]
    assert res["status"] == "failed" and "not an output of hsiffc correct" in res["reason"]
    assert foreign.read_bytes() == b"someone else's file"


# -- layout and usage --------------------------------------------------------------------------

def test_refuses_to_write_over_an_input(world, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    victim = out / "cube_0.corrected.tif"
    victim.write_bytes(world["good"][0].read_bytes())  # an input that has an output's name
    before = _digest([victim])
    assert _run(world["good"][0], victim, "--calibration", world["cal"], "-o", out) == 2
    assert "never writes over an input" in capsys.readouterr().err
    assert _digest([victim]) == before


def test_inputs_from_files_folders_and_globs(world, tmp_path, capsys):
    raw = world["raw"]
    jobs, ignored = batch.plan_jobs([raw / "cube_0.tif", str(raw / "**" / "cube_[34].tif"),
                                     raw], tmp_path)
    assert [j.rel for j in jobs] == ["cube_0.tif", "day2/cube_3.tif", "day2/cube_4.tif",
                                     "cube_1.tif", "cube_2.tif"]
    assert jobs[1].output == str((tmp_path / "day2" / "cube_3.corrected.tif").resolve())
    # outputs found by a folder scan are not inputs
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "a.tif").write_bytes(world["good"][0].read_bytes())
    (mixed / "a.corrected.tif").write_bytes(b"x")
    jobs, ignored = batch.plan_jobs([mixed], mixed)
    assert [j.rel for j in jobs] == ["a.tif"] and [p.name for p in ignored] == ["a.corrected.tif"]
    # usage errors: exit status 2 with a message naming the argument
    for args, message in (([tmp_path / "missing.tif"], "no such file or folder"),
                          ([str(tmp_path / "*.tiff")], "matches no TIFF"),
                          ([world["cal"]], "not a TIFF file name")):
        assert _run(*args, "--calibration", world["cal"], "-o", tmp_path / "o") == 2
        assert message in capsys.readouterr().err
    assert _run(raw, "--calibration", tmp_path / "nope.npz", "-o", tmp_path / "o") == 2
    assert "calibration file not found" in capsys.readouterr().err
    jobs, _ = batch.plan_jobs([world["good"][0], world["good"][0].parent / "cube_0.tif"],
                              tmp_path)
    assert len(jobs) == 1  # the same file twice is one job
    (tmp_path / "dup").mkdir()
    (tmp_path / "dup" / "cube_0.tif").write_bytes(world["good"][0].read_bytes())
    with pytest.raises(batch.BatchError, match="both be written"):
        batch.plan_jobs([world["good"][0], tmp_path / "dup" / "cube_0.tif"], tmp_path)


def test_an_unfinished_corrected_file_is_not_valid(tmp_path):
    path = tmp_path / "x.corrected.tif"
    w = CorrectedWriter(path, {}, n_frames=2, frame_shape=(4, 6))
    w.write(np.zeros((4, 6)), np.zeros((4, 6), np.uint32), None)
    w.close()
    with pytest.raises(DataFormatError, match="incomplete"):
        read_provenance(path)
    w = CorrectedWriter(path, {"note": "ok"}, n_frames=1, frame_shape=(4, 6))
    w.write(np.ones((4, 6)), np.zeros((4, 6), np.uint32), None)
    prov = w.finish({"extra": 1})
    c = read_corrected(path)
    assert prov["status"] == "complete" and c.provenance["extra"] == 1
    assert np.isnan(c.alpha).all() and (c.data == 1).all()


# -- parallel and distributed ------------------------------------------------------------------

def test_local_workers_give_identical_outputs(world, tmp_path, clean_run, monkeypatch):
    import hsiffc.batch.workers as planning

    monkeypatch.setattr(planning, "STARTUP_S", 0.0)  # a cluster even for this small input
    bar = Progress()
    summary = batch.correct_batch([world["raw"]], tmp_path, world["cal"], workers=2,
                                  observer=bar)
    assert len(summary.done) == 5 and summary.exit_status == 0
    assert summary.execution["workers"] == min(2, planning.available_cores())
    assert bar._frames == 20 and bar._failed == 0  # the CLI's bar saw every file
    _assert_same(_outputs(tmp_path), clean_run[1])


def test_dask_scheduler_runs_the_same_batch(world, bad_folder, tmp_path, clean_run):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        summary = batch.correct_batch([world["raw"]], tmp_path / "a", world["cal"],
                                      scheduler=cluster.scheduler_address)
        assert len(summary.done) == 5
        bad = batch.correct_batch([bad_folder / "truncated.tif", bad_folder / "good_b.tif"],
                                  tmp_path / "b", world["cal"],
                                  scheduler=cluster.scheduler_address)
    _assert_same(_outputs(tmp_path / "a"), clean_run[1])
    assert [r["status"] for r in bad.results] == ["failed", "done"]
    assert "truncated" in bad.results[0]["reason"] and bad.exit_status == 1


def test_recorded_uniformity_is_eq6_like_for_like(world, clean_run, tmp_path):
    """Before: the input less the dark the pipeline removed; after: the corrected frame; both
    eq. (6) per band over the pixels without a DQ bit in the input nor in the output. With no
    flat field the two are equal."""
    from hsiffc.flatfield.two_point import uniformity_per_band

    out, _ = clean_run
    prov = read_provenance(out / "cube_0.corrected.tif")
    frames = Frame.list_from_sweep(read_sweep(world["good"][0]))
    band = world["sensor"].band_map
    pipe = batch.default_pipeline(world["cal"], threshold_percent=12.0)
    recorded = {key: [[np.nan if v is None else v for v in row] for row in prov["frames"][key]]
                for key in ("uniformity_before", "uniformity_after")}  # None: no good pixel
    for k, frame in enumerate(frames):
        res = pipe.transform(frame)
        dq = frame.dq | res.dq
        before = uniformity_per_band(frame.data - res.dark_removed, band, dq=dq)
        after = uniformity_per_band(res.data, band, dq=dq)
        np.testing.assert_allclose(recorded["uniformity_before"][k], before, rtol=1e-3)
        np.testing.assert_allclose(recorded["uniformity_after"][k], after, rtol=1e-3)
        # not the raw frame with its dark (pedestal and pattern) in it
        raw = uniformity_per_band(frame.data, band, dq=dq)
        assert not np.allclose(recorded["uniformity_before"][k], raw, rtol=1e-3,
                               equal_nan=True)
    none = batch.correct_batch([world["good"][0]], tmp_path, world["cal"], ffc="none")
    res = none.results[0]
    assert res["uniformity_before"] == res["uniformity_after"]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the overflow this test provokes
@pytest.mark.parametrize("ffc", ["none", "model"])
def test_correction_that_gives_nan_is_flagged_never_written_as_nan(world, tmp_path, ffc):
    """An exposure far outside the calibration's range makes the dark model overflow: the
    output holds 0 DN flagged NONFINITE + DO_NOT_USE. Without a flat field the batch's own
    net catches the NaN (and the summary says so); model_ffc flags it itself."""
    cube = read_sweep(world["good"][0])
    odd = tmp_path / "odd.tif"
    write_sweep(odd, replace(cube, meta={}, exposure_ms=np.full(cube.n_frames, 1e300)))
    res = batch.correct_batch([odd], tmp_path / "out", world["cal"], ffc=ffc).results[0]
    assert res["status"] == "done"
    c = read_corrected(tmp_path / "out" / "odd.corrected.tif")
    assert np.isfinite(c.data).all()
    lost = (c.dq & int(DQ.NONFINITE | DQ.DO_NOT_USE)) == int(DQ.NONFINITE | DQ.DO_NOT_USE)
    assert lost.any() and (c.data[lost] == 0).all()
    if ffc == "none":
        assert any("NaN/inf" in w["message"] for w in res["warnings"])
        assert "NonFiniteOutputWarning" in [w["class"] for w in c.provenance["warnings"]]
        assert sum(c.provenance["frames"]["nonfinite_output_pixels"]) == int(lost.sum())


def test_metadata_options_correct_plain_tiffs_and_count_in_the_fingerprint(world, tmp_path):
    """Files without metadata take it from the command line; other values redo the outputs."""
    cube = read_sweep(world["good"][0])
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, cube.data, photometric="minisblack")
    args = [plain, "--calibration", world["cal"], "-o", tmp_path / "out", "-q", "--bit-depth",
            "10"]
    assert _run(*args) == 1  # no exposure: the file fails with the three ways to give it
    assert _run(*args, "--exposure-ms", "10") == 0
    prov = read_provenance(tmp_path / "out" / "plain.corrected.tif")
    assert prov["exposure"] == [10.0] * cube.n_frames
    assert prov["pipeline"]["input_overrides"]["exposure_ms"] == "10.0"
    again = batch.correct_batch([plain], tmp_path / "out", world["cal"],
                                overrides={"exposure_ms": 10.0, "bit_depth": 10})
    assert again.skipped  # same metadata: up to date
    with pytest.raises(batch.BatchError, match="another job"):  # other metadata: another job
        batch.correct_batch([plain], tmp_path / "out", world["cal"],
                            overrides={"exposure_ms": 20.0, "bit_depth": 10})
    other = batch.correct_batch([plain], tmp_path / "out", world["cal"], overwrite=True,
                                overrides={"exposure_ms": 20.0, "bit_depth": 10})
    assert other.done


def test_size_limits_apply_before_any_decode_and_the_batch_carries_on(world, tmp_path,
                                                                       monkeypatch):
    """io's header limits (here lowered through their environment variable) fail the file
    that exceeds them, with the limit's name, and nothing is written for it."""
    big = tmp_path / "big.tif"
    cube = read_sweep(world["good"][0])
    write_sweep(big, replace(cube, meta={}, data=np.tile(cube.data, (1, 2, 1)),
                             mosaic=cube.mosaic))
    monkeypatch.setenv("HSIFFC_MAX_FRAME_PIXELS", str(SHAPE[0] * SHAPE[1]))
    summary = batch.correct_batch([big, world["good"][1]], tmp_path / "out", world["cal"])
    status = {Path(r["input"]).name: r for r in summary.results}
    assert status["big.tif"]["status"] == "failed"
    assert "HSIFFC_MAX_FRAME_PIXELS" in status["big.tif"]["reason"]
    assert status["cube_1.tif"]["status"] == "done" and summary.exit_status == 1
    assert not (tmp_path / "out" / "big.corrected.tif").exists()


# -- ENVI outputs never replaced nor read back as inputs; --json never an output's name

@pytest.fixture(scope="module")
def small_world(tmp_path_factory):
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


def _correct(small_world, inputs, out, *extra):
    return main(["correct", *map(str, inputs), "--calibration", str(small_world["cal"]), "-o",
                 str(out), "--format", "envi", "-q", *extra])


def _envi(out):
    return sorted(p for p in out.rglob("*") if p.suffix in (".hdr", ".img"))


def test_envi_cubes_of_skipped_outputs_are_left_alone_on_a_rerun(small_world, tmp_path, capsys):
    out = tmp_path / "out"
    assert _correct(small_world, [small_world["raw"]], out) == 0
    cubes = _envi(out)
    # 4 frames -> _f0000.._f0003, 1 frame -> no index; each: data + DQ (alpha only with
    # --with-alpha), header + data file; no hsiffc TIFF (not asked for)
    assert len(cubes) == 4 * 4 + 4
    assert any(p.name == "multi.corrected_f0003.dq.img" for p in cubes)
    assert not any("alpha" in p.name for p in cubes)
    assert any(p.name == "single.corrected.hdr" for p in cubes)
    assert not list(out.rglob("*.tif"))
    stamps = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in cubes}
    capsys.readouterr()
    assert _correct(small_world, [small_world["raw"]], out) == 0
    assert "0 done, 2 skipped" in capsys.readouterr().out
    assert {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in cubes} == stamps


def test_envi_cubes_missing_for_a_skipped_output_are_written(small_world, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["correct", str(small_world["raw"]), "--calibration", str(small_world["cal"]), "-o",
                 str(out), "-q"]) == 0
    assert not _envi(out)
    assert _correct(small_world, [small_world["raw"]], out) == 0
    assert len(_envi(out)) == 20
    assert _correct(small_world, [small_world["raw"]], out, "--with-alpha") == 0
    assert len(_envi(out)) == 30  # the alpha planes too


def test_a_file_hsiffc_did_not_write_at_an_envi_name_is_kept(small_world, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "multi.corrected_f0001.hdr"
    mine.write_text("ENVI\ndescription = {my own cube}\n")
    capsys.readouterr()
    assert _correct(small_world, [small_world["raw"]], out) == 1  # that file failed, rest done
    said = capsys.readouterr().out
    assert "multi.corrected_f0001.hdr" in said and "--overwrite" in said
    assert mine.read_text() == "ENVI\ndescription = {my own cube}\n"
    assert (out / "single.corrected.hdr").exists()
    assert _correct(small_world, [small_world["raw"]], out, "--overwrite") == 0
    assert "hsiffc correct: frame 1 of multi.tif" in mine.read_text()


def test_envi_outputs_in_the_input_folder_are_not_read_back(small_world, tmp_path, capsys):
    folder = tmp_path / "data"
    shutil.copytree(small_world["raw"], folder)
    assert _correct(small_world, [folder], folder) == 0
    before = sorted(p.name for p in folder.iterdir())
    capsys.readouterr()
    assert _correct(small_world, [folder], folder) == 0
    printed = capsys.readouterr().out
    assert "2 files: 0 done, 2 skipped, 0 failed" in printed
    assert sorted(p.name for p in folder.iterdir()) == before
    pairs, ignored = discover_inputs([folder])
    assert sorted(p.name for p, _ in pairs) == ["multi.tif", "single.tif"]
    assert all(is_batch_output(p) for p in ignored) and len(ignored) == 5 * 2  # the headers


@pytest.mark.parametrize("name", ["single.corrected.tif", "multi.corrected_f0000.dq.hdr",
                                  ".hsiffc.lock"])
def test_json_may_not_take_the_name_of_an_output(small_world, tmp_path, capsys, name):
    # the summary is written last: it replaced the corrected file the run had just written,
    # or was refused at the end, after the whole batch, on the folder's lock file
    out = tmp_path / "out"
    assert _correct(small_world, [small_world["raw"]], out, "--json", str(out / name)) == 2
    err = capsys.readouterr().err
    assert "give the summary another name" in err and str(out / name) in err
    assert not out.exists()


def test_json_onto_an_input_found_in_a_folder_is_refused_before_the_batch(small_world, tmp_path,
                                                                          capsys):
    # it was refused only when the summary was written, after the whole batch had run
    target = small_world["raw"] / "single.tif"
    before = target.read_bytes()
    out = tmp_path / "out"
    assert _correct(small_world, [small_world["raw"]], out, "--json", str(target), "--overwrite") == 2
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


def test_local_workers_keep_dask_chatter_off_stderr(small_world, tmp_path):
    # distributed sets its loggers to INFO when imported: --workers 2 printed ~30
    # "INFO distributed.scheduler ..." lines on every run
    import subprocess
    import sys

    # a cluster even for this small input (hsiffc.batch.workers would run it in-process)
    code = ("import sys, hsiffc.batch.workers as w; w.STARTUP_S = 0.0; "
            "from hsiffc.cli import main; sys.exit(main(sys.argv[1:]))")
    run = subprocess.run([sys.executable, "-c", code, "correct", str(small_world["raw"]),
                          "--calibration", str(small_world["cal"]), "-o", str(tmp_path / "o"),
                          "--workers", "2", "-q"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "2 files: 2 done" in run.stdout
    assert "INFO" not in run.stderr and "distributed" not in run.stderr, run.stderr


def test_closing_the_local_cluster_keeps_the_nannys_kill_warning_off(caplog):
    # at load 10 the real run printed "WARNING distributed.nanny: Worker process still alive
    # after 4.0 seconds, killing" twice: shutdown of hsiffc's own workers, nothing to act on
    import logging

    from hsiffc.batch.executors import close_quietly

    class Cluster:
        closed = False

        def close(self):
            logging.getLogger("distributed.nanny").warning("Worker process still alive")
            logging.getLogger("distributed.scheduler").warning("a scheduler warning")
            self.closed = True

    cluster = Cluster()
    nanny = logging.getLogger("distributed.nanny")
    level = nanny.level
    with caplog.at_level(logging.WARNING):
        close_quietly(cluster)
    assert cluster.closed
    assert "still alive" not in caplog.text
    assert "a scheduler warning" in caplog.text  # only the nanny's shutdown line is muted
    assert nanny.level == level


def test_summary_times_the_whole_job_and_counts_the_bytes_written(small_world, tmp_path,
                                                                  capsys):
    """The summary and --json: one time for the whole job (the cubes are written inside it),
    the files written and their bytes, per file and in all."""
    out = tmp_path / "out"
    summary = tmp_path / "summary.json"
    assert _correct(small_world, [small_world["raw"]], out, "--json", str(summary)) == 0
    said = capsys.readouterr().out
    doc = json.loads(summary.read_text())
    on_disk = {str(p): p.stat().st_size for p in out.rglob("*") if p.is_file()
               and not p.name.startswith(".")}
    listed = [f for r in doc["results"] for f in r["files"]]
    assert sorted(listed) == sorted(on_disk)
    assert doc["bytes_written"] == sum(on_disk.values()) == sum(
        r["bytes_written"] for r in doc["results"])
    assert doc["seconds"] >= max(r["seconds"] for r in doc["results"])
    assert "corrected and written in" in said and "the whole job" in said
    assert f"{sum(on_disk.values()) / 1e6:.1f} MB written" in said


@pytest.mark.parametrize("value", ["envi,foo", ",", "TIFF;envi"])
def test_an_unknown_format_is_one_line_before_anything_is_written(small_world, tmp_path, capsys,
                                                                  value):
    out = tmp_path / "out"
    assert main(["correct", str(small_world["raw"]), "--calibration", str(small_world["cal"]),
                 "-o", str(out), "--format", value, "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--format must be one or more of" in err
    assert repr(value) in err and not out.exists()
