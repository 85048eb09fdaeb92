"""Batch correction benchmark: ``hsiffc correct`` against the I/O bound, and its peak memory.

A batch of 2048 x 1088 cubes of 16 uint16 frames (one simulated cube written with
``write_sweep`` and copied under many names). The calibration is the simulator's own fixed
pattern (responsivity, a, b, dark level, dark current) so no 90 s calibration fit is needed.

* **I/O bound** (baseline, same run): for every input, ``tifffile`` reads each page and writes
  the same output volume as ``hsiffc correct`` (per frame a float32 plane, a uint32 plane and a
  float32 plane, 12 bytes per pixel) to a new TIFF, then ``fsync`` (durable, as the engine's
  atomic write is). Median of runs interleaved with the engine's (3; 2 with --quick), after
  the freshly written inputs were flushed to disk (os.sync).
* **engine, one worker**: :func:`hsiffc.batch.correct_batch` in this process, inputs hashed
  (sha256 in the provenance), with the default pipeline (dark from the calibration + alpha
  mask at 12 % + model_ffc) and with a dark-only pipeline (``--pipeline``: the engine's own
  cost: reading, frames, provenance, statistics, atomic writes).
* **engine, two workers**: the default pipeline on a local Dask cluster (2 processes).
* **where the time goes**: the default and dark-only pipelines alone on one frame.
* **peak memory**: the engine with the default pipeline in a fresh subprocess per batch size
  (10 and 40 cubes): peak traced heap (tracemalloc, numpy arrays included) and peak RSS.

Needs about 3.2 GB (quick: 0.1 GB) of disk for the inputs plus 0.43 GB per cube of output while
a batch runs (outputs are deleted after each run); ``HSIFFC_BENCH_DIR`` chooses the folder.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import tifffile

from benchutil import figure, median_time, row
from hsiffc.batch import correct_batch, default_pipeline
from hsiffc.calibrate.product import Calibration
from hsiffc.data.frame import Frame
from hsiffc.io import read_sweep, write_sweep
from hsiffc.batch.memory import reuse_freed_memory
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline

FULL = {"shape": (1088, 2048), "frames": 16, "throughput_cubes": 10, "memory_cubes": (10, 40),
        "repeat": 3}
QUICK = {"shape": (272, 512), "frames": 8, "throughput_cubes": 4, "memory_cubes": (3, 12),
         "repeat": 2}

_MEMORY_CHILD = r"""
import json, resource, sys, time, tracemalloc
from pathlib import Path
from hsiffc.batch import correct_batch
files, out, cal = json.loads(sys.argv[1])
tracemalloc.start()
t0 = time.perf_counter()
summary = correct_batch(files, out, cal)
seconds = time.perf_counter() - t0
peak = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
print(json.dumps({"seconds": seconds, "traced_peak_mb": peak / 2 ** 20,
                  "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "done": len(summary.done), "frames": sum(r["frames"] for r in summary.done)}))
"""


def _make_inputs(folder: Path, cfg: dict, n_cubes: int) -> tuple[list[Path], Path]:
    shape, n = cfg["shape"], cfg["frames"]
    sensor = MosaicSensor(shape, seed=0)
    exposures = np.linspace(8.0, 32.0, 4)
    sweep = sensor.sweep(exposures, "lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2["training"] * 0.8,
                         n_frames=n // len(exposures), darks=False, seed=1)
    first = folder / "cube_000.tif"
    write_sweep(first, replace(sweep, meta={}))
    files = [first]
    for i in range(1, n_cubes):
        files.append(folder / f"cube_{i:03d}.tif")
        shutil.copyfile(first, files[-1])
    # responsivity: the light rate (DN/ms) at relative rate 1 = the benchmark's own light, which
    # model_ffc (the default pipeline's flat field) needs
    k = sensor.light_rate("lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2["training"] * 0.8)
    arrays = {"a_dn_per_ms": sensor.a_dn_per_ms, "b_per_dn": sensor.b_per_dn,
              "dark_dn": sensor.dark_dn, "dark_current_dn_per_ms": sensor.dark_current,
              "responsivity": k}
    cal = Calibration(arrays={k: np.asarray(v, np.float32) for k, v in arrays.items()},
                      domain={"exposure_ms": [1.0, 40.0], "light_rate": [0.0, 1.0],
                              "light_rate_unit": "relative", "bit_depth": 10,
                              "frame_shape": list(shape), "mosaic": sensor.mosaic.to_dict(),
                              "full_scale_dn": 1023},
                      method="joint", fitted_on={"source": "simulator truth (benchmark)"})
    cal_path = folder / "calibration.npz"
    cal.save(cal_path)
    return files, cal_path


def _baseline(files, out: Path) -> None:
    """tifffile alone: read every page, write the same volume (3 planes), fsync."""
    out.mkdir(parents=True, exist_ok=True)
    for f in files:
        with tifffile.TiffFile(f) as tf, open(out / f.name, "wb") as fh:
            with tifffile.TiffWriter(fh) as tw:
                for page in tf.pages:
                    data = page.asarray().astype(np.float32)
                    rows = data.shape[0]
                    tw.write(data, photometric="minisblack", metadata=None, rowsperstrip=rows)
                    tw.write(np.zeros(data.shape, np.uint32), photometric="minisblack",
                             metadata=None, rowsperstrip=rows)
                    tw.write(data, photometric="minisblack", metadata=None,
                             rowsperstrip=max(1, (rows + 1) // 2))
            fh.flush()
            os.fsync(fh.fileno())


def _timed(fn, out: Path) -> float:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    fn()
    seconds = time.perf_counter() - t0
    shutil.rmtree(out, ignore_errors=True)
    return seconds


def main(quick: bool = False) -> dict:
    cfg = QUICK if quick else FULL
    h, w = cfg["shape"]
    n_max = max(cfg["memory_cubes"] + (cfg["throughput_cubes"],))
    cube_mb = cfg["frames"] * h * w * 2 / 1e6
    base_dir = os.environ.get("HSIFFC_BENCH_DIR") or tempfile.gettempdir()
    need = n_max * cube_mb * 1.1 + n_max * cube_mb * 6.2
    free = shutil.disk_usage(base_dir).free / 1e6
    if free < need:
        raise SystemExit(f"bench_batch needs {need / 1e3:.1f} GB in {base_dir}, only "
                         f"{free / 1e3:.1f} GB free; set HSIFFC_BENCH_DIR or use --quick")
    # hsiffc correct sets the allocator so that a frame's arrays reuse freed memory
    # (hsiffc.batch.memory); set here first, the I/O bound and the engine run in the same state
    results = {"frame_shape": [h, w], "frames_per_cube": cfg["frames"],
               "allocator_reuses_freed_memory": reuse_freed_memory()}
    print(f"Batch correction: cubes of {cfg['frames']} x {w} x {h} uint16 ({cube_mb:.1f} MB in, "
          f"{cube_mb * 6:.0f} MB out each)")
    with tempfile.TemporaryDirectory(dir=base_dir, prefix="hsiffc-bench-batch-") as tmp:
        tmp = Path(tmp)
        (tmp / "in").mkdir()
        t0 = time.perf_counter()
        files, cal_path = _make_inputs(tmp / "in", cfg, n_max)
        print(row("simulate + write the inputs", time.perf_counter() - t0, "s",
                  f"{n_max} cubes"))
        # the inputs reach the disk before any timing: otherwise the first runs (baseline and
        # engine alike) share the disk with the write-back of the GBs just written
        os.sync()
        batch = files[:cfg["throughput_cubes"]]
        n_frames = len(batch) * cfg["frames"]
        dark_only = Pipeline(default_pipeline(cal_path).steps[:1])
        dark_only.save(tmp / "dark_only.npz")
        out = tmp / "out"
        # warm-up: the first call in a process compiles the kernels (or loads them from numba's
        # disk cache); that one-off cost is reported, not timed with the batches
        frame0 = Frame.list_from_sweep(read_sweep(files[0]))[0]
        t0 = time.perf_counter()
        default_pipeline(cal_path).transform(frame0)
        results["first_call_s"] = time.perf_counter() - t0
        print(row("first call of the default pipeline in this process", results["first_call_s"],
                  "s", "compile, or load from numba's disk cache"))
        runs = {"baseline": [], "default": [], "dark_only": []}
        for _ in range(cfg["repeat"]):
            runs["baseline"].append(_timed(lambda: _baseline(batch, out), out))
            runs["default"].append(_timed(lambda: correct_batch(batch, out, cal_path), out))
            runs["dark_only"].append(_timed(lambda: correct_batch(
                batch, out, cal_path, pipeline=tmp / "dark_only.npz"), out))
        runs["default_2_workers"] = [_timed(lambda: correct_batch(batch, out, cal_path,
                                                                  workers=2), out)]
        t_base = statistics.median(runs["baseline"])
        results["baseline_frames_s"] = n_frames / t_base
        results["baseline_mb_s_in"] = len(batch) * cube_mb / t_base
        print(row(f"I/O bound: tifffile read + write, {len(batch)} cubes",
                  results["baseline_frames_s"], "frames/s",
                  f"{results['baseline_mb_s_in']:.0f} MB/s in, "
                  f"{results['baseline_mb_s_in'] * 6:.0f} MB/s out; runs "
                  + ", ".join(f"{t:.1f}" for t in runs["baseline"]) + " s"))
        for key, label in (("default", "hsiffc correct, 1 worker, default pipeline"),
                           ("dark_only", "hsiffc correct, 1 worker, dark-only pipeline"),
                           ("default_2_workers", "hsiffc correct, 2 workers, default pipeline")):
            t = statistics.median(runs[key])
            results[f"{key}_frames_s"] = n_frames / t
            results[f"{key}_ratio_to_io_bound"] = t_base / t
            print(row(label, n_frames / t, "frames/s",
                      f"{t_base / t:.2f} of the I/O bound; runs "
                      + ", ".join(f"{x:.1f}" for x in runs[key]) + " s"))
        # where the time goes: the pipeline alone on one frame, against the I/O bound per frame
        frame = Frame.list_from_sweep(read_sweep(files[0]))[-1]
        pipe = default_pipeline(cal_path)
        for key, p in (("default", pipe), ("dark_only", dark_only)):
            ms = median_time(lambda p=p: p.transform(frame), repeat=5) * 1e3
            results[f"{key}_pipeline_ms_per_frame"] = ms
            print(row(f"pipeline alone ({key.replace('_', '-')}), one frame", ms, "ms",
                      f"I/O bound {1e3 / results['baseline_frames_s']:.0f} ms/frame"))
        def decode():
            with tifffile.TiffFile(files[0]) as tf:
                for page in tf.pages:
                    page.asarray()

        ms = median_time(decode, repeat=3) * 1e3 / cfg["frames"]
        results["decode_ms_per_frame"] = ms
        print(row("decode alone (tifffile), one frame", ms, "ms",
                  "read ahead on its own thread by hsiffc correct"))
        for n in cfg["memory_cubes"]:
            arg = json.dumps([[str(f) for f in files[:n]], str(out), str(cal_path)])
            proc = subprocess.run([sys.executable, "-c", _MEMORY_CHILD, arg], check=True,
                                  capture_output=True, text=True,
                                  env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
            shutil.rmtree(out, ignore_errors=True)
            mem = json.loads(proc.stdout.strip().splitlines()[-1])
            results[f"peak_traced_mb_{n}_cubes"] = mem["traced_peak_mb"]
            results[f"peak_rss_mb_{n}_cubes"] = mem["maxrss_mb"]
            results[f"frames_s_{n}_cubes_traced"] = mem["frames"] / mem["seconds"]
            print(row(f"peak memory, {n} cubes (default pipeline)", mem["traced_peak_mb"], "MiB",
                      f"traced heap; peak RSS {mem['maxrss_mb']:.0f} MiB; "
                      f"{mem['frames'] / mem['seconds']:.1f} frames/s under tracemalloc"))
        a, b = cfg["memory_cubes"]
        results["peak_traced_growth"] = (results[f"peak_traced_mb_{b}_cubes"]
                                         / results[f"peak_traced_mb_{a}_cubes"])
        results["peak_rss_growth"] = (results[f"peak_rss_mb_{b}_cubes"]
                                      / results[f"peak_rss_mb_{a}_cubes"])
        print(row(f"peak memory {b} / {a} cubes", results["peak_traced_growth"], "x",
                  f"traced; RSS {results['peak_rss_growth']:.2f} x (1.0 = does not grow)"))
    ratio = results["default_ratio_to_io_bound"]
    where = (f"per frame: pipeline {results['default_pipeline_ms_per_frame']:.0f} ms, decode "
             f"{results['decode_ms_per_frame']:.0f} ms, I/O bound "
             f"{1e3 / results['baseline_frames_s']:.0f} ms (read + write + fsync)")
    results["figures"] = [
        figure("hsiffc correct, default pipeline, 1 worker", results["default_frames_s"],
               "frames/s", baseline=results["baseline_frames_s"],
               baseline_name="tifffile read + write of the same volume", ratio=ratio,
               target=">= 0.7 of the I/O bound", met=ratio >= 0.7, note=where),
        figure(f"peak memory, {b} vs {a} cubes", results[f"peak_traced_mb_{b}_cubes"], "MiB",
               baseline=results[f"peak_traced_mb_{a}_cubes"], baseline_name=f"{a} cubes",
               ratio=results["peak_traced_growth"], target="flat (ratio ~1)",
               met=results["peak_traced_growth"] < 1.2,
               note=f"traced heap; peak RSS {results[f'peak_rss_mb_{a}_cubes']:.0f} -> "
                    f"{results[f'peak_rss_mb_{b}_cubes']:.0f} MiB"),
    ]
    return results


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
