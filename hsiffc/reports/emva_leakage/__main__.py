"""``python3 -m hsiffc.reports.emva_leakage SWEEP OUTDIR``: the report from the command line.

SWEEP is an EMVA 1288 descriptor or folder; OUTDIR receives ``emva_leakage.json``,
``emva_leakage.md`` and ``emva_leakage_pixels.png`` (an existing file is replaced only with
``--overwrite``).
"""

from __future__ import annotations

import argparse
import sys

from ...files.atomic import write_policy
from ...errors import HsiffcError
from ...io import read_emva1288
from . import sweep_steps_only, write_emva_leakage_report


def main(argv=None) -> int:
    """Parse ``argv``, run the report, print where it went; exit status 2 on a bad input."""
    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.reports.emva_leakage",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("sweep", help="EMVA 1288 descriptor or folder")
    ap.add_argument("outdir", help="folder for the report")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier report")
    args = ap.parse_args(argv)
    try:
        with write_policy(overwrite=args.overwrite, inputs=[args.sweep]):
            res = write_emva_leakage_report(sweep_steps_only(read_emva1288(args.sweep)),
                                            args.outdir)
    except (HsiffcError, OSError) as exc:
        print(f"emva_leakage: error: {exc}", file=sys.stderr)
        return 2
    for path in res["files"].values():
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
