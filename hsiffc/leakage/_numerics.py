"""Small numerical helpers shared by the leakage-model modules.

:mod:`hsiffc.leakage.model` (the closed-form response and its inversion) and
:mod:`hsiffc.leakage._derived` (saturation level, leakage rate and percentage) both convert their
arguments to float64, take logarithms that map 0 to ``-inf`` quietly, need ``log(1 - e^{-x})``
accurately and refuse a non-positive leakage exponent ``b``; those four pieces live here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["B_MESSAGE", "NEGATIVE_MESSAGE", "as_float64", "check_positive_b", "log1mexp",
           "log_or_neg_inf", "smallest"]


def as_float64(*arrays):
    """Every argument as a float64 ndarray.

    Parameters
    ----------
    *arrays : array_like
        Values to convert (any shape).

    Returns
    -------
    list of ndarray of float64
        One array per argument, in order.
    """
    return [np.asarray(a, dtype=np.float64) for a in arrays]


def log_or_neg_inf(x):
    """Natural log that maps 0 to -inf without a warning.

    Parameters
    ----------
    x : array_like
        Values >= 0.

    Returns
    -------
    ndarray or float
        ``log(x)``, -inf where x is 0.
    """
    with np.errstate(divide="ignore"):
        return np.log(x)


def log1mexp(x):
    """log(1 - exp(-x)) for x >= 0, accurate everywhere (Maechler 2012).

    Parameters
    ----------
    x : array_like
        Values >= 0 (0 gives -inf).

    Returns
    -------
    ndarray of float64
        Shape of ``x``.
    """
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        small = x < np.log(2.0)
        return np.where(small, np.log(-np.expm1(-np.where(small, x, 1.0))),
                        np.log1p(-np.exp(-np.where(small, 1.0, x))))


def smallest(x) -> float:
    """The smallest value of ``x`` that is not NaN (NaN when there is none): one pass, no
    temporary array (``np.any(x < 0)`` builds a boolean array of the frame first), and
    ``smallest(x) < 0`` means exactly ``np.any(x < 0)``."""
    a = np.asarray(x)
    return float(np.fmin.reduce(a, axis=None)) if a.size else np.nan


B_MESSAGE = "b (1/DN) must be > 0: the leakage grows with the collected signal"
NEGATIVE_MESSAGE = "t_ms, k and a must be >= 0"


def check_positive_b(b):
    """Refuse a leakage exponent that is not > 0.

    Parameters
    ----------
    b : array_like, 1/DN
        Leakage exponent(s).

    Returns
    -------
    None

    Raises
    ------
    ValueError
        If any ``b`` is <= 0.
    """
    if smallest(b) <= 0:
        raise ValueError(B_MESSAGE)
