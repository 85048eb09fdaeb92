"""Per-step statistics of a sweep's frames (numba): the step means each pixel's calibration fit
sees, and the two-frame temporal variance of the photon transfer (EMVA 1288).

:func:`hsiffc.calibrate.samples.collect_samples` and
:func:`hsiffc.calibrate.samples.photon_transfer` run them.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import cached_jit

__all__ = ["pair_stats", "step_means"]


@cached_jit(parallel=True)
def step_means(data, sel, nsel, r0, r1, fs, floor, means, clipped):
    """Per step s, the mean (in the dtype of ``means``) over its frames ``sel[s, :nsel[s]]`` of
    rows ``r0:r1`` of ``data`` (N, H, W), and whether any of them is at or above ``fs`` or at
    or below ``floor``; outputs (S, P)."""
    w = data.shape[2]
    for rr in prange(r1 - r0):
        r = r0 + rr
        for s in range(sel.shape[0]):
            inv = 1.0 / nsel[s]
            for c in range(w):
                acc = 0.0
                clip = False
                for j in range(nsel[s]):
                    v = np.float64(data[sel[s, j], r, c])
                    acc += v
                    clip |= (v >= fs) | (v <= floor)
                means[s, rr * w + c] = acc * inv
                clipped[s, rr * w + c] = clip


@cached_jit(parallel=True)
def pair_stats(f0, f1, fs):
    """(pixels below ``fs`` in both frames, their mean level, half their mean squared
    frame-to-frame difference) of two frames (H, W): the EMVA 1288 temporal variance."""
    h, w = f0.shape
    n = np.zeros(h)
    sm = np.zeros(h)
    sv = np.zeros(h)
    for r in prange(h):
        # sums in locals, stored once per row (threads writing neighbouring elements of n,
        # sm, sv pixel by pixel share their cache lines)
        nr = smr = svr = 0.0
        for c in range(w):
            a = np.float64(f0[r, c])
            b = np.float64(f1[r, c])
            if a < fs and b < fs:
                nr += 1.0
                smr += 0.5 * (a + b)
                svr += (a - b) * (a - b)
        n[r] = nr
        sm[r] = smr
        sv[r] = svr
    total = n.sum()
    if total == 0:
        return 0.0, np.nan, np.nan
    return total, sm.sum() / total, 0.5 * sv.sum() / total
