"""Least-squares pieces the joint fit of :mod:`hsiffc.diagnose.fitting` is built from.

Per pixel, the weighted Gram products ``a^T W b`` (:func:`gram`) and the projection off the
base model's Jacobian (:func:`projector`: what the base parameters cannot absorb); the fraction
of a candidate effect that stays separable from the base on a design
(:func:`separable_fraction`); the least-squares fit of one effect on a residual, jointly with
the base or not (:func:`fit_effect`), and of a within-step effect on the frame differences
(:func:`fit_pair_effect`, on what :func:`pair_regression` sets up). All are re-exported by
:mod:`hsiffc.diagnose.fitting`.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from .fitdata import Data

__all__ = ["fit_effect", "fit_frame_pairs", "fit_on_differences", "fit_pair_effect",
           "frame_regression", "gram",
           "pair_regression", "projector", "separable_fraction"]


def gram(a, w, b):
    """Per pixel a^T W b: (P, S, i), (P, S), (P, S, j) -> (P, i, j), as batched matmuls.

    Parameters
    ----------
    a : ndarray, (P, S, i)
    w : ndarray, (P, S)
        Weights.
    b : ndarray, (P, S, j)

    Returns
    -------
    ndarray, (P, i, j)
    """
    return np.matmul((a * w[..., None]).transpose(0, 2, 1), b)


def projector(jac, w):
    """Per pixel, the map v -> v - J (J^T W J)^-1 J^T W v (what the base cannot absorb).

    Parameters
    ----------
    jac : ndarray, (P, S, n)
        Base-model Jacobian.
    w : ndarray, (P, S)
        Weights.

    Returns
    -------
    callable
        ``project(v)`` for v of shape (P, S) or (P, S, m).
    """
    normal = gram(jac, w, jac)
    normal += 1e-9 * (np.einsum("pii->p", normal)[:, None, None] + 1e-30) * np.eye(jac.shape[-1])
    inv = np.linalg.pinv(normal)
    jw_t = (jac * w[..., None]).transpose(0, 2, 1)  # (P, n, S)

    def project(v):  # v: (P, S) or (P, S, m)
        squeeze = v.ndim == 2
        vv = v[..., None] if squeeze else v
        out = vv - np.matmul(jac, np.matmul(inv, np.matmul(jw_t, vv)))
        return out[..., 0] if squeeze else out
    return project


def separable_fraction(effect, ctx, project, w) -> float:
    """Smallest fraction of the effect's weighted column energy, over directions in its
    parameter space, that the base model's parameters cannot absorb (1: fully separable,
    0: the design cannot tell the effect from the base).

    Parameters
    ----------
    effect : Effect
        The candidate.
    ctx : Context
        Base model on the data.
    project : callable
        From :func:`projector`.
    w : ndarray, (P, S)
        Weights.

    Returns
    -------
    float
        In [0, 1].
    """
    if effect.scope in ("step", "pair", "frame"):
        return 1.0
    X = effect.columns(ctx)
    Xp = project(X)
    if effect.scope == "global":
        g = gram(X, w, X).sum(axis=0)
        gp = gram(Xp, w, Xp).sum(axis=0)
        if not np.all(np.isfinite(g)) or np.trace(g) <= 0:
            return 0.0
        scale = np.sqrt(np.clip(np.diag(g), 1e-300, None))
        g, gp = g / np.outer(scale, scale), gp / np.outer(scale, scale)
        try:
            ev = linalg.eigh(gp, g + 1e-12 * np.eye(len(g)), eigvals_only=True)
        except (linalg.LinAlgError, ValueError):
            return 0.0
        return float(max(ev.min(), 0.0))
    num = (Xp * Xp * w[..., None]).sum(axis=(1, 2))
    den = (X * X * w[..., None]).sum(axis=(1, 2))
    ok = den > 0
    return float(np.median(num[ok] / den[ok])) if ok.any() else 0.0


#: pixels keep part of their own estimates (:func:`pool_pixels`) only where their spread beyond
#: their errors is shown: Cochran's Q above its expectation under one value for the sensor by
#: this many standard deviations of its chi-square. Not 5: a dark signal outside the photodiode
#: whose pixels differ by 30 %, without dark frames, at one light rate, showed its spread by
#: 5.3-13.9 (development seeds 111068, 111180, 112188; each of its 190-380 effective parameters
#: removing 2.2-2.5 weighted squared units of the fit, where noise alone removes one), counted
#: as one parameter a pixel and lost to an offset drift on the BIC; at several light rates it
#: showed by 97-183
POOL_SIGMAS = 20.0


def pool_pixels(theta, precision):
    """Per-pixel estimates pooled towards the sensor's value (random-effects shrinkage).

    The spread between the pixels beyond their own errors (``tau^2``, moment estimate of
    DerSimonian and Laird) sets how far each pixel keeps its own estimate: a pixel with an
    error much larger than ``tau`` takes the sensor's (precision-weighted) mean. Where the
    data do not show such a spread (Cochran's Q, which is chi-square with ``P - 1`` degrees of
    freedom when the pixels share one value, within ``POOL_SIGMAS`` of its standard deviation
    of ``P - 1``), every pixel takes the sensor's value: one parameter, not ``P`` that keep
    some of their noise (the moment estimate is above zero for half of all sensors whose
    pixels do share one value).

    Parameters
    ----------
    theta : ndarray, (P,)
        Each pixel's least-squares estimate.
    precision : ndarray, (P,)
        Its inverse variance (the weighted column energy).

    Returns
    -------
    ndarray, (P,)

    Examples
    --------
    >>> import numpy as np
    >>> pool_pixels(np.array([1.0, 2.0]), np.array([1.0, 1.0])).tolist()  # within errors: pooled
    [1.5, 1.5]
    >>> pool_pixels(np.array([1.0, 5.0, 9.0]), np.array([1e4, 1e4, 1e4])).round(3).tolist()
    [1.0, 5.0, 9.0]
    """
    a = np.clip(precision, 0.0, None)
    total = a.sum()
    if total <= 0 or theta.size < 2:
        return theta
    mean = float((a * theta).sum() / total)
    q = float((a * (theta - mean) ** 2).sum())
    if q - (theta.size - 1) <= POOL_SIGMAS * np.sqrt(2.0 * (theta.size - 1)):
        return np.full_like(theta, mean)
    # Q exceeds its expectation here, so the moment estimate of the spread is positive
    tau2 = (q - (theta.size - 1)) / max(total - (a * a).sum() / total, 1e-300)
    return (a * theta + mean / tau2) / (a + 1.0 / tau2)


def fit_effect(effect, ctx, res, w, project=None):
    """Least-squares parameters of one effect on a residual; returns (params, prediction).

    Parameters
    ----------
    effect : Effect
        The effect.
    ctx : Context
        Base model on the data.
    res : ndarray, (P, S), DN
        Residual to explain.
    w : ndarray, (P, S)
        Weights.
    project : callable, optional
        From :func:`projector`: fit jointly with the base (what the base cannot absorb).

    Returns
    -------
    params : ndarray
        (m,) for a global effect, (P, m) per pixel, (S,) per step.
    prediction : ndarray, (P, S), DN
    """
    X = effect.columns(ctx)  # (P, S, m)
    joint = project is not None and effect.scope in ("global", "pixel")
    Xp = project(X) if joint else X
    rp = project(res) if joint else res
    if effect.scope == "global":
        a = gram(Xp, w, Xp).sum(axis=0)
        b = gram(Xp, w, rp[..., None]).sum(axis=0)[:, 0]
        theta = np.linalg.lstsq(a + 1e-12 * np.trace(a) * np.eye(a.shape[0]), b, rcond=None)[0]
        return theta, X @ theta
    if effect.scope == "pixel":
        a = gram(Xp, w, Xp)
        b = gram(Xp, w, rp[..., None])
        # a ridge relative to the pixel's own and to the typical pixel's column energy: a
        # pixel whose column is all but absorbed by its base gets no huge parameter
        tr = np.einsum("pii->p", a)
        lam = 1e-9 * (tr + 1e-30) + 1e-6 * float(np.median(tr))
        a = a + lam[:, None, None] * np.eye(a.shape[1])
        theta = np.linalg.solve(a, b)[..., 0]
        if effect.pooled and theta.shape[1] == 1:
            theta = pool_pixels(theta[:, 0], a[:, 0, 0])[:, None]
        return theta, np.matmul(X, theta[..., None])[..., 0]
    # step: one factor per light step, shared by the pixels
    x = X[..., 0]
    num = (w * x * res).sum(axis=0)
    den = (w * x * x).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.where((den > 0) & ctx.light, num / den, 0.0)
    return theta, x * theta[None, :]


def pair_regression(effect, ctx, data: Data):
    """What a within-step effect is fitted on: its column times the frame gap ``x`` (P, S),
    the light samples valid in both halves ``ok`` (P, S) and the frame differences ``d``
    (held-out minus fit half, DN; 0 outside ``ok``).

    Parameters
    ----------
    effect : Effect
        A within-step ("pair") effect.
    ctx : Context
        Base model on the data.
    data : Data
        The samples.

    Returns
    -------
    x, ok, d : ndarray, (P, S)
    """
    x = effect.columns(ctx)[..., 0] * data.frame_gap
    ok = data.valid & data.valid_ho & data.light[None, :]
    return x, ok, np.where(ok, data.y_ho - data.y, 0.0)


def fit_pair_effect(effect, ctx, data: Data, prediction):
    """A within-step effect (the held-out frames differ from the fit frames of the same step),
    fitted on the frame differences by two-fold cross-fitting over pixels: the parameter applied
    to one half of the pixels is estimated on the other half, so the held-out error stays
    honest.

    Parameters
    ----------
    effect : Effect
        A within-step ("pair") effect.
    ctx : Context
        Base model on the data.
    data : Data
        The samples (fit and held-out halves).
    prediction : ndarray, (P, S), DN
        Current model prediction.

    Returns
    -------
    params : ndarray, (1,)
        Whole-sensor estimate.
    prediction : ndarray, (P, S), DN
        What the effect adds to the held-out half.
    """
    x, ok, d = pair_regression(effect, ctx, data)
    theta, coef = _cross_fitted(x, d, np.where(ok, data.w, 0.0))
    return np.array([theta]), coef[:, None] * x


def _cross_fitted(x, d, w):
    """Coefficient of ``d`` on ``x`` (weights ``w``, 0 outside the samples used) for the whole
    sensor, and per pixel the one estimated on the other half of the pixels (P,)."""
    half = (np.arange(x.shape[0]) % 2).astype(bool)

    def estimate(sel):
        den = (w[sel] * x[sel] ** 2).sum()
        return float((w[sel] * x[sel] * d[sel]).sum() / den) if den > 0 else 0.0
    coef = np.where(half, estimate(~half), estimate(half))
    return estimate(np.ones_like(half)), coef


def fit_on_differences(effect, ctx, data: Data):
    """A one-parameter global effect with its own held-out columns whose evidence is the frame
    differences (``frame_lag``: what the held-out frames of a step carry differs from what the
    fit frames carry), fitted on them: the held-out frames less the fit frames against its
    held-out columns less its fit columns, cross-fitted over two halves of the pixels as
    :func:`fit_pair_effect` (same parameters; ``effect`` has ``ho_columns`` and one
    parameter). The fit half alone sees such an effect mostly as a gain of the base (a lag of
    9.8 % fitted there came out 8.8 % on development seed 100272); the differences see it net
    of the base.

    Returns
    -------
    params : ndarray, (1,)
        Whole-sensor estimate.
    prediction, prediction_ho : ndarray, (P, S), DN
        What it adds to the fit half and to the held-out half (each pixel with the estimate of
        the other half).
    """
    col = effect.columns(ctx)[..., 0]
    col_ho = effect.ho_columns(ctx)[..., 0]
    x = col_ho - col
    ok = data.valid & data.valid_ho & np.isfinite(x)
    w = np.where(ok, data.w, 0.0)
    theta, coef = _cross_fitted(np.where(ok, x, 0.0), np.where(ok, data.y_ho - data.y, 0.0), w)
    return np.array([theta]), coef[:, None] * col, coef[:, None] * col_ho


def frame_regression(effect, ctx, data: Data):
    """What the part of a ``frame`` effect between the halves is fitted on: its column ``x``
    (P, S), the light samples valid in both halves ``ok`` and the frame differences ``d``
    (held-out minus fit half, DN; 0 outside ``ok``), as :func:`pair_regression`, with one
    factor per step (no frame gap).

    Parameters
    ----------
    effect : Effect
        A ``frame`` effect.
    ctx : Context
        Base model on the data.
    data : Data
        The samples.

    Returns
    -------
    x, ok, d : ndarray, (P, S)
    """
    x = effect.columns(ctx)[..., 0]
    ok = data.valid & data.valid_ho & data.light[None, :] & np.isfinite(x)
    return np.where(ok, x, 0.0), ok, np.where(ok, data.y_ho - data.y, 0.0)


def fit_frame_pairs(effect, ctx, data: Data):
    """The part of a ``frame`` effect between the halves: a factor per light step fitted on the
    frame differences, cross-fitted over two halves of the pixels (the factor applied to one
    half is estimated on the other), so the held-out error stays honest.

    Parameters
    ----------
    effect : Effect
        A ``frame`` effect.
    ctx : Context
        Base model on the data.
    data : Data
        The samples.

    Returns
    -------
    factors : ndarray, (S,)
        Whole-sensor estimate per step (0 for darks).
    extra : ndarray, (P, S), DN
        What it adds to the held-out half.
    """
    x, ok, d = frame_regression(effect, ctx, data)
    wx = np.where(ok, data.w, 0.0)
    half = (np.arange(x.shape[0]) % 2).astype(bool)

    def estimate(sel):
        den = (wx[sel] * x[sel] ** 2).sum(axis=0)
        num = (wx[sel] * x[sel] * d[sel]).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    coef = np.where(half[:, None], estimate(~half)[None, :], estimate(half)[None, :])
    return estimate(np.ones_like(half)), coef * x
