"""Cube outputs benchmark: ``hsiffc correct --cube bilinear`` against the read + write bound.

Inputs as in the batch benchmark (:mod:`bench_batch`): hsiffc TIFFs of 2048 x 1088 uint16
frames of the simulated 8-band (4 x 2) mosaic sensor, with the simulator's own calibration.

* **I/O bound** (baseline, same run): for every input, ``tifffile`` reads each page and writes
  the bytes ``hsiffc correct --cube bilinear`` writes for it (per frame an (H, W, 8) float32
  data page, a uint32 DQ page and a float32 alpha page: 96 bytes per pixel), then ``fsync``.
* **engine**: :func:`hsiffc.batch.correct_batch` in this process with the default pipeline
  (dark + alpha mask + model_ffc from the calibration) and ``cube="bilinear"``: full-resolution
  cubes with DQ and alpha, inputs hashed, written atomically.
* Runs interleaved (baseline, engine; 3 rounds, 2 with --quick), medians; outputs deleted
  after each run. The target (issue 39): the engine at >= 0.7 of the I/O bound.

Measured (``python3 benchmarks/bench_cubes.py``, 2026-11-26 04:33-04:42 UTC, this 2-core
machine shared with other jobs at load 13-17): I/O bound 0.311 frames/s (67 MB/s written; runs
51.4, 53.6, 30.5 s), engine 0.343 frames/s (runs 49.8, 45.6, 46.6 s): 1.10 of the I/O bound
(target >= 0.7: met); pipeline + bilinear cube alone 2.65 s/frame on that loaded machine.

Needs about 0.2 GB of input and 3.5 GB (quick: 0.2 GB) of free disk per run;
``HSIFFC_BENCH_DIR`` chooses the folder.
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from bench_batch import _make_inputs, _timed
from benchutil import figure, median_time, row
from hsiffc.batch import correct_batch, default_pipeline
from hsiffc.data.frame import Frame
from hsiffc.io import read_sweep
from hsiffc.batch.memory import reuse_freed_memory
from hsiffc.stages import create

FULL = {"shape": (1088, 2048), "frames": 8, "cubes": 2, "repeat": 3}
QUICK = {"shape": (272, 512), "frames": 4, "cubes": 2, "repeat": 2}
BANDS = 8


def _baseline(files, out: Path) -> None:
    """tifffile alone: read every page, write the cube volume (3 planes of H x W x 8), fsync."""
    out.mkdir(parents=True, exist_ok=True)
    for f in files:
        with tifffile.TiffFile(f) as tf, open(out / f.name, "wb") as fh:
            with tifffile.TiffWriter(fh, bigtiff=True) as tw:
                for page in tf.pages:
                    frame = page.asarray()
                    h, w = frame.shape
                    cube = np.empty((h, w, BANDS), np.float32)
                    cube[...] = frame[:, :, None]  # the bytes, not a computation
                    for plane in (cube, cube.view(np.uint32), cube):
                        tw.write(plane, photometric="minisblack", planarconfig="contig",
                                 metadata=None, rowsperstrip=h)
            fh.flush()
            os.fsync(fh.fileno())


def main(quick: bool = False) -> dict:
    cfg = QUICK if quick else FULL
    h, w = cfg["shape"]
    n_frames = cfg["frames"] * cfg["cubes"]
    out_mb = n_frames * h * w * BANDS * 12 / 1e6
    base_dir = os.environ.get("HSIFFC_BENCH_DIR") or tempfile.gettempdir()
    free = shutil.disk_usage(base_dir).free / 1e6
    if free < out_mb * 1.5:
        raise SystemExit(f"bench_cubes needs {out_mb * 1.5 / 1e3:.1f} GB in {base_dir}, only "
                         f"{free / 1e3:.1f} GB free; set HSIFFC_BENCH_DIR or use --quick")
    results = {"frame_shape": [h, w], "bands": BANDS, "frames": n_frames,
               "allocator_reuses_freed_memory": reuse_freed_memory()}
    print(f"Cube outputs: {cfg['cubes']} inputs of {cfg['frames']} x {w} x {h} uint16 -> "
          f"bilinear cubes {h} x {w} x {BANDS} with DQ and alpha ({out_mb:.0f} MB written)")
    with tempfile.TemporaryDirectory(dir=base_dir, prefix="hsiffc-bench-cubes-") as tmp:
        tmp = Path(tmp)
        (tmp / "in").mkdir()
        files, cal_path = _make_inputs(tmp / "in", cfg, cfg["cubes"])
        os.sync()
        out = tmp / "out"
        frame = Frame.list_from_sweep(read_sweep(files[0]))[-1]
        pipe = default_pipeline(cal_path)
        cube_step = create("reconstruct", method="bilinear").fit([])
        t0 = time.perf_counter()
        cube_step.transform(pipe.transform(frame))
        print(row("first call (compile or load the kernels)", time.perf_counter() - t0, "s"))
        runs = {"baseline": [], "engine": []}
        for _ in range(cfg["repeat"]):
            runs["baseline"].append(_timed(lambda: _baseline(files, out), out))
            runs["engine"].append(_timed(lambda: correct_batch(files, out, cal_path,
                                                               cube="bilinear"), out))
        t_base, t_eng = statistics.median(runs["baseline"]), statistics.median(runs["engine"])
        ratio = t_base / t_eng
        results.update(baseline_frames_s=n_frames / t_base, engine_frames_s=n_frames / t_eng,
                       ratio_to_io_bound=ratio, baseline_runs_s=runs["baseline"],
                       engine_runs_s=runs["engine"],
                       baseline_mb_s_out=out_mb / t_base, engine_mb_s_out=out_mb / t_eng)
        print(row("I/O bound: tifffile read + write of the cube bytes", n_frames / t_base,
                  "frames/s", f"{out_mb / t_base:.0f} MB/s out; runs "
                  + ", ".join(f"{t:.1f}" for t in runs["baseline"]) + " s"))
        print(row("hsiffc correct --cube bilinear, default pipeline", n_frames / t_eng,
                  "frames/s", f"{ratio:.2f} of the I/O bound; runs "
                  + ", ".join(f"{t:.1f}" for t in runs["engine"]) + " s"))
        ms = median_time(lambda: cube_step.transform(pipe.transform(frame)), repeat=3) * 1e3
        results["pipeline_ms_per_frame"] = ms
        print(row("pipeline + bilinear cube alone, one frame", ms, "ms",
                  f"I/O bound {1e3 * t_base / n_frames:.0f} ms/frame"))
    results["figures"] = [
        figure("hsiffc correct --cube bilinear, 1 worker", results["engine_frames_s"],
               "frames/s", baseline=results["baseline_frames_s"],
               baseline_name="tifffile read + write of the same bytes", ratio=ratio,
               target=">= 0.7 of the I/O bound", met=ratio >= 0.7,
               note=f"{w} x {h} x {BANDS} cubes with DQ and alpha; pipeline + cube "
                    f"{results['pipeline_ms_per_frame']:.0f} ms/frame, I/O bound "
                    f"{1e3 / results['baseline_frames_s']:.0f} ms/frame"),
    ]
    return results


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
