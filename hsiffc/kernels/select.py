"""Medians of several sample sets in parallel (the band medians of a reconstruction).

numpy's ``partition`` holds the GIL, so with it the band medians of a frame are taken one
band after another, a serial part that bounds how far the bilinear pipeline scales with
threads on a many-core machine. This kernel takes
every set's median in its own thread (numba's ``np.partition`` of a copy), with the value of
:func:`hsiffc.reconstruct.prepare.median_in_place`: the middle element, or for an even count
the float32 mean of the two middle ones (``(lo + hi) / 2`` rounded to float32).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import cached_jit

__all__ = ["medians_of"]


@cached_jit(parallel=True)
def _medians(samples, counts, out):
    for i in prange(counts.shape[0]):
        n = counts[i]
        if n == 0:
            out[i] = 0.0
            continue
        k = n // 2
        part = np.partition(samples[i, :n].copy(), k)
        if n % 2:
            out[i] = np.float64(part[k])
        else:
            lo = part[:k].max()
            out[i] = np.float64(np.float32(np.float32(lo + part[k]) / np.float32(2.0)))


def medians_of(samples: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Median of ``samples[i, :counts[i]]`` for every row ``i`` (float32 samples; 0 for an
    empty row), as float64, all rows in parallel."""
    out = np.empty(len(counts), np.float64)
    _medians(np.ascontiguousarray(samples, np.float32), np.asarray(counts, np.int64), out)
    return out
