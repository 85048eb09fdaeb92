"""Output files benchmark: what ``hsiffc correct --format F --cube bilinear`` writes and costs.

Inputs as in the batch benchmark (:mod:`bench_batch`): an hsiffc TIFF of 2048 x 1088 uint16
frames of the simulated 8-band (4 x 2) mosaic sensor, with the simulator's own calibration.
Every job corrects them with the default pipeline into full-resolution bilinear cubes
(H, W, 8) and writes one format, with its default compression ("auto": the DQ plane
compressed, :data:`hsiffc.cubes.stream.DEFAULT_COMPRESSION`) and, for the TIFF formats,
without (``compression=None``).

* **bytes written per cube byte**: the size of every file the job wrote over the float32
  cube's own size (frames x H x W x 8 x 4 bytes). An ENVI-only job holds the cube, a uint16
  DQ plane and headers: the target is at most 1.6.
* **whole job** (:func:`hsiffc.batch.correct_batch`: read, correct, reconstruct, write every
  file, fsync, rename; inputs hashed) against the **read + write bound of the same bytes**
  (baseline, same run, interleaved): ``tifffile`` reads every page of the inputs and the
  bytes that job wrote are written to one new file and fsynced. A compressed job writes fewer
  bytes, so its bound is lower; its ratio says what the compression costs in time.
* **compression's cost on the default job**: ``hsiffc correct`` (default pipeline, mosaic
  frames, the hsiffc TIFF) with its default zstd against the same job uncompressed, in the
  same run (the no-slowdown check of the default command).

Before the jobs, one frame is corrected into every format, so that the kernels are loaded
and every format's libraries imported: a ``hsiffc correct --format netcdf`` process pays once
for importing xarray and its netCDF backend (``write_cube`` of a 272 x 512 x 8 cube: 5.8 s the
first time in a process, 0.3-0.4 s after; one run, load 17). Runs interleaved, medians of 2 (full)
or 1 (--quick) rounds (the default job: 5 or 3, the
first of each round alternating); outputs deleted after each run.
Needs about 1.5 GB (quick: 0.1 GB) of free disk; ``HSIFFC_BENCH_DIR`` chooses the folder.
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import tifffile

from bench_batch import _make_inputs, _timed
from benchutil import figure, row
from hsiffc.batch import correct_batch

FULL = {"shape": (1088, 2048), "frames": 4, "cubes": 1, "repeat": 2}
QUICK = {"shape": (272, 512), "frames": 4, "cubes": 1, "repeat": 1}
BANDS = 8
#: (label, formats, compression) of every job measured
JOBS = [("tiff (auto: zstd DQ)", "tiff", "auto"), ("tiff, uncompressed", "tiff", None),
        ("envi", "envi", "auto"), ("ome (auto: deflate DQ)", "ome", "auto"),
        ("ome, uncompressed", "ome", None), ("netcdf (auto: zlib dq)", "netcdf", "auto")]


def _bound(files, nbytes: int, out: Path) -> None:
    """tifffile reads every input page; ``nbytes`` go to one new file, fsynced."""
    out.mkdir(parents=True, exist_ok=True)
    for f in files:
        with tifffile.TiffFile(f) as tf:
            for page in tf.pages:
                page.asarray()
    block = bytes(1 << 24)
    with open(out / "bound.bin", "wb") as fh:
        left = nbytes
        while left > 0:
            fh.write(block[:min(left, len(block))])
            left -= len(block)
        fh.flush()
        os.fsync(fh.fileno())


def _job(files, out: Path, cal, **options) -> tuple[float, int]:
    """Seconds of one ``correct_batch`` into a fresh ``out`` and the bytes it wrote (its
    summary's ``bytes_written``: every file of every format)."""
    got = {}
    seconds = _timed(lambda: got.update(s=correct_batch(files, out, cal, **options)), out)
    return seconds, got["s"].to_dict()["bytes_written"]


def main(quick: bool = False) -> dict:
    cfg = QUICK if quick else FULL
    h, w = cfg["shape"]
    n_frames = cfg["frames"] * cfg["cubes"]
    cube_bytes = n_frames * h * w * BANDS * 4
    base_dir = os.environ.get("HSIFFC_BENCH_DIR") or tempfile.gettempdir()
    free = shutil.disk_usage(base_dir).free
    if free < 4 * cube_bytes:
        raise SystemExit(f"bench_outputs needs {4 * cube_bytes / 1e9:.1f} GB in {base_dir}; "
                         "set HSIFFC_BENCH_DIR or use --quick")
    print(f"Output files: {n_frames} frames {w} x {h} uint16 -> bilinear cubes {h} x {w} x "
          f"{BANDS} (float32 cube {cube_bytes / 1e6:.0f} MB), one job per format")
    results = {"frame_shape": [h, w], "bands": BANDS, "frames": n_frames,
               "cube_bytes": cube_bytes, "jobs": {}}
    figures = []
    with tempfile.TemporaryDirectory(dir=base_dir, prefix="hsiffc-bench-outputs-") as tmp:
        tmp = Path(tmp)
        (tmp / "in").mkdir()
        files, cal = _make_inputs(tmp / "in", cfg, cfg["cubes"])
        os.sync()
        out = tmp / "out"
        # kernels loaded and every format's libraries imported (xarray and the netCDF backend
        # take seconds to import, once per process): the jobs compare the formats' own costs
        correct_batch(files[:1], out, cal, cube="bilinear", formats=",".join(
            sorted({fmt for _, fmt, _ in JOBS})))
        shutil.rmtree(out)
        for label, fmt, comp in JOBS:
            times = {"job": [], "bound": []}
            written = 0
            for _ in range(cfg["repeat"]):
                seconds, written = _job(files, out, cal, cube="bilinear", formats=fmt,
                                        compression=comp)
                times["job"].append(seconds)
                times["bound"].append(_timed(lambda: _bound(files, written, out), out))
            t_job, t_bound = (statistics.median(times[k]) for k in ("job", "bound"))
            per_byte = written / cube_bytes
            results["jobs"][label] = {"format": fmt, "compression": comp, "bytes": written,
                                      "bytes_per_cube_byte": per_byte, "job_s": t_job,
                                      "bound_s": t_bound, "job_runs_s": times["job"],
                                      "bound_runs_s": times["bound"]}
            print(row(f"{label}: bytes per cube byte", per_byte, "x",
                      f"{written / 1e6:.0f} MB written"))
            print(row(f"{label}: whole job", n_frames / t_job, "frames/s",
                      f"{t_bound / t_job:.2f} of the read + write bound of its bytes "
                      f"({n_frames / t_bound:.2f} frames/s); runs "
                      + ", ".join(f"{t:.1f}" for t in times["job"]) + " s"))
            target = "<= 1.6 (cube + uint16 DQ + headers)" if fmt == "envi" else ""
            figures.append(figure(
                f"--format {label}: bytes written per float32 cube byte", per_byte, "x",
                target=target, met=per_byte <= 1.6 if target else None,
                note=f"{written / 1e6:.0f} MB for a {cube_bytes / 1e6:.0f} MB cube"))
            figures.append(figure(
                f"--format {label} --cube bilinear, whole job", n_frames / t_job, "frames/s",
                baseline=n_frames / t_bound,
                baseline_name="tifffile read + write of the same bytes", ratio=t_bound / t_job,
                note="read, correct, reconstruct, write, fsync, rename"))
        # the default command: mosaic frames to the hsiffc TIFF, zstd DQ against none; the
        # two in turn, the first of each round alternating (a run pays for the page cache the
        # one before it left)
        times = {"zstd": [], "none": []}
        options = {"zstd": {}, "none": {"compression": None}}
        sizes = {}
        for k in range(2 * cfg["repeat"] + 1):
            for name in (("zstd", "none") if k % 2 == 0 else ("none", "zstd")):
                seconds, sizes[name] = _job(files, out, cal, **options[name])
                times[name].append(seconds)
        zstd_bytes, none_bytes = sizes["zstd"], sizes["none"]
        t_z, t_n = statistics.median(times["zstd"]), statistics.median(times["none"])
        results["default_job"] = {"zstd_s": t_z, "none_s": t_n, "zstd_bytes": zstd_bytes,
                                  "none_bytes": none_bytes}
        print(row("default job, hsiffc TIFF zstd vs none", t_n / t_z, "x",
                  f"{n_frames / t_z:.2f} vs {n_frames / t_n:.2f} frames/s; "
                  f"{zstd_bytes / 1e6:.0f} vs {none_bytes / 1e6:.0f} MB"))
        figures.append(figure(
            "hsiffc correct (default: mosaic frames, hsiffc TIFF, zstd DQ)", n_frames / t_z,
            "frames/s", baseline=n_frames / t_n, baseline_name="the same job uncompressed",
            ratio=t_n / t_z, target="no slowdown (ratio >= 0.9, within noise)",
            met=t_n / t_z >= 0.9,
            note=f"{zstd_bytes / none_bytes:.2f} of the uncompressed bytes"))
    results["figures"] = figures
    return results


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
