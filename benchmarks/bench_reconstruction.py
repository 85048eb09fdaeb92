"""Demosaicking speed: hsiffc's best method (``ppid_edge``) against today's ``ppid``.

``python3 benchmarks/run.py reconstruction``. On a 2048 x 1088 frame with 0.1 % flagged
samples, each method's :func:`hsiffc.reconstruct.demosaic` (cube and DQ) on the 8-band 4 x 2
layout of the pipeline benchmark, the 4 x 4 and the 5 x 5 layouts, the calls interleaved (a
figure and its baseline see the same state of a shared machine), medians; the process keeps
freed memory for reuse as ``hsiffc correct`` does (:mod:`hsiffc.batch.memory`). Target (issue
55): ``ppid_edge`` at >= 30 Mpx/s on 2 cores on the 8-band layout. Its accuracy is on the
reconstruction results page (``python3 docs/gen/results.py recon``).
"""

from __future__ import annotations

import numpy as np
from benchutil import figure, interleaved_medians, row

from hsiffc.batch.memory import reuse_freed_memory
from hsiffc.data.dq import DQ
from hsiffc.data.mosaic import Mosaic
from hsiffc.reconstruct import demosaic

METHODS = ("ppid", "ppid_edge", "ppid_paper", "bilinear")


def main(quick: bool = False) -> dict:
    reuse_freed_memory()
    rng = np.random.default_rng(0)
    shape = (1088, 2048)
    raw = rng.uniform(20, 900, shape).astype(np.float32)
    dq = np.where(rng.random(shape) < 1e-3, np.uint32(DQ.DEAD), np.uint32(0))
    npx = raw.size
    repeat = 2 if quick else 5
    results = {"figures": []}
    print(f"demosaicking, 2048 x 1088 frame, 0.1 % flagged, medians of {repeat} "
          "(interleaved)")
    for mosaic in (Mosaic.rectangular(2, 4), Mosaic.square(4), Mosaic.square(5)):
        fns = {m: (lambda m=m, mo=mosaic: demosaic(raw, mo, method=m, dq=dq)) for m in METHODS}
        t = interleaved_medians(fns, repeat=repeat)
        speed = {m: npx / t[m] / 1e6 for m in METHODS}
        results[mosaic.name] = speed
        for m in METHODS:
            print(row(f"{mosaic.name} ({mosaic.n_bands} bands): {m}", speed[m], "Mpx/s",
                      f"{t[m] * 1e3:.0f} ms"))
        main8 = mosaic.n_bands == 8
        results["figures"].append(figure(
            f"ppid_edge cube, {mosaic.n_bands} bands ({mosaic.name})", speed["ppid_edge"],
            "Mpx/s", baseline=speed["ppid"], baseline_name="ppid, same frame",
            ratio=t["ppid"] / t["ppid_edge"], target=">= 30 Mpx/s" if main8 else "",
            met=(speed["ppid_edge"] >= 30) if main8 else None,
            note="demosaic() alone (cube + DQ), 0.1 % flagged samples; ratio = ppid time / "
                 "ppid_edge time"))
    return results


if __name__ == "__main__":
    main()
