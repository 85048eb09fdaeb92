"""Polynomial flat-field correction over several flat levels (array functions).

For every pixel a polynomial maps its dark-subtracted response at each flat level to the band's
mean response at that level (what a uniform pixel would give), the family of the paper's
reference [11]. :func:`polynomial_fit` solves the least-squares problems of all pixels at once;
:func:`polynomial_apply` evaluates them on any frame. The ``polynomial_ffc`` stage runs these.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..spectral.bandstats import band_reduce
from ..data.dq import DQ, DQ_DTYPE


@dataclass(frozen=True)
class PolynomialFlat:
    """Per-pixel polynomials learnt by :func:`polynomial_fit`.

    Attributes
    ----------
    coef : (order + 1, H, W) float64
        Coefficients, lowest power first, of the polynomial in ``u = x / scale``.
    scale : (H, W) float64, DN
        Largest flat signal of the pixel (keeps the powers well conditioned).
    x_min, x_max : (H, W) float32, DN
        The pixel's trained signal range.
    dq : (H, W) uint32
        NO_FLAT where the pixel's flats cannot define a correction (no positive, varying
        signal); those pixels are passed through unchanged. SATURATED where a flat was.
    """

    coef: np.ndarray
    scale: np.ndarray
    x_min: np.ndarray
    x_max: np.ndarray
    dq: np.ndarray


def polynomial_fit(levels, *, order: int, band_map=None, level_dq=None) -> PolynomialFlat:
    """Fit one polynomial per pixel from dark-subtracted flats at several levels.

    Parameters
    ----------
    levels : (L, H, W) array_like, DN
        Dark-subtracted flat signal at each level (L >= order + 1).
    order : int, >= 1
    band_map : (H, W) int array, optional
        Targets are the per-band means of each level.
    level_dq : (L, H, W) uint32 array, optional
        DQ of each level; flagged pixels are left out of the band means, SATURATED is carried.

    Returns
    -------
    PolynomialFlat
    """
    if isinstance(order, bool) or not float(order) == int(order) or int(order) < 1:
        raise ValueError(f"order must be a whole number >= 1 (1: linear), got {order!r}")
    order = int(order)
    x = np.asarray(levels, np.float64)
    if x.ndim != 3 or x.shape[0] < order + 1:
        raise ValueError(f"a polynomial of order {order} needs at least {order + 1} flat "
                         f"levels of shape (L, H, W); got {x.shape}")
    ldq = np.zeros(x.shape, DQ_DTYPE) if level_dq is None else np.asarray(level_dq, DQ_DTYPE)
    bm = np.zeros(x.shape[1:], np.intp) if band_map is None else np.asarray(band_map)
    y = np.stack([band_reduce(x[i], bm, ldq[i] == 0)[bm] for i in range(x.shape[0])])
    dq = np.bitwise_or.reduce(ldq, axis=0) & DQ_DTYPE(DQ.SATURATED)
    finite = np.isfinite(x).all(axis=0) & np.isfinite(y).all(axis=0)
    x = np.where(finite, x, 0.0)
    x_min, x_max = x.min(axis=0), x.max(axis=0)
    # a correction needs a positive signal that varies between the levels
    degenerate = ~finite | ~(x_max > 0) | ~(x_max - x_min > 1e-6 * np.abs(x_max))
    dq[degenerate] |= DQ_DTYPE(DQ.NO_FLAT)
    scale = np.where(degenerate, 1.0, np.maximum(np.abs(x_max), 1e-6))
    y = np.where(degenerate, x, y)
    u = x / scale
    powers = np.stack([u ** j for j in range(order + 1)], axis=-1)  # (L, H, W, n)
    ata = np.einsum("lhwi,lhwj->hwij", powers, powers) + 1e-12 * np.eye(order + 1)
    atb = np.einsum("lhwi,lhw->hwi", powers, y)
    coef = np.moveaxis(np.linalg.solve(ata, atb[..., None])[..., 0], -1, 0)
    neutral = np.zeros_like(coef)
    neutral[1] = scale  # the identity: out = u * scale = x
    coef = np.where(degenerate, neutral, coef)
    return PolynomialFlat(coef, scale, x_min.astype(np.float32), x_max.astype(np.float32), dq)


def polynomial_eval(coef, u) -> np.ndarray:
    """Horner evaluation of per-pixel polynomials (coefficients lowest power first)."""
    out = np.zeros(np.shape(u))
    for c in coef[::-1]:
        out = out * u + c
    return out


def polynomial_apply(signal, flat: PolynomialFlat, *, margin: float = 0.05):
    """Correct a dark-subtracted frame with per-pixel polynomials.

    Signals outside a pixel's trained range (with ``margin`` relative slack) continue along
    the polynomial's end tangent rather than being extrapolated, and are flagged
    OUT_OF_DOMAIN. NO_FLAT pixels pass through unchanged.

    Parameters
    ----------
    signal : (H, W) array_like, DN
    flat : PolynomialFlat
    margin : float, >= 0

    Returns
    -------
    corrected : (H, W) float32, DN (always finite: 0 where the input is not finite or the
        result is beyond the float32 range, flagged NONFINITE | DO_NOT_USE)
    dq : (H, W) uint32 (``flat.dq`` plus OUT_OF_DOMAIN, NONFINITE, DO_NOT_USE)
    """
    x = np.asarray(signal, np.float64)
    span = flat.x_max - flat.x_min
    lo, hi = flat.x_min - margin * span, flat.x_max + margin * span
    no_flat = (flat.dq & DQ_DTYPE(DQ.NO_FLAT)) != 0
    outside = ((x < lo) | (x > hi)) & ~no_flat
    xc = np.clip(x, lo, hi)
    u = xc / flat.scale
    h = 1e-4
    slope = (polynomial_eval(flat.coef, u + h) - polynomial_eval(flat.coef, u - h)) / (2 * h)
    out = polynomial_eval(flat.coef, u) + slope / flat.scale * (x - xc)
    out = np.where(no_flat, x, out)
    dq = flat.dq.copy()
    dq[outside] |= DQ_DTYPE(DQ.OUT_OF_DOMAIN)
    with np.errstate(over="ignore"):  # beyond the float32 range: flagged below
        out = out.astype(np.float32)
    finite = np.isfinite(out)
    dq[~finite] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
    return np.where(finite, out, np.float32(0.0)), dq
