"""DQ planes merged in parallel: ``dst |= a | b`` over whole frames.

numpy's in-place ``|=`` runs on one thread: a serial part of every frame of the model FFC
stage that keeps the default correction from scaling with threads.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import Kernel

__all__ = ["or_into", "or_into_flag_uncertain"]


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


def _or_flag_loop(dst, a, b, value, c, e, bit):
    for i in prange(dst.shape[0]):
        v = value[i]
        dst[i] |= a[i] | b[i] | (bit if c[i] > e[i] * v * v else 0)


_or_flag_kernel = Kernel(_or_flag_loop, 0, parallel_min=1 << 18)


def or_into_flag_uncertain(dst: np.ndarray, a: np.ndarray, b: np.ndarray, value: np.ndarray,
                           c: np.ndarray, e: np.ndarray, bit: int) -> np.ndarray:
    """``dst |= a | b``, and ``bit`` where ``c > e value^2`` (all planes of one shape; ``c``,
    ``e`` float32): one pass for :class:`hsiffc.stages.model_ffc.ModelFFC`'s UNCERTAIN flag,
    a relative error ``sqrt(s^2 + c / value^2)`` above a limit ``L`` with ``e = L^2 - s^2``
    (NaN values are not flagged here)."""
    if not (dst.shape == np.shape(a) == np.shape(b) == np.shape(value) == np.shape(c)
            == np.shape(e)) or not dst.flags.c_contiguous:
        or_into(dst, a, b)
        v = np.asarray(value, np.float32)
        dst[np.asarray(c) > np.asarray(e) * v * v] |= dst.dtype.type(bit)
        return dst
    flat = [np.ascontiguousarray(x, t).reshape(-1) for x, t in (
        (a, dst.dtype), (b, dst.dtype), (value, np.float32), (c, np.float32), (e, np.float32))]
    _or_flag_kernel(dst.reshape(-1), *flat, dst.dtype.type(bit))
    return dst
