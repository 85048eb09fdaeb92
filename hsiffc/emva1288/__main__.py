"""``python3 -m hsiffc.emva1288 DATA OUTDIR``: hsiffc's EMVA 1288 figures of the shared data sets
beside the reference implementation's, and the full report of the CMOS set.

DATA is the shared data folder (``../shared/data``: the EMVA 1288 sets and
``emva1288-reference-figures.json``). OUTDIR receives ``emva1288_agreement.md`` and
``emva1288_agreement.json`` (every figure of every set beside the reference, with its difference
and tolerance) and the report of ``emva1288-cmos8-roi`` (``emva1288.md``, ``emva1288.json``, the
standard's plots and the leakage figure). Existing files are replaced only with ``--overwrite``.
Exit status 1 when a figure is outside its tolerance, 2 on a bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

CMOS = "emva1288-cmos8-roi"


def main(argv=None) -> int:
    """Parse ``argv``, compare, write the pages, print the table."""
    from ..files.atomic import atomic_write_text, write_policy
    from ..errors import HsiffcError
    from ..io import open_source
    from ..files.jsonsafe import json_safe
    from . import run_characterisation, write_report
    from .agreement import compare_with_reference, render_agreement

    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.emva1288",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("data", help="shared data folder (../shared/data)")
    ap.add_argument("outdir", help="folder for the pages")
    ap.add_argument("--no-leakage", action="store_true",
                    help="skip the leakage calibration of the CMOS set")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier output")
    args = ap.parse_args(argv)
    out = Path(args.outdir)
    try:
        with write_policy(overwrite=args.overwrite, inputs=[args.data]):
            t0 = time.perf_counter()
            cmp = compare_with_reference(args.data)
            t_cmp = time.perf_counter() - t0
            out.mkdir(parents=True, exist_ok=True)
            atomic_write_text(out / "emva1288_agreement.md", render_agreement(cmp))
            atomic_write_text(out / "emva1288_agreement.json",
                              json.dumps(json_safe(cmp), indent=1, allow_nan=False) + "\n")
            files = {}
            if (Path(args.data) / CMOS).exists():
                t0 = time.perf_counter()
                with open_source(Path(args.data) / CMOS) as sweep:  # streamed
                    res, leak, note = run_characterisation(sweep, leakage=not args.no_leakage)
                files = write_report(None, res, out, leak, note)
                t_cmos = time.perf_counter() - t0
    except HsiffcError as exc:
        print(f"emva1288: error: {exc}", file=sys.stderr)
        return 2
    for name, d in cmp["datasets"].items():
        if "missing" in d:
            print(f"{name}: not compared ({d['missing']})")
            continue
        bad = [r["figure"] for r in d["rows"] if not r["agrees"]]
        worst = max((abs(r["difference"]) for r in d["rows"]
                     if r["difference"] is not None and r["kind"] == "rel"), default=0.0)
        print(f"{name}: {len(d['rows']) - len(bad)} of {len(d['rows'])} figures within tolerance"
              f"{' (outside: ' + ', '.join(bad) + ')' if bad else ''}; largest relative "
              f"difference {worst:.2g}")
    print(f"compared in {t_cmp:.1f} s")
    if files:
        print(f"{CMOS} report (read + figures + leakage + plots) in {t_cmos:.1f} s")
    print(f"wrote {out / 'emva1288_agreement.md'}, {out / 'emva1288_agreement.json'}"
          + (", " + ", ".join(sorted(Path(p).name for p in files.values())) if files else ""))
    return 0 if cmp["all_agree"] else 1


if __name__ == "__main__":
    sys.exit(main())
