"""EMVA 1288 benchmark: hsiffc against the standard's reference implementation, whole processes
as a user runs them (``python3 benchmarks/run.py emva1288``; ``--quick``: one repeat, a smaller
synthetic set).

Measured in one run, interleaved (one call of each per round, median over the rounds; peak
resident memory of each process from GNU time, see ``_process``; CPU time user + system):

- the reference implementation (``emva1288`` from PyPI, the ``emva-reference`` extra) run as
  its documentation shows (``benchmarks/emva_reference_run.py``): the figures only;
- ``hsiffc emva1288 SET --no-leakage --json OUT``: the figures only, streamed;
- ``hsiffc emva1288 SET --json OUT``: the default, with the leakage account (a joint per-pixel
  calibration on the step means of ``hsiffc.emva1288.LEAKAGE_PIXELS`` pixels drawn at random),
  computed in a child process forked before the frames are read: its CPU time counts (the
  child is waited for), its peak memory is the larger of the two processes' (GNU time);

on the shared CMOS set (``../shared/data/emva1288-cmos8-roi``, 600 frames of 128 x 256 px,
8-bit) and on a seeded synthetic 12-bit linear sensor (``synthetic_set``) of 2048 x 2048 px
with N exposure steps (a light and a dark step of 2 frames each) and a 16-frame light and dark
stack, at N = 50 and at 2N = 100 (``EMVA_BENCH_SIDE`` sets another side, e.g. 1024 for a
shorter run). ``--quick``: 512 x 512, N = 25 and 50, one round. The CMOS set gets a warm-up
round (page cache, numba's cache); the synthetic sets were just written (in the page cache) and
get none. The load average (1 minute) is recorded before and after each set.

Targets (issue 57): figures-only wall at or below the reference's, peak memory at most 1.5 x
the reference's and flat in the number of steps (2N against N), the default with leakage at
most 2 x the figures alone. Flatness is judged on the traced heap's peak (one more run of the
figures-only command per synthetic set under tracemalloc, which counts numpy's buffers): the
resident peak of the same command varies by tens of MB between identical runs at 2048 x 2048
(what glibc's allocator keeps), so its medians are shown beside with the spread of the runs.
Without the reference installed, the baseline is hsiffc's in-memory path (``read_emva1288`` +
``characterise``, every frame held), and the table says so.
Skipped (empty result) when the shared data are absent.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchutil import figure, row

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data" / "emva1288-cmos8-roi"
REFERENCE = HERE / "emva_reference_run.py"
IN_MEMORY = ("import sys\nfrom hsiffc.io import read_emva1288\n"
             "from hsiffc.emva1288 import characterise\n"
             "characterise(read_emva1288(sys.argv[1]))\n")
# the figures-only command in a process that traces its heap (tracemalloc: numpy's buffers
# included) and prints the peak in bytes
TRACED = ("import sys, tracemalloc\ntracemalloc.start()\nfrom hsiffc.cli import main\n"
          "rc = main(['emva1288', sys.argv[1], '--no-leakage', '--json', sys.argv[2], "
          "'--overwrite'])\nprint(tracemalloc.get_traced_memory()[1])\nsys.exit(rc)\n")


def synthetic_set(root: Path, *, shape=(1024, 1024), n_steps=50, stack=16, seed=0) -> Path:
    """Write a seeded EMVA 1288 measurement of a linear 12-bit sensor into ``root``.

    Gain 0.1 DN/e-, QE 0.5, read noise 6 e-, dark 40 DN with a 0.8 DN pattern, PRNU 1 %,
    shot noise as a Gaussian of the electron count's variance, full well at 3900 DN (so the
    variance peaks before the ADC clips); exposures 0.1-10 ms at one irradiance (up to
    1.2 x the full well), a light and a dark step of 2 frames at each, then a ``stack``-frame
    light and dark stack at half the full well; 16-bit PNGs (compression 1), exposure in ns.
    """
    import cv2

    rng = np.random.default_rng(seed)
    h, w = shape
    gain, qe, read_e, fw_dn = 0.1, 0.5, 6.0, 3900.0
    prnu = (1 + 0.01 * rng.standard_normal(shape)).astype(np.float32)
    offset = (40 + 0.8 * rng.standard_normal(shape)).astype(np.float32)
    p_full = 1.2 * (fw_dn - 40) / gain / qe  # photons at the longest exposure
    (root / "images").mkdir(parents=True, exist_ok=True)
    lines = ["v 4.0", f"n 12 {w} {h}"]
    k = 0

    def frames(photons, n):
        nonlocal k
        names = []
        e = qe * photons * prnu
        for _ in range(n):
            noise = rng.standard_normal(shape, dtype=np.float32)
            y = offset + gain * (e + np.sqrt(e + read_e ** 2) * noise)
            y = np.minimum(y, fw_dn + 0.5 * noise)
            img = np.clip(np.rint(y), 0, 4095).astype(np.uint16)
            name = f"images/f{k:05d}.png"
            cv2.imwrite(str(root / name), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            names.append(f"i {name}")
            k += 1
        return names

    for t_ms in np.linspace(0.1, 10.0, n_steps):
        photons = p_full * t_ms / 10.0
        lines += [f"b {t_ms * 1e6:.0f} {photons:.4f}"] + frames(photons, 2)
        lines += [f"d {t_ms * 1e6:.0f}"] + frames(0.0, 2)
    t_ms = 5.0
    lines += [f"b {t_ms * 1e6 + 1:.0f} {p_full / 2.4:.4f}"] + frames(p_full / 2.4, stack)
    lines += [f"d {t_ms * 1e6 + 1:.0f}"] + frames(0.0, stack)
    path = root / "EMVA1288_Data.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


TIME = Path("/usr/bin/time")  # GNU time: the peak memory of the process itself


def _process(cmd) -> dict:
    """Wall (s), CPU (s, user + system) and peak resident memory (MB) of one process.

    The peak is GNU time's (``/usr/bin/time -f %M``): the child of a small process. A child
    of this benchmark's process would report at least this process's resident memory (Linux
    records the parent's peak at ``exec``), about 100 MB here once the synthetic sets are
    written, more than the reference or hsiffc needs on the CMOS set. Without GNU time, the
    ``wait4`` figure with that floor."""
    with tempfile.NamedTemporaryFile("r", suffix=".txt") as tf:
        timed = TIME.is_file()
        argv = [str(TIME), "-f", "%M", "-o", tf.name, *cmd] if timed else list(cmd)
        t0 = time.perf_counter()
        p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        err = p.stderr.read().decode(errors="replace")
        p.stderr.close()
        if status:
            raise RuntimeError(f"{cmd[:3]} failed ({status}): {err[-500:]}")
        rss_kb = int(tf.read().split()[-1]) if timed else ru.ru_maxrss
    return {"wall": wall, "cpu": ru.ru_utime + ru.ru_stime, "rss": rss_kb / 1024}


def _medians(cmds: dict, repeat: int, warmup: int = 1) -> dict:
    """Run ``cmds`` (name -> argv) in turn, ``repeat`` rounds after ``warmup`` warm-up rounds
    (numba's cache, the page cache); median wall, CPU and peak memory per name, and the
    smallest and largest peak (``rss_range``)."""
    for _ in range(warmup):
        for cmd in cmds.values():
            _process(cmd)
    runs = {name: [] for name in cmds}
    for _ in range(repeat):
        for name, cmd in cmds.items():
            runs[name].append(_process(cmd))
    return {name: {**{k: statistics.median(r[k] for r in rs) for k in ("wall", "cpu", "rss")},
                   "rss_range": (min(r["rss"] for r in rs), max(r["rss"] for r in rs))}
            for name, rs in runs.items()}


def _traced_peak(desc: Path, out: Path) -> float:
    """Peak traced heap (MB) of ``hsiffc emva1288 DESC --no-leakage`` in one process: what
    the computation allocates (tracemalloc counts numpy's buffers), without what the C
    allocator keeps around, which makes the resident peak vary by tens of MB from run to run
    at 2048 x 2048 (glibc's arenas and its moving mmap threshold)."""
    run = subprocess.run([sys.executable, "-c", TRACED, str(desc), str(out)],
                         capture_output=True, text=True, check=True)
    return int(run.stdout.split()[-1]) / 2 ** 20


def _reference_available() -> bool:
    return subprocess.run([sys.executable, "-c", "import emva1288"],
                          capture_output=True).returncode == 0


def main(quick: bool = False) -> dict:
    if not (DATA / "EMVA1288_Data.txt").is_file():
        print(f"emva1288: {DATA} not found; skipped")
        return {}
    repeat = 1 if quick else 3
    side = int(os.environ.get("EMVA_BENCH_SIDE", "2048"))
    shape, n = ((512, 512), 25) if quick else ((side, side), 50)
    ref_ok = _reference_available()
    base = "reference implementation (emva1288)" if ref_ok else \
        "hsiffc's in-memory path (reference not installed)"
    env_py = [sys.executable]
    out = {"repeat": repeat, "baseline": base, "sets": {}, "figures": []}
    print(f"emva1288: hsiffc against the {base}; whole processes, median of {repeat}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sets = {"CMOS 8-bit 128 x 256, 600 frames": DATA / "EMVA1288_Data.txt"}
        for steps in (n, 2 * n):
            t0 = time.perf_counter()
            desc = synthetic_set(tmp / f"syn{steps}", shape=shape, n_steps=steps)
            label = (f"synthetic 12-bit {shape[0]} x {shape[1]}, {steps} steps "
                     f"({4 * steps + 32} frames)")
            print(f"  wrote {label} in {time.perf_counter() - t0:.0f} s")
            sets[label] = desc
        for label, desc in sets.items():
            o = tmp / "out.json"
            cmds = {"baseline": env_py + ([str(REFERENCE), str(desc)] if ref_ok else
                                          ["-c", IN_MEMORY, str(desc)]),
                    "figures": env_py + ["-m", "hsiffc", "emva1288", str(desc), "--no-leakage",
                                         "--json", str(o), "--overwrite"],
                    "leakage": env_py + ["-m", "hsiffc", "emva1288", str(desc), "--json",
                                         str(o), "--overwrite"]}
            load0 = os.getloadavg()[0]
            m = _medians(cmds, repeat, warmup=0 if quick or label.startswith("synthetic") else 1)
            load = f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}"
            out["sets"][label] = {**m, "load": load}
            if label.startswith("synthetic"):
                out["sets"][label]["traced_peak_mb"] = _traced_peak(desc, o)
            b, f = m["baseline"], m["figures"]
            print(f"  {label} ({load})")
            print(row("baseline: " + ("reference, figures" if ref_ok else "in-memory"),
                      b["wall"], "s", f"CPU {b['cpu']:.3g} s, peak {b['rss']:.0f} MB"))
            print(row("hsiffc emva1288 --no-leakage --json", f["wall"], "s",
                      f"CPU {f['cpu']:.3g} s, peak {f['rss']:.0f} MB; wall x "
                      f"{f['wall'] / b['wall']:.2f}, memory x {f['rss'] / b['rss']:.2f}"))
            out["figures"].append(figure(
                f"figures-only wall, {label}", f["wall"], "s", baseline=b["wall"],
                baseline_name=base, ratio=f["wall"] / b["wall"], target="<= 1 x baseline",
                met=f["wall"] <= b["wall"],
                note=f"CPU {f['cpu']:.3g} s against {b['cpu']:.3g} s; {load}"))
            out["figures"].append(figure(
                f"figures-only peak memory, {label}", f["rss"], "MB", baseline=b["rss"],
                baseline_name=base, ratio=f["rss"] / b["rss"], target="<= 1.5 x baseline",
                met=f["rss"] <= 1.5 * b["rss"], note=load))
            lk = m["leakage"]  # every set: the default with leakage against the figures alone
            print(row("hsiffc emva1288 --json (default, leakage)", lk["wall"], "s",
                      f"CPU {lk['cpu']:.3g} s, peak {lk['rss']:.0f} MB; x "
                      f"{lk['wall'] / f['wall']:.2f} the figures alone"))
            out["figures"].append(figure(
                f"default with leakage, {label}", lk["wall"], "s", baseline=f["wall"],
                baseline_name="hsiffc figures alone", ratio=lk["wall"] / f["wall"],
                target="<= 2 x figures alone", met=lk["wall"] <= 2 * f["wall"],
                note=f"CPU {lk['cpu']:.3g} s against {f['cpu']:.3g} s (the account's child "
                     f"process included), peak {lk['rss']:.0f} MB (the larger process); {load}"))
        syn = [s for s in out["sets"] if s.startswith("synthetic")]
        r1, r2 = (out["sets"][s]["figures"]["rss"] for s in syn)
        (lo1, hi1), (lo2, hi2) = (out["sets"][s]["figures"]["rss_range"] for s in syn)
        t1, t2 = (out["sets"][s]["traced_peak_mb"] for s in syn)
        b1, b2 = (out["sets"][s]["baseline"]["rss"] for s in syn)
        print(row(f"hsiffc peak memory, {2 * n} steps / {n} steps", r2 / r1, "x",
                  f"resident, medians {r1:.0f} -> {r2:.0f} MB (runs {lo1:.0f}-{hi1:.0f}, "
                  f"{lo2:.0f}-{hi2:.0f} MB)"))
        print(row(f"hsiffc traced heap peak, {2 * n} steps / {n} steps", t2 / t1, "x",
                  f"{t1:.1f} -> {t2:.1f} MB"))
        out["figures"].append(figure(
            "figures-only traced heap peak at 2x the steps", t2, "MB", baseline=t1,
            baseline_name=f"the same at {n} steps", ratio=t2 / t1, target="flat (<= 1.1 x)",
            met=t2 <= 1.1 * t1,
            note="tracemalloc, numpy's buffers included, one run each (the same every run)"))
        out["figures"].append(figure(
            "figures-only peak memory at 2x the steps", r2, "MB", baseline=r1,
            baseline_name=f"the same at {n} steps", ratio=r2 / r1, target="flat (<= 1.1 x)",
            met=r2 <= 1.1 * r1,
            note=f"resident (GNU time), medians; the runs spread {lo1:.0f}-{hi1:.0f} and "
                 f"{lo2:.0f}-{hi2:.0f} MB (the C allocator's retained memory); the baseline: "
                 f"{b1:.0f} -> {b2:.0f} MB ({b2 / b1:.2f} x)"))
    return out


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
