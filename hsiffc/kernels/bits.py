"""DQ planes merged in parallel: ``dst |= a | b`` over whole frames.

numpy's in-place ``|=`` runs on one thread: a serial part of every frame of the model FFC
stage that keeps the default correction from scaling with threads.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import Kernel

__all__ = ["or_into"]


def _or_loop(dst, a, b):
    for i in prange(dst.shape[0]):
        dst[i] |= a[i] | b[i]


_or_kernel = Kernel(_or_loop, 0, parallel_min=1 << 18)


def or_into(dst: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``dst |= a | b`` in place (three uint32 planes of one shape; ``dst`` C-contiguous)."""
    if not (dst.shape == np.shape(a) == np.shape(b)) or not dst.flags.c_contiguous:
        dst |= a
        dst |= b
        return dst
    _or_kernel(dst.reshape(-1), np.ascontiguousarray(a, dst.dtype).reshape(-1),
               np.ascontiguousarray(b, dst.dtype).reshape(-1))
    return dst
