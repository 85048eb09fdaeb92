"""``python3 -m hsiffc.reports.reflectance OUTDIR [--emva FOLDER]``: the reflectance study.

OUTDIR receives ``reflectance_study.md``, ``reflectance_study.json`` and
``reflectance_study.png`` (an existing file is replaced only with ``--overwrite``).
"""

from __future__ import annotations

import argparse
import sys

from ...files.atomic import write_policy
from ...errors import HsiffcError
from . import DEV_SEEDS, EVAL_SEEDS, write_reflectance_study


def main(argv=None) -> int:
    """Parse ``argv``, run the study, print where it went; exit status 2 on a bad output."""
    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.reports.reflectance",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("outdir", help="folder for the study")
    ap.add_argument("--dev", action="store_true",
                    help=f"run the development seeds {DEV_SEEDS} instead of the evaluation "
                         f"seeds {EVAL_SEEDS}")
    ap.add_argument("--emva", action="append", default=[], metavar="FOLDER",
                    help="also a part on this EMVA 1288 light sweep (e.g. "
                         "../shared/data/emva1288-cmos8-roi); may be repeated")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier study")
    args = ap.parse_args(argv)
    try:
        with write_policy(overwrite=args.overwrite, inputs=args.emva):
            paths = write_reflectance_study(args.outdir,
                                            seeds=DEV_SEEDS if args.dev else EVAL_SEEDS,
                                            emva=args.emva)
    except (HsiffcError, OSError) as exc:
        print(f"reflectance study: error: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
