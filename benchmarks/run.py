"""Run every benchmark: ``python benchmarks/run.py [--quick] [--json FILE] [names...]``.

Each ``bench_*.py`` module's ``main(quick)`` prints its figures and returns them as a dict.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("names", nargs="*", help="benchmarks to run (default: all), e.g. foundation")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and samples")
    ap.add_argument("--json", type=Path, help="write all figures to this JSON file")
    args = ap.parse_args()
    mods = sorted(p.stem for p in HERE.glob("bench_*.py"))
    if args.names:
        mods = [m for m in mods if m.removeprefix("bench_") in args.names]
    print(f"python {platform.python_version()} on {platform.machine()}, "
          f"{__import__('os').cpu_count()} cores")
    out = {}
    for m in mods:
        out[m] = importlib.import_module(m).main(quick=args.quick)
        print()
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
