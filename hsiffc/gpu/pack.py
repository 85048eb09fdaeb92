"""Compact output types for live streams: the scalar rules shared by the CPU and GPU paths.

The copy of the cube back to host memory bounds a GPU correction (a 2048 x 1088 x 8 float32
cube is 71 MB), so a stream may store its output smaller where the user allows it:

* data ``"float16"``: IEEE half precision (11 significant bits: 0.5 DN steps at 1000 DN).
  Values beyond half's range (|v| > 65504) are stored as +-65504 and flagged SATURATED.
* data ``"uint16"``: ``floor(v + 0.5)``; values below 0 are stored as 0 and flagged
  BELOW_DARK, values above 65535 as 65535 and flagged SATURATED (nothing is clipped without
  a flag; NaN, which a finished cube does not hold, is stored as 0 with DO_NOT_USE).
* DQ ``"uint8"``: bits 0-7 as they are (DO_NOT_USE ... BELOW_DARK); a value with any of the
  higher bits (UNREACHABLE, NOT_CONVERGED, LEAK_UNCONSTRAINED, OUT_OF_DOMAIN) also gets
  DO_NOT_USE: the plane says "do not use" where it can no longer say why.

The rules are numba functions of one value (:func:`clip_half`, :func:`round_u16`,
:func:`fold_dq8`), compiled for the CPU here and called by the GPU kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..data.dq import DQ, DQ_DTYPE
from ..errors import ParameterError

__all__ = ["DATA_DTYPES", "DQ_DTYPES", "check_dtypes", "clip_half", "fold_dq8", "pack_cpu",
           "round_u16"]

DATA_DTYPES = ("float32", "float16", "uint16")
DQ_DTYPES = ("uint32", "uint8")
_HALF_MAX = 65504.0
_SAT = int(DQ.SATURATED)
_BELOW = int(DQ.BELOW_DARK)
_DNU = int(DQ.DO_NOT_USE)
_JIT = {"cache": False, "fastmath": False, "error_model": "numpy", "inline": "always"}


@njit(**_JIT)
def clip_half(v):
    """(value to store as float16, DQ bits): +-65504 and SATURATED beyond half's range
    (values from 65504 up to the rounding midpoint 65520 round to 65504 anyway)."""
    if v >= 65520.0:
        return _HALF_MAX, _SAT
    if v <= -65520.0:
        return -_HALF_MAX, _SAT
    return v, 0


@njit(**_JIT)
def round_u16(v):
    """(value as uint16 number, DQ bits): ``floor(v + 0.5)`` in 0..65535, flagged where
    clipped (BELOW_DARK under 0, SATURATED over 65535, DO_NOT_USE for NaN)."""
    if not (v == v):
        return 0.0, _DNU
    if v < -0.5:
        return 0.0, _BELOW
    if v >= 65535.5:
        return 65535.0, _SAT
    return np.float64(math.floor(v + 0.5)), 0


@njit(**_JIT)
def fold_dq8(bits):
    """A uint32 DQ value as uint8: bits 0-7 kept, DO_NOT_USE added where a higher bit is
    set."""
    return (bits & 0xFF) | (_DNU if (bits & ~0xFF) != 0 else 0)


def check_dtypes(data_dtype: str, dq_dtype: str) -> tuple[str, str]:
    """The two names, checked (ParameterError naming the parameter otherwise)."""
    if str(data_dtype) not in DATA_DTYPES:
        raise ParameterError(f"data_dtype={data_dtype!r}: use one of {', '.join(DATA_DTYPES)}")
    if str(dq_dtype) not in DQ_DTYPES:
        raise ParameterError(f"dq_dtype={dq_dtype!r}: use one of {', '.join(DQ_DTYPES)}")
    return str(data_dtype), str(dq_dtype)


@njit(parallel=True, cache=True, error_model="numpy")
def _pack_loop(data, dq, mode, fold, out_value, out_dq):
    for i in prange(data.shape[0]):
        v = np.float64(data[i])
        bits = np.int64(dq[i])
        if mode == 1:
            v, extra = clip_half(v)
            bits |= extra
        elif mode == 2:
            v, extra = round_u16(v)
            bits |= extra
        out_value[i] = v
        out_dq[i] = fold_dq8(bits) if fold else bits


def pack_cpu(data, dq, data_dtype: str = "float32", dq_dtype: str = "uint32"):
    """``(data, dq)`` (float32, uint32) in the compact types: the CPU side of the rules."""
    data_dtype, dq_dtype = check_dtypes(data_dtype, dq_dtype)
    if data_dtype == "float32" and dq_dtype == "uint32":
        return data, dq
    mode = DATA_DTYPES.index(data_dtype)
    value = np.empty(data.shape, np.float32)
    bits = np.empty(data.shape, DQ_DTYPE)
    _pack_loop(np.ascontiguousarray(data, np.float32).reshape(-1),
               np.ascontiguousarray(dq, DQ_DTYPE).reshape(-1), mode, dq_dtype == "uint8",
               value.reshape(-1), bits.reshape(-1))
    # float16: IEEE round to nearest even, as the device stores it; uint8: folded above
    return value.astype(data_dtype), bits.astype(dq_dtype)
