"""The leakage model of a low-light CMOS pixel (Liu et al., section III), vectorised.

A pixel's raw response Y (DN) grows with the light rate k (DN/ms) and loses charge through the
transfer transistor's sub-threshold leakage, which grows exponentially with the collected signal:

    dY/dt = k - a * exp(b * Y)                                   (paper eq. 2)

Units used throughout: exposure ``t_ms`` in milliseconds, ``k`` and ``a`` in DN/ms, ``b`` in 1/DN,
responses and dark levels in raw DN. Every function broadcasts over arrays of any shape.

Numerically stable closed form
------------------------------
With ``z = exp(-b Y)`` the ODE is linear, ``dz/dt = a b - b k z``, so from the level ``Y0`` at
``t = 0`` (the dark level):

    exp(-b Y(t)) = exp(-b Y0 - x) + a b t * phi(x),   x = b k t,   phi(x) = (1 - exp(-x)) / x

Both terms are positive for every k >= 0. The compiled kernels
(:mod:`hsiffc.kernels.leakage`) sum them directly and fall back to ``logaddexp`` of their logs
where the sum would under- or overflow, so nothing overflows: the form stays finite for b k t
up to 1e4 and beyond, for a/k from 0 to 1e3 and more, for k = 0 (pure leakage) and for
starting levels above the dynamic saturation level. The paper's eq. (3) with its
integration constant c is the same curve: ``c_from_dark`` / ``dark_from_c`` convert between
the two.

This module holds the response (closed form, the paper's eq. 3 and the linear eq. 1), its
inversion, its gradient and the reference ODE solution, the quantities derived from the
parameters (dynamic saturation level, leakage rate and percentage, exposure at a given
percentage) and the numerical helpers they share (float64 arguments, logarithms that map 0 to
``-inf`` quietly, ``log(1 - e^{-x})``, the check of a positive leakage exponent ``b``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.dq import DQ_DTYPE
from ..kernels import gradient, inversion, leakage
from ..kernels.operands import flat_operands
__all__ = [
    "response", "response_from_c", "linear_response", "c_from_dark", "dark_from_c",
    "dynamic_saturation_level", "leakage_rate", "leakage_percentage",
    "leakage_percentage_paper", "leakage_percentage_paper_into", "exposure_at_leakage_percentage",
    "invert_response",
    "Inversion", "solve_ode", "response_and_gradient",
]


# -- numerical helpers: float64 arguments, quiet logarithms, log(1 - e^-x), the b check ------

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


# -- the response ------------------------------------------------------------------------------


def _response(t_ms, k, a, b, dark, check: bool = False):
    """Model response (float64 out, shape of the broadcast); ``check``: refuse inputs outside
    the model's domain, counted by the kernel in its own pass."""
    shape, ops = flat_operands(t_ms, k, a, b, dark,
                               names=("t_ms", "k", "a", "b", "dark"))
    out = np.empty(int(np.prod(shape, dtype=np.int64)))
    negative, b_bad = leakage.response_kernel(*ops, out)
    if check and b_bad:
        raise ValueError(B_MESSAGE)
    if check and negative:
        raise ValueError(NEGATIVE_MESSAGE)
    return out.reshape(shape)


def response(t_ms, k, a, b, dark):
    """Response of the leakage model after ``t_ms`` from the level ``dark`` at t = 0.

    Parameters
    ----------
    t_ms : array_like, ms
        Exposure time (>= 0).
    k : array_like, DN/ms
        Light rate (>= 0).
    a : array_like, DN/ms
        Leakage amplitude (>= 0; 0 gives the linear response of eq. 1).
    b : array_like, 1/DN
        Leakage exponent (> 0).
    dark : array_like, DN
        Response at t = 0 (the dark level).

    Returns
    -------
    ndarray of float64, DN

    Examples
    --------
    >>> round(float(response(10.0, 2.0, 0.0, 0.01, 50.0)), 6)   # a = 0: linear
    70.0
    >>> y = response(1e4, 2.0, 2 * np.exp(-8.0), 0.01, 50.0)      # long exposure: saturated
    >>> round(float(y), 3), round(float(dynamic_saturation_level(2.0, 2 * np.exp(-8.0), 0.01)), 3)
    (800.0, 800.0)
    """
    return _response(t_ms, k, a, b, dark, check=True)


def response_from_c(t_ms, k, a, b, c):
    """The paper's eq. (3): ``Y = ln(k e^{bk(t+c)} / (1 + a e^{bk(t+c)})) / b``, stable form.

    Computed as ``(ln k - logaddexp(ln a, -b k (t + c))) / b``, which never overflows.
    ``c`` (ms) is the integration constant; see :func:`c_from_dark`. Needs k > 0.

    Parameters
    ----------
    t_ms : array_like, ms
        Exposure time.
    k : array_like, DN/ms
        Light rate (> 0).
    a : array_like, DN/ms
        Leakage amplitude.
    b : array_like, 1/DN
        Leakage exponent (> 0).
    c : array_like, ms
        Integration constant of eq. (3).

    Returns
    -------
    ndarray of float64, DN
        The response, shape of the broadcast of the arguments.

    Examples
    --------
    >>> k, a, b, d = 2.0, 2 * np.exp(-8.0), 0.01, 50.0
    >>> c = c_from_dark(k, a, b, d)
    >>> bool(np.isclose(response_from_c(10.0, k, a, b, c), response(10.0, k, a, b, d)))
    True
    """
    t_ms, k, a, b, c = as_float64(t_ms, k, a, b, c)
    check_positive_b(b)
    if np.any(k <= 0):
        raise ValueError("k must be > 0 in the paper's form (use response() for k = 0)")
    return (np.log(k) - np.logaddexp(log_or_neg_inf(a), -b * k * (t_ms + c))) / b


def linear_response(t_ms, k, dark):
    """The linear model of eq. (1): ``Y = k t + d`` (DN).

    Parameters
    ----------
    t_ms : array_like, ms
        Exposure time.
    k : array_like, DN/ms
        Light rate.
    dark : array_like, DN
        Dark level (response at t = 0).

    Returns
    -------
    ndarray of float64, DN
        Shape of the broadcast of the arguments.
    """
    t_ms, k, dark = as_float64(t_ms, k, dark)
    return k * t_ms + dark


def c_from_dark(k, a, b, dark):
    """Integration constant c (ms) of eq. (3) that makes Y(0) equal ``dark``.

    ``c = -ln(k e^{-b d} - a) / (b k)``. It exists only while the dark level is below the dynamic
    saturation level (k e^{-bd} > a); elsewhere the result is NaN and the starting-level form
    :func:`response` must be used.

    Parameters
    ----------
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
        The constant c, NaN where it does not exist; shape of the broadcast.
    """
    k, a, b, dark = as_float64(k, a, b, dark)
    check_positive_b(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        # ln(k e^{-bd} - a) = ln k - b d + log(1 - (a/k) e^{bd})
        log_ratio = log_or_neg_inf(a) - np.log(k) + b * dark
        inner = np.log(k) - b * dark + log1mexp(-log_ratio)
        c = -inner / (b * k)
    return np.where((log_ratio < 0) & (k > 0), c, np.nan)


def dark_from_c(k, a, b, c):
    """Level at t = 0 (DN) of eq. (3) with constant ``c`` (ms); inverse of :func:`c_from_dark`.

    Parameters
    ----------
    k, a, b : array_like
        Light rate (DN/ms, > 0), leakage amplitude (DN/ms) and exponent (1/DN, > 0).
    c : array_like, ms
        Integration constant of eq. (3).

    Returns
    -------
    ndarray of float64, DN
        Shape of the broadcast of the arguments.
    """
    return response_from_c(0.0, k, a, b, c)


@dataclass(frozen=True)
class Inversion:
    """Result of :func:`invert_response`.

    Attributes
    ----------
    k : ndarray, DN/ms
        Light rate explaining each response. Where ``flags`` is not GOOD it holds the nearest
        admissible value (0 below the zero-light level, the rate reaching full scale for a clipped
        response, ``k_max`` beyond it) and must be read together with the flag.
    flags : ndarray of uint32
        :class:`hsiffc.data.dq.DQ` bits: BELOW_DARK, SATURATED, UNREACHABLE, NONFINITE, NOT_CONVERGED.
    iterations : int
        Largest number of iterations any pixel needed.
    """

    k: np.ndarray
    flags: np.ndarray
    iterations: int

    @property
    def valid(self) -> np.ndarray:
        """Boolean array, True where the inversion is good (no DQ flag)."""
        return self.flags == 0


def invert_response(y, t_ms, a, b, dark, *, full_scale=None, k_max=None, tol_dn=1e-9,
                    max_iter=60) -> Inversion:
    """Light rate k that explains response ``y`` at exposure ``t_ms``, for whole frames at once.

    The model response increases monotonically with k, from the zero-light level (pure leakage
    from ``dark``) towards infinity, so a unique k exists for every response above the zero-light
    level. It is found per pixel by a compiled kernel
    (:func:`hsiffc.kernels.inversion.invert_point`): with ``x = b k t`` the model scaled by
    ``e^{bY}`` is convex and decreasing in x, so Halley's iteration from the lower bounds
    ``x >= b (Y - d)`` and ``x >= a b t e^{bY}`` converges fast (vectorised rounds of two, then
    one step, each checked, then bracketed steps for what is left, until the response matches
    within ``tol_dn + 8 eps |y|``; see :mod:`hsiffc.kernels.inversion`).

    Parameters
    ----------
    y : array_like, DN
        Responses (any shape; broadcast with the other arguments).
    t_ms : array_like, ms
        Exposure time (> 0).
    a, b, dark : array_like
        Leakage parameters and level at t = 0, as in :func:`response`.
    full_scale : float, optional, DN
        Responses at or above it are clipped: flagged SATURATED, and k is the rate that just
        reaches full scale (a lower bound).
    k_max : float, optional, DN/ms
        Responses that need more light than this are flagged UNREACHABLE (k set to k_max).
    tol_dn : float
        Convergence tolerance on the response, in DN.
    max_iter : int
        Iterations per pixel before it is flagged NOT_CONVERGED.

    Returns
    -------
    Inversion
        ``k`` (DN/ms) and ``flags`` of the broadcast shape.

    Examples
    --------
    >>> a, b, d = 2 * np.exp(-8.0), 0.01, 50.0
    >>> y = response([10.0, 400.0], 2.0, a, b, d)
    >>> inv = invert_response(y, [10.0, 400.0], a, b, d)
    >>> np.round(inv.k, 9).tolist(), inv.flags.tolist()
    ([2.0, 2.0], [0, 0])
    """
    check_positive_b(b)
    if np.any(np.asarray(t_ms) <= 0):
        raise ValueError("t_ms must be > 0 to invert a response (at t = 0 no light is measured)")
    shape, ops = flat_operands(y, t_ms, a, b, dark,
                               names=("y", "t_ms", "a", "b", "dark"))
    n = int(np.prod(shape, dtype=np.int64))
    k = np.empty(n)
    flags = np.empty(n, DQ_DTYPE)
    iterations = np.zeros(max(1, -(-n // leakage.BLOCK)), np.int64)
    inversion.invert_kernel(*ops, np.inf if full_scale is None else float(full_scale),
                          np.inf if k_max is None else float(k_max), float(tol_dn),
                          int(max_iter), k, flags, iterations)
    return Inversion(k.reshape(shape), flags.reshape(shape), int(iterations.max()))


def solve_ode(t_ms, k, a, b, dark, *, rtol=1e-10, atol=1e-10):
    """Reference solution of eq. (2) for one pixel with :func:`scipy.integrate.solve_ivp`.

    Slow (one ODE solve per pixel); used by the tests and the benchmark as ground truth.

    Parameters
    ----------
    t_ms : array_like, ms
        Sorted 1-D array of exposures.
    k, a, b, dark : float
        Light rate (DN/ms), leakage amplitude (DN/ms), exponent (1/DN) and level at t = 0 (DN)
        of the one pixel.
    rtol, atol : float
        Tolerances of the LSODA solver.

    Returns
    -------
    ndarray of float64, DN
        Y at the exposures, shape ``(len(t_ms),)``.

    Raises
    ------
    RuntimeError
        If the solver fails.
    """
    from scipy.integrate import solve_ivp

    t_ms = np.asarray(t_ms, dtype=np.float64)
    k, a, b, dark = (float(v) for v in (k, a, b, dark))

    def rhs(_t, yv):
        return [k - a * np.exp(min(b * yv[0], 700.0))]

    def jac(_t, yv):
        return [[-a * b * np.exp(min(b * yv[0], 700.0))]]

    sol = solve_ivp(rhs, (0.0, float(t_ms.max())), [dark], method="LSODA", t_eval=t_ms,
                    rtol=rtol, atol=atol, jac=jac)
    if not sol.success:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    return sol.y[0]


def response_and_gradient(t_ms, k, a, b, dark):
    """Response of the leakage model and its derivatives, for whole arrays (numba, parallel).

    Parameters
    ----------
    t_ms, k, a, b, dark : array_like
        As in :func:`response` (broadcast together).

    Returns
    -------
    y, dy_dlnk, dy_dlna, dy_dlnb, dy_ddark : ndarrays of float64, broadcast shape
        The response (DN) and its derivatives with respect to ``ln k``, ``ln a``, ``ln b`` (DN)
        and the dark level (dimensionless).

    Examples
    --------
    >>> y, *_ = response_and_gradient(10.0, 2.0, 0.0, 0.01, 50.0)
    >>> round(float(y), 6)
    70.0
    """
    shape, ops = flat_operands(t_ms, k, a, b, dark,
                               names=("t_ms", "k", "a", "b", "dark"))
    check_positive_b(b)
    if smallest(t_ms) < 0 or smallest(k) < 0 or smallest(a) < 0:
        raise ValueError(NEGATIVE_MESSAGE)
    out = np.empty((5, int(np.prod(shape))))
    gradient.response_gradient_kernel(*ops, out)
    return tuple(o.reshape(shape) for o in out)


# -- quantities derived from the parameters -----------------------------------------------------
# where leakage balances the light (the dynamic saturation level ln(k/a)/b), the leakage rate
# a e^{bY} at a response, the leakage percentage alpha of eq. (4) (with k from the model, or as
# the paper computes it from the signal over the exposure) and the exposure at which the model
# response reaches a given alpha

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
