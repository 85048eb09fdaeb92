"""Benchmarks of two git revisions in one run, alternated: the before and after of a change.

    python3 benchmarks/compare_revisions.py --base REV [--head REV] [--rounds 3] NAMES...

Each revision is checked out into a temporary git worktree (nothing in this checkout is read
or written but its git objects) and runs its *own* ``benchmarks/run.py --quick NAMES`` with
its own package on ``PYTHONPATH``, so a figure is measured by the code of its revision. A first
round of each compiles the numba kernels into that worktree's cache and is not counted; then
the revisions alternate ``--rounds`` times (base, head, base, head, ...), so a change of the
machine's load falls on both. For every figure both revisions report (by name), the medians
and the ratio head / base are printed, with the spread of the rounds (max / min of one
revision's values) as the noise to read the ratio against, and whether head is slower beyond
that noise (figures in s or ms: higher is slower; in a rate: lower is slower; others: not
judged).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TIMES = ("s", "ms")
RATES = ("Mpx/s", "frames/s", "MB/s", "GB/s")


def _worktree(rev: str, where: Path) -> Path:
    path = where / rev.replace("/", "_")
    subprocess.run(["git", "worktree", "add", "--detach", "-q", str(path), rev], cwd=ROOT,
                   check=True)
    return path


def _figures(tree: Path, names, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    subprocess.run([sys.executable, "benchmarks/run.py", "--quick", "--json", str(out), *names],
                   cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
    runs = json.loads(out.read_text())["runs"]
    return {f["name"]: (f["value"], f["unit"]) for res in runs.values() if isinstance(res, dict)
            for f in res.get("figures") or () if f.get("value") is not None}


def verdict(unit: str, ratio: float, noise: float) -> str:
    """'slower', 'faster' or 'same' for a head / base ``ratio`` of a figure in ``unit``,
    against the rounds' spread ``noise`` (>= 1); '' where the unit says no direction."""
    if unit in TIMES:
        slower = ratio
    elif unit in RATES:
        slower = 1.0 / ratio
    else:
        return ""
    if slower > noise:
        return "slower"
    return "faster" if slower < 1.0 / noise else "same"


def compare(base: dict[str, list], head: dict[str, list], units: dict[str, str]) -> list[tuple]:
    """Rows (name, unit, base median, head median, ratio, noise, verdict) for the figures both
    revisions measured."""
    rows = []
    for name in base:
        if name not in head:
            continue
        b, h = statistics.median(base[name]), statistics.median(head[name])
        spread = [max(v) / min(v) for v in (base[name], head[name]) if min(v) > 0]
        noise = max(spread, default=1.0)
        ratio = h / b if b else float("nan")
        rows.append((name, units[name], b, h, ratio, noise, verdict(units[name], ratio, noise)))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="+", help="benchmarks, e.g. pipeline calibration")
    ap.add_argument("--base", required=True, help="the revision before")
    ap.add_argument("--head", default="HEAD", help="the revision after (default HEAD)")
    ap.add_argument("--rounds", type=int, default=3, help="counted rounds of each (default 3)")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="hsiffc-compare-") as tmp:
        tmp = Path(tmp)
        trees = {}
        try:
            for rev in (args.base, args.head):
                trees[rev] = _worktree(rev, tmp)
            values = {rev: {} for rev in trees}
            units = {}
            for i in range(args.rounds + 1):
                for rev, tree in trees.items():
                    figs = _figures(tree, args.names, tmp / f"{i}-{tree.name}.json")
                    print(f"round {i}{' (warm-up, not counted)' if i == 0 else ''}: {rev} done",
                          flush=True)
                    if i == 0:
                        continue
                    for name, (value, unit) in figs.items():
                        values[rev].setdefault(name, []).append(value)
                        units[name] = unit
        finally:
            for tree in trees.values():
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT)
    print(f"\n{args.head} against {args.base}: medians of {args.rounds} alternated rounds of "
          f"benchmarks/run.py --quick {' '.join(args.names)}; load average {load:.1f} at the "
          f"start, {os.getloadavg()[0]:.1f} at the end")
    print(f"{'figure':58s} {'base':>10s} {'head':>10s} {'ratio':>7s} {'noise':>6s}  verdict")
    for name, unit, b, h, ratio, noise, word in compare(values[args.base], values[args.head],
                                                         units):
        print(f"{name[:58]:58s} {b:10.4g} {h:10.4g} {ratio:7.3f} {noise:6.3f}  {word} ({unit})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
