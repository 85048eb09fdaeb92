"""Data-quality bit flags, one uint32 plane per frame (JWST-style).

Flag, never delete: a flagged pixel keeps a finite value and gains a bit here.
"""

from __future__ import annotations

import enum

import numpy as np

DQ_DTYPE = np.uint32


class DQ(enum.IntFlag):
    """Named data-quality bits."""

    GOOD = 0
    DO_NOT_USE = 1 << 0
    SATURATED = 1 << 1  # at full scale (ADC clip) or full well
    LEAKAGE = 1 << 2  # leakage percentage alpha over threshold
    DEAD = 1 << 3
    HOT = 1 << 4
    NO_FLAT = 1 << 5
    NONFINITE = 1 << 6  # input was NaN or inf
    BELOW_DARK = 1 << 7  # response below what zero light can give
    UNREACHABLE = 1 << 8  # no light rate explains the response
    NOT_CONVERGED = 1 << 9
    LEAK_UNCONSTRAINED = 1 << 10  # calibration: the data do not pin the leakage a, b
    OUT_OF_DOMAIN = 1 << 11  # outside the calibration's validity domain


def empty_dq(shape) -> np.ndarray:
    """A DQ plane of the given shape with every pixel GOOD."""
    return np.zeros(shape, dtype=DQ_DTYPE)


def as_dq(plane, name: str = "dq") -> np.ndarray:
    """``plane`` as a uint32 DQ array (no copy when it is one), refusing what is not a set of
    bits: floats (0.5 would become 0), negative integers (-1 would become every bit), complex.

    Examples
    --------
    >>> as_dq(np.array([0, 6], np.int16)).tolist()
    [0, 6]
    """
    a = np.asarray(plane)
    if a.dtype == DQ_DTYPE:
        return a
    if a.dtype.kind not in "biu":
        raise ValueError(f"{name} must hold integer DQ bits (uint32), got dtype {a.dtype}; "
                         f"build it with hsiffc.dq.empty_dq or from DQ flags")
    if a.dtype.kind == "i" and a.size and a.min() < 0:
        raise ValueError(f"{name} holds negative values (min {a.min()}); DQ bits are unsigned: "
                         "build it with hsiffc.dq.empty_dq or from DQ flags")
    if a.size and a.dtype.itemsize > 4 and a.max() > np.iinfo(DQ_DTYPE).max:
        raise ValueError(f"{name} holds values beyond 32 bits (max {a.max()}); DQ planes are "
                         "uint32")
    return a.astype(DQ_DTYPE)


def describe(value: int) -> list[str]:
    """Names of the bits set in ``value``.

    Examples
    --------
    >>> describe(DQ.SATURATED | DQ.LEAKAGE)
    ['SATURATED', 'LEAKAGE']
    """
    return [f.name for f in DQ if f and (int(value) & int(f)) == int(f)]
