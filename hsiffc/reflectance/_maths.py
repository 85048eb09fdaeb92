"""Reflectance factor from a white reference (array functions).

A band's reflectance factor is the scene's light over the white panel's light, times the
panel's own reflectance factor, pixel by pixel (so each pixel's sensitivity cancels):

    R = R_panel * q_scene / q_white

where q is a rate that is proportional to the light. Two rates are offered:

- ``"ratio"``: DN above dark per ms, ``(Y - D) / t``. Right for a linear sensor; on a leaky
  pixel the white panel's response is bent below the line (the leakage grows as ``e^{bY}``), so
  targets darker than the panel come out too bright.
- ``"model"``: the light rate k recovered through the calibrated leakage model
  (:func:`hsiffc.leakage.linearise.linearise`: the model ``dY/dt = k - a e^{bY}`` inverted per pixel).
  k is linear in the light at every level the model describes, so the ratio is right for dark
  and bright targets alike; the inversion's noise grows like ``1 / (1 - alpha)`` near dynamic
  saturation.

Dividing rates also takes a scene and a reference at different exposures; with ``"ratio"`` that
assumes a linear response and a dark matched to each exposure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.dq import DQ, DQ_DTYPE

__all__ = ["WhiteReference", "white_reference", "reflectance_factor", "band_median",
           "band_fraction"]


@dataclass(frozen=True)
class WhiteReference:
    """A white reference at one exposure (:func:`white_reference`).

    Attributes
    ----------
    rate : ndarray, float32
        Rate per pixel (DN/ms for ``"ratio"``, light rate k in DN/ms for ``"model"``), > 0
        everywhere: pixels without a usable rate hold their band's median and NO_FLAT.
    dq : ndarray, uint32
        OR of the frames' flags, and NO_FLAT where the rate was replaced.
    sigma : ndarray, float32, or None
        Temporal standard deviation of one frame's rate per pixel (None with one frame).
    n_frames : int
    """

    rate: np.ndarray
    dq: np.ndarray
    sigma: np.ndarray | None
    n_frames: int


def band_median(values, bands, n_bands: int, good=None) -> np.ndarray:
    """Median of ``values`` per band over the good, finite values (NaN for an empty band).

    Parameters
    ----------
    values, bands : arrays of one shape
        Values and the band index of each (a mosaic's band map, or a cube's channel index).
    n_bands : int
    good : bool array of that shape, optional

    Returns
    -------
    (n_bands,) float64

    Examples
    --------
    >>> band_median(np.array([1., 2., 3., 10.]), np.array([0, 0, 0, 1]), 2).tolist()
    [2.0, 10.0]
    """
    v = np.asarray(values, np.float64)
    use = np.isfinite(v) if good is None else np.isfinite(v) & good
    out = np.full(n_bands, np.nan)
    for b in range(n_bands):
        sel = v[use & (bands == b)]
        if sel.size:
            out[b] = np.median(sel)
    return out


def band_fraction(mask, bands, n_bands: int) -> np.ndarray:
    """Fraction of each band's values where ``mask`` is true, (n_bands,) float64."""
    counts = np.bincount(np.ravel(bands), minlength=n_bands)[:n_bands]
    hits = np.bincount(np.ravel(bands), weights=np.ravel(mask).astype(np.float64),
                       minlength=n_bands)[:n_bands]
    return hits / np.maximum(counts, 1)


def white_reference(rates, dqs, bands, n_bands: int, *, average: str = "mean") -> WhiteReference:
    """Average a stack of white-reference rates into one reference.

    Parameters
    ----------
    rates : (N, ...) array_like
        One rate per frame and pixel (see the module docstring), N >= 1.
    dqs : (N, ...) uint32
        The frames' DQ planes.
    bands : int array, shape of one frame
        Band index of each value.
    n_bands : int
    average : "mean" or "median"
        The mean keeps the precision of integer data (a median of a few integer frames is
        itself nearly an integer).

    Returns
    -------
    WhiteReference

    Examples
    --------
    >>> ref = white_reference([[2.0, 0.0], [4.0, 0.0]], np.zeros((2, 2), np.uint32),
    ...                       np.array([0, 0]), 1)
    >>> ref.rate.tolist(), [int(d) for d in ref.dq]   # the dead pixel gets the band median
    ([3.0, 3.0], [0, 32])
    """
    r = np.asarray(rates, np.float64)
    if r.ndim < 2 or r.shape[0] < 1:
        raise ValueError(f"rates must be a stack (N, ...) of N >= 1 frames, got shape {r.shape}")
    n = r.shape[0]
    mean = np.median(r, axis=0) if (average == "median" and n >= 3) else r.mean(axis=0)
    sigma = r.std(axis=0, ddof=1).astype(np.float32) if n >= 2 else None
    dq = np.bitwise_or.reduce(np.asarray(dqs, DQ_DTYPE), axis=0)
    bad = ~(np.isfinite(mean) & (mean > 0))
    if bad.any():
        med = band_median(mean, bands, n_bands, good=~bad)
        fill = np.where(np.isfinite(med), med, np.nanmedian(np.where(bad, np.nan, mean))
                        if (~bad).any() else 1.0)
        mean = np.where(bad, fill[bands], mean)
        dq = dq | np.where(bad, DQ_DTYPE(DQ.NO_FLAT), DQ_DTYPE(0))
    return WhiteReference(mean.astype(np.float32), dq.astype(DQ_DTYPE), sigma, n)


def reflectance_factor(rate, white_rate, panel) -> np.ndarray:
    """``panel * rate / white_rate`` in float32 (the reflectance factor per value).

    Parameters
    ----------
    rate : array_like
        The scene's rate (same kind as the reference's).
    white_rate : array_like, > 0
        The white reference's rate (:attr:`WhiteReference.rate`).
    panel : array_like
        The panel's reflectance factor, broadcast to the values (per band).

    Returns
    -------
    ndarray of float32

    Examples
    --------
    >>> r = reflectance_factor(np.array([1.0, 2.0]), np.array([4.0, 4.0]), 0.99)
    >>> r.dtype, [round(v, 6) for v in r.tolist()]
    (dtype('float32'), [0.2475, 0.495])
    """
    out = np.asarray(rate, np.float64) * (np.asarray(panel, np.float64)
                                          / np.asarray(white_rate, np.float64))
    return out.astype(np.float32)
