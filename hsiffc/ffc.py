"""Flat-field correction and the uniformity metric (array functions).

Two-point FFC is the paper's eq. (5): with R(L1) the dark, R(L2) the flat (training light) and
R(L3) the test image, ``R_new = Avg(L3) * (R(L3) - R(L1)) / (R(L2) - R(L1))``.
"""

from __future__ import annotations

import numpy as np

from .dq import DQ, DQ_DTYPE
from .uniformity import (FixedPattern, fixed_pattern_nonuniformity,  # noqa: F401 (re-export)
                         fixed_pattern_variance, uniformity_before_after)

NORMALISATIONS = ("paper", "mean_gain")


def two_point_gain(dark, flat, *, band_map=None):
    """Per-pixel gain ``mean(flat - dark) / (flat - dark)`` and DQ flags.

    The mean is taken per band when ``band_map`` is given (each band of a mosaic sees a
    different light). Pixels whose flat signal is not positive or not finite get gain 1.0 and
    the NO_FLAT flag (flag, never delete).

    Returns
    -------
    gain : (H, W) float32
    dq : (H, W) uint32
    """
    signal = np.asarray(flat, np.float64) - np.asarray(dark, np.float64)
    bad = ~np.isfinite(signal) | (signal <= 0)
    dq = np.zeros(signal.shape, DQ_DTYPE)
    dq[bad] |= DQ_DTYPE(DQ.NO_FLAT)
    ref = _band_mean(np.where(bad, np.nan, signal), band_map)
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(bad, 1.0, ref / signal)
    gain = np.where(np.isfinite(gain), gain, 1.0)
    return gain.astype(np.float32), dq


def two_point_correct(test, dark, flat, *, normalisation: str = "paper", band_map=None):
    """Two-point flat-field correction of ``test``.

    Parameters
    ----------
    test, dark, flat : (H, W) arrays, DN
        R(L3), R(L1) and R(L2) of eq. (5) (dark and flat usually averages of several frames).
    normalisation : "paper" or "mean_gain"
        ``"paper"``: eq. (5) exactly, ``Avg(L3) (R3 - R1) / (R2 - R1)`` (a relative image scaled
        by the test image's mean raw level); ``"mean_gain"``: ``(R3 - R1) mean(R2 - R1) /
        (R2 - R1)`` (dark-subtracted DN at the flat's mean gain: the common normalisation that
        keeps the signal in DN).
    band_map : (H, W) int, optional
        Averages are taken per band (a mosaic's bands see different light).

    Returns
    -------
    corrected : (H, W) float32
    dq : (H, W) uint32 (NO_FLAT where the flat cannot be used; those pixels keep the
         uncorrected dark-subtracted value times the scale)
    """
    if normalisation not in NORMALISATIONS:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}")
    test = np.asarray(test, np.float64)
    dark = np.asarray(dark, np.float64)
    flat = np.asarray(flat, np.float64)
    if not (test.shape == dark.shape == flat.shape):
        raise ValueError(f"test {test.shape}, dark {dark.shape} and flat {flat.shape} must have "
                         "the same shape; use dark and flat frames of the same sensor region")
    gain, dq = two_point_gain(dark, flat, band_map=band_map)
    signal = test - dark
    if normalisation == "mean_gain":
        return (signal * gain).astype(np.float32), dq
    # eq. (5): Avg(L3) * (R3 - R1) / (R2 - R1) = Avg(L3) * gain (R3 - R1) / mean(R2 - R1)
    flat_mean = _band_mean(np.where(dq == 0, flat - dark, np.nan), band_map)
    scale = _band_mean(test, band_map) / flat_mean
    return (signal * gain * scale).astype(np.float32), dq


def _band_mean(values, band_map):
    """Mean of ``values`` (NaN ignored) over the frame or per band, broadcast back per pixel."""
    values = np.asarray(values, np.float64)
    if band_map is None:
        return np.full(values.shape, np.nanmean(values))
    bm = np.asarray(band_map)
    ok = np.isfinite(values)
    n = int(bm.max()) + 1
    sums = np.bincount(bm[ok], weights=values[ok], minlength=n)
    cnts = np.bincount(bm[ok], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / cnts
    return means[bm]


def uniformity(image, mask=None) -> float:
    """Non-uniformity of eq. (6): ``100 * std / mean`` in percent over the (masked) pixels."""
    v = np.asarray(image, np.float64)
    if mask is not None:
        v = v[np.asarray(mask, bool)]
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return float(100.0 * v.std() / v.mean())


def uniformity_per_band(image, band_map, *, dq=None) -> np.ndarray:
    """Eq. (6) per band of a mosaic frame (pixels with any DQ bit set are left out)."""
    bm = np.asarray(band_map)
    good = np.ones(bm.shape, bool) if dq is None else (np.asarray(dq) == 0)
    return np.array([uniformity(image, (bm == b) & good) for b in range(int(bm.max()) + 1)])


def uniformity_improvement(before, after, band_map, *, dq=None) -> dict:
    """Eq. (6) per band before and after a stage, and the improvement (percentage points,
    positive = more uniform), as in the paper's Table II.

    ``before`` and ``after`` are (H, W) frames (e.g. a frame before and after flat-fielding);
    pixels with any bit of ``dq`` set are left out of both.

    Examples
    --------
    >>> bm = np.array([[0, 1], [0, 1]])
    >>> r = uniformity_improvement(np.array([[9., 20], [11, 20]]), np.full((2, 2), 10.), bm)
    >>> [round(v, 3) for v in r["improvement"]]
    [10.0, 0.0]
    """
    u_before = uniformity_per_band(before, band_map, dq=dq)
    u_after = uniformity_per_band(after, band_map, dq=dq)
    return {"before": u_before.tolist(), "after": u_after.tolist(),
            "improvement": (u_before - u_after).tolist()}
