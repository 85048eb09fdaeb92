"""Functions of the package that take more than 8 parameters (a shape of the code, not a speed).

    python3 benchmarks/param_counts.py [--limit 8] [--top 20] [--base REV]

Counts every named parameter of every ``def`` under ``hsiffc/`` (``*args`` and ``**kwargs``
count as one each; ``self`` and ``cls`` do not), prints the longest signatures and the number
over the limit; with ``--base REV`` also the same count at that git revision (read with
``git show``, nothing checked out), so a change quotes its before and after from one run.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def signatures(sources) -> list[tuple[int, str, str]]:
    """``(parameters, name, where)`` of every function in ``sources`` ((path, text) pairs)."""
    rows = []
    for path, text in sources:
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
                n = len([x for x in names if x not in ("self", "cls")])
                rows.append((n, node.name, f"{path}:{node.lineno}"))
    return sorted(rows, reverse=True)


def _worktree():
    for p in sorted((ROOT / "hsiffc").rglob("*.py")):
        yield str(p.relative_to(ROOT)), p.read_text(encoding="utf-8")


def _revision(rev: str):
    files = subprocess.run(["git", "ls-tree", "-r", "--name-only", rev, "hsiffc"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    for name in sorted(f for f in files if f.endswith(".py")):
        yield name, subprocess.run(["git", "show", f"{rev}:{name}"], cwd=ROOT,
                                   capture_output=True, text=True, check=True).stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=int, default=8)
    ap.add_argument("--top", type=int, default=20)
    ap.add_argument("--base", help="a git revision to count as well (before)")
    args = ap.parse_args()
    now = signatures(_worktree())
    for n, name, where in now[:args.top]:
        print(f"{n:3d}  {name:28s} {where}")
    over = sum(n > args.limit for n, _, _ in now)
    print(f"working tree: {over} functions take more than {args.limit} parameters")
    if args.base:
        before = signatures(_revision(args.base))
        was = sum(n > args.limit for n, _, _ in before)
        print(f"{args.base}: {was} functions take more than {args.limit} parameters")


if __name__ == "__main__":
    main()
