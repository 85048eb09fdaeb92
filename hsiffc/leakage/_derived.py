"""Quantities derived from the leakage model's parameters (Liu et al., section III).

Where leakage balances the light (the dynamic saturation level ``ln(k/a)/b``), the leakage
rate ``a e^{bY}`` at a response, the leakage percentage alpha of eq. (4) (with k from the model,
or as the paper computes it from the signal over the exposure) and the exposure at which the
model response reaches a given alpha. Units as in :mod:`hsiffc.leakage.model`: ``t_ms`` in ms, ``k`` and
``a`` in DN/ms, ``b`` in 1/DN, responses and dark levels in raw DN, alpha in percent. Every
function broadcasts over arrays of any shape. All are also importable from :mod:`hsiffc.leakage.model`.
"""

from __future__ import annotations

import numpy as np

from ..kernels import leakage
from ..kernels.operands import flat_operands
from ._numerics import as_float64, check_positive_b, log1mexp, log_or_neg_inf

__all__ = [
    "dynamic_saturation_level",
    "exposure_at_leakage_percentage",
    "leakage_percentage",
    "leakage_percentage_paper",
    "leakage_percentage_paper_into",
    "leakage_rate",
]


def dynamic_saturation_level(k, a, b):
    """Level ``ln(k/a)/b`` (DN) where leakage balances the light: the dynamic saturation.

    Parameters
    ----------
    k : array_like, DN/ms
        Light rate.
    a : array_like, DN/ms
        Leakage amplitude (0 gives +inf: no saturation).
    b : array_like, 1/DN
        Leakage exponent (> 0).

    Returns
    -------
    ndarray of float64, DN
        Shape of the broadcast of the arguments.

    Examples
    --------
    >>> round(float(dynamic_saturation_level(2.0, 2 * np.exp(-8.0), 0.01)), 6)
    800.0
    """
    k, a, b = as_float64(k, a, b)
    check_positive_b(b)
    with np.errstate(divide="ignore"):
        return (log_or_neg_inf(k) - log_or_neg_inf(a)) / b


def leakage_rate(y, a, b):
    """Leakage ``a e^{bY}`` (DN/ms) at response ``y`` (DN).

    Parameters
    ----------
    y : array_like, DN
        Response.
    a : array_like, DN/ms
        Leakage amplitude.
    b : array_like, 1/DN
        Leakage exponent.

    Returns
    -------
    ndarray of float64, DN/ms
        Shape of the broadcast (inf where it overflows).
    """
    y, a, b = as_float64(y, a, b)
    with np.errstate(over="ignore"):
        return np.exp(log_or_neg_inf(a) + b * y)


def leakage_percentage(y, k, a, b):
    """Leakage percentage alpha of eq. (4) with k from the model: ``100 a e^{bY} / k`` (percent).

    Along a response that starts below saturation alpha stays below 100 %: it reaches 100 % only
    at the dynamic saturation level.

    Parameters
    ----------
    y : array_like, DN
        Response.
    k : array_like, DN/ms
        Light rate (from the calibration or an inversion).
    a : array_like, DN/ms
        Leakage amplitude.
    b : array_like, 1/DN
        Leakage exponent.

    Returns
    -------
    ndarray of float64, percent
        Shape of the broadcast of the arguments.

    Examples
    --------
    >>> a, b = 2 * np.exp(-8.0), 0.01
    >>> round(float(leakage_percentage(800.0, 2.0, a, b)), 6)   # at the dynamic saturation
    100.0
    """
    shape, ops = flat_operands(y, k, a, b, names=("y", "k", "a", "b"))
    out = np.empty(int(np.prod(shape, dtype=np.int64)))
    leakage.alpha_model_kernel(*ops, out)
    return out.reshape(shape)


def leakage_percentage_paper(y, t_ms, a, b, dark=0.0):
    """Alpha as the paper computes it, with k approximated by the signal over the exposure.

    ``alpha = 100 a e^{bY} / ((Y - dark) / t)`` in percent. The paper divides the raw response
    by the exposure (``dark=0``, the default, reproduces that); passing the dark level gives the
    signal rate. Because Y/t underestimates k once leakage bends the curve, this alpha exceeds
    100 % deep in saturation (the paper's 173.5 % example). Where the signal is not positive the
    result is ``inf`` (no light rate can be estimated: treat as invalid).

    Parameters
    ----------
    y : array_like, DN
        Raw response.
    t_ms : array_like, ms
        Exposure time (> 0).
    a : array_like, DN/ms
        Leakage amplitude.
    b : array_like, 1/DN
        Leakage exponent.
    dark : array_like, DN
        Level subtracted before dividing by the exposure (0: the paper's form).

    Returns
    -------
    ndarray of float64, percent
        Shape of the broadcast of the arguments.
    """
    return leakage_percentage_paper_into(None, y, t_ms, a, b, dark)


def leakage_percentage_paper_into(out, y, t_ms, a, b, dark=0.0):
    """:func:`leakage_percentage_paper` written into ``out`` (float32 or float64, the shape of
    the broadcast; None allocates float64). float32 is enough for a validity mask: alpha is
    computed in float64 and rounded once (1e-7 relative).

    Parameters
    ----------
    out : ndarray or None
        C-contiguous output of the broadcast shape (float32 or float64), or None.
    y, t_ms, a, b, dark : array_like
        As in :func:`leakage_percentage_paper`.

    Returns
    -------
    ndarray, percent
        ``out`` (or the new float64 array).
    """
    shape, ops = flat_operands(y, t_ms, a, b, dark,
                               names=("y", "t_ms", "a", "b", "dark"))
    if out is None:
        out = np.empty(shape)
    if out.shape != tuple(shape) or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous array of shape {tuple(shape)}, got "
                         f"{out.shape}")
    leakage.alpha_paper_kernel(*ops, out.reshape(-1))
    return out


def exposure_at_leakage_percentage(alpha_percent, k, a, b, dark):
    """Exposure (ms) at which the model response reaches a leakage percentage.

    With ``alpha0`` the model alpha at the dark level,
    ``t = (logit(alpha) - logit(alpha0)) / (b k)``.
    Returns 0 where the response starts at or above that alpha and ``inf`` where it is never
    reached (alpha >= 100 %, or k = 0).

    Parameters
    ----------
    alpha_percent : array_like, percent
        Leakage percentage to reach (model alpha, :func:`leakage_percentage`).
    k : array_like, DN/ms
        Light rate.
    a : array_like, DN/ms
        Leakage amplitude.
    b : array_like, 1/DN
        Leakage exponent (> 0).
    dark : array_like, DN
        Level at t = 0.

    Returns
    -------
    ndarray of float64, ms
        Shape of the broadcast of the arguments.

    Examples
    --------
    >>> from hsiffc.leakage.model import response
    >>> k, a, b, d = 2.0, 2 * np.exp(-8.0), 0.01, 50.0
    >>> t = exposure_at_leakage_percentage(50.0, k, a, b, d)
    >>> round(float(leakage_percentage(response(t, k, a, b, d), k, a, b)), 6)
    50.0
    """
    alpha, k, a, b, dark = as_float64(alpha_percent, k, a, b, dark)
    check_positive_b(b)
    p = alpha / 100.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        log_p0 = log_or_neg_inf(a) + b * dark - log_or_neg_inf(k)  # log of alpha0 as a fraction
        logit_p = np.log(p) - log1mexp(-np.log(p))
        logit_p0 = log_p0 - log1mexp(-log_p0)
        t = (logit_p - logit_p0) / (b * k)
    t = np.where(p >= 1.0, np.inf, t)
    t = np.where((p < 1.0) & (log_p0 >= np.log(np.minimum(p, 1.0))), 0.0, t)
    return np.where(k > 0, np.maximum(t, 0.0), np.inf)
