"""Flat-field correction and the uniformity metric (array functions).

Two-point FFC is the paper's eq. (5): with R(L1) the dark, R(L2) the flat (training light) and
R(L3) the test image, ``R_new = Avg(L3) * (R(L3) - R(L1)) / (R(L2) - R(L1))``. It is split in
two so that a stage can learn once and apply to many frames: :func:`two_point_fit` learns the
per-pixel gain from a dark-subtracted flat, :func:`two_point_apply` applies it (element-wise);
:func:`two_point_correct` is both in one call, and the ``two_point_ffc`` stage runs the same two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..spectral.bandstats import band_layout, band_reduce
from ..data.dark import subtract_dark
from ..data.dq import DQ, DQ_DTYPE
from ..kernels.bands import band_scale_kernel, band_sums, phase_scale_kernel, scale_kernel
from ..kernels.launch import PARALLEL_MIN
from ..kernels.operands import flat_operands
from ..data.mosaic import row_period
from ..data.params import validate_method
from .uniformity import (
    FixedPattern,
    fixed_pattern_nonuniformity,
    fixed_pattern_variance,
    uniformity_before_after,
)

NORMALISATIONS = ("paper", "mean_gain")
#: flat-frame DQ bits that make a flat pixel unusable (it gets gain 1.0 and NO_FLAT)
UNUSABLE_FLAT = DQ.SATURATED | DQ.DEAD | DQ.HOT | DQ.DO_NOT_USE | DQ.NONFINITE


@dataclass(frozen=True)
class FlatField:
    """What :func:`two_point_fit` learns from a flat.

    Attributes
    ----------
    gain : (H, W) float32
        ``flat_mean[band] / flat signal``: 1.0 where the flat is unusable.
    flat_mean : (n_bands,) float64, DN
        Mean flat signal per band over the usable pixels (NaN for a band without one).
    dq : (H, W) uint32
        NO_FLAT where the flat is unusable, plus the flat's own unusable bits.
    """

    gain: np.ndarray
    flat_mean: np.ndarray
    dq: np.ndarray


def two_point_fit(flat_signal, *, band_map=None, flat_dq=None) -> FlatField:
    """Per-pixel two-point gain from a dark-subtracted flat.

    Parameters
    ----------
    flat_signal : (H, W) array_like, DN
        R(L2) - R(L1): the flat less its dark (usually averages of several frames).
    band_map : (H, W) int array, optional
        Means are taken per band (each band of a mosaic sees a different light).
    flat_dq : (H, W) uint32 array, optional
        DQ of the flat; pixels with a bit of :data:`UNUSABLE_FLAT` are not used.

    Returns
    -------
    FlatField
        Pixels whose flat signal is not positive, not finite or flagged get gain 1.0 and
        NO_FLAT (flag, never delete).
    """
    signal = np.asarray(flat_signal, np.float64)
    if signal.size == 0:
        raise ValueError(f"flat_signal is empty (shape {signal.shape}); give the flat of the "
                         "sensor region to correct")
    bad = ~np.isfinite(signal) | ~(signal > 0)
    dq = np.zeros(signal.shape, DQ_DTYPE)
    if flat_dq is not None:
        carried = np.asarray(flat_dq, DQ_DTYPE) & DQ_DTYPE(UNUSABLE_FLAT)
        bad |= carried != 0
        dq |= carried
    dq[bad] |= DQ_DTYPE(DQ.NO_FLAT)
    flat_mean = band_reduce(signal, band_map, ~bad)
    per_pixel = flat_mean[np.zeros(signal.shape, np.intp) if band_map is None else band_map]
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(bad, 1.0, per_pixel / signal)
    gain = np.where(np.isfinite(gain), gain, 1.0)
    return FlatField(gain.astype(np.float32), flat_mean, dq)


def paper_ratio(raw, flat_mean, *, band_map=None, good=None) -> np.ndarray:
    """The factor ``Avg(L3) / mean(R(L2) - R(L1))`` of eq. (5) per band.

    Parameters
    ----------
    raw : (H, W) array_like, DN
        The raw test image R(L3); Avg(L3) is its mean per band over ``good`` pixels.
    flat_mean : (n_bands,) array_like, DN
        :attr:`FlatField.flat_mean`.
    band_map : (H, W) int array, optional
    good : (H, W) bool array, optional

    Returns
    -------
    (n_bands,) float32
        1.0 (neutral) in a band where either mean is undefined.
    """
    return means_ratio(band_reduce(raw, band_map, good, n_bands=len(flat_mean)), flat_mean)


def means_ratio(test_mean, flat_mean) -> np.ndarray:
    """:func:`paper_ratio` from the test image's per-band mean ``Avg(L3)`` (DN, NaN where
    undefined) when it is known already (a fused pass takes it:
    :func:`hsiffc.leakage.validity.subtract_dark_and_flag`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.asarray(test_mean, np.float64) / np.asarray(flat_mean, np.float64)
    return np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0).astype(np.float32)


def paper_scale(raw, flat_mean, *, band_map=None, good=None) -> np.ndarray:
    """:func:`paper_ratio` per pixel: an (H, W) float32 map (each pixel its band's factor)."""
    bm = np.zeros(np.shape(raw), np.intp) if band_map is None else band_map
    return paper_ratio(raw, flat_mean, band_map=band_map, good=good)[bm]


def two_point_apply(signal, gain, scale=1.0, *, band_map=None, dq=None) -> np.ndarray:
    """Apply a two-point gain: ``signal * gain * scale`` element-wise (float32 DN).

    Parameters
    ----------
    signal : (H, W) array_like, DN
        The test image less its dark, R(L3) - R(L1).
    gain : (H, W) array_like
        :attr:`FlatField.gain`.
    scale : float, (H, W) array_like, or (n_bands,) array_like with ``band_map``
        1.0 for the ``"mean_gain"`` normalisation (DN at the flat's mean gain), or eq. (5)
        exactly: :func:`paper_scale` per pixel, or :func:`paper_ratio` per band with
        ``band_map`` (the same product, without building the per-pixel map).
    band_map : (H, W) int array, optional
        Band of each pixel, when ``scale`` is given per band.
    dq : (H, W) uint32 ndarray, optional
        The result's DQ, updated in place: where the product is not finite in float32 (NaN
        in, or beyond the float32 range) the value is set to 0 DN and flagged NONFINITE |
        DO_NOT_USE, as :meth:`hsiffc.data.frame.Frame.from_raw` does. Without it such values stay
        as they are.
    """
    if band_map is not None:
        sig = np.asarray(signal)
        bm = np.asarray(band_map)
        ratio = np.asarray(scale, np.float32).reshape(-1)
        if ratio.size == 0:
            raise ValueError("scale has no per-band factor; give one per band of band_map")
        if bm.shape != sig.shape or np.shape(gain) != sig.shape:
            raise ValueError(f"signal {sig.shape}, gain {np.shape(gain)} and band_map "
                             f"{bm.shape} must have the same shape")
        out = np.empty(sig.shape, np.float32)
        outside = (f"band_map has bands outside the {ratio.size} of scale; give the per-band "
                   "factors of every band of the map")
        period = row_period(band_map) if sig.ndim == 2 and sig.size >= PARALLEL_MIN else 0
        if period:  # a mosaic's map: each column's factor per row phase, no per-pixel lookup
            phase_bands = bm[:period]
            if phase_bands.min() < 0 or phase_bands.max() >= ratio.size:
                raise ValueError(outside)
            bad = phase_scale_kernel(np.ascontiguousarray(sig), np.ascontiguousarray(gain),
                                     ratio[phase_bands], out)
        else:
            flat = (lambda a, dt=None: np.ascontiguousarray(a, dt).reshape(-1))
            n_outside, bad = band_scale_kernel(flat(sig), flat(gain), ratio, flat(bm, np.int64),
                                               out.reshape(-1))
            if n_outside:
                raise ValueError(outside)
    else:
        shape, ops = flat_operands(signal, gain, scale, names=("signal", "gain", "scale"))
        out = np.empty(shape, np.float32)
        bad = scale_kernel(*ops, out.reshape(-1))  # one compiled pass
    if bad and dq is not None:  # rare: the pass counted them, so no test of every pixel
        if np.shape(dq) != out.shape:
            raise ValueError(f"dq has shape {np.shape(dq)} but the result has {out.shape}")
        nonfinite = ~np.isfinite(out)
        dq[nonfinite] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
        out[nonfinite] = 0.0
    return out


def two_point_gain(dark, flat, *, band_map=None):
    """Per-pixel gain ``mean(flat - dark) / (flat - dark)`` and DQ flags (see
    :func:`two_point_fit`).

    Parameters
    ----------
    dark, flat : (H, W) array_like, DN
        R(L1) and R(L2) of eq. (5), usually averages of several frames.
    band_map : (H, W) int array, optional
        The mean is taken per band.

    Returns
    -------
    gain : (H, W) float32
        1.0 where the flat is unusable.
    dq : (H, W) uint32
        NO_FLAT where the flat signal is not positive or not finite.

    Examples
    --------
    >>> gain, dq = two_point_gain(np.zeros((1, 3)), np.array([[90., 100, 110]]))
    >>> [round(float(g), 4) for g in gain[0]], dq.tolist()
    ([1.1111, 1.0, 0.9091], [[0, 0, 0]])
    """
    ff = two_point_fit(subtract_dark(flat, dark), band_map=band_map)
    return ff.gain, ff.dq


def two_point_correct(test, dark, flat, *, normalisation: str = "paper", band_map=None,
                      dq=None, flat_dq=None):
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
    dq : (H, W) uint32, optional
        DQ of the test image: flagged pixels are left out of Avg(L3).
    flat_dq : (H, W) uint32, optional
        DQ of the flat (see :func:`two_point_fit`).

    Returns
    -------
    corrected : (H, W) float32
    dq : (H, W) uint32 (the test's DQ, plus NO_FLAT where the flat cannot be used; those
         pixels keep the uncorrected dark-subtracted value times the scale)
    """
    validate_method(normalisation, NORMALISATIONS, "two-point normalisation")
    test, dark, flat = (np.asarray(v) for v in (test, dark, flat))
    if not (test.shape == dark.shape == flat.shape):
        raise ValueError(f"test {test.shape}, dark {dark.shape} and flat {flat.shape} must have "
                         "the same shape; use dark and flat frames of the same sensor region")
    ff = two_point_fit(subtract_dark(flat, dark), band_map=band_map, flat_dq=flat_dq)
    return two_point_correct_with(test, dark, ff, normalisation=normalisation,
                                  band_map=band_map, dq=dq)


def two_point_correct_with(test, dark, ff: FlatField, *, normalisation: str = "paper",
                           band_map=None, dq=None):
    """Eq. (5) of ``test`` with a flat fitted already (:func:`two_point_fit`): the apply half
    of :func:`two_point_correct`, and the ``"two_point"`` entry of
    :data:`hsiffc.flatfield.FFC_METHODS`.

    Parameters
    ----------
    test, dark : (H, W) arrays, DN
        R(L3) and R(L1) of eq. (5).
    ff : FlatField
    normalisation, band_map, dq
        As for :func:`two_point_correct`.

    Returns
    -------
    corrected : (H, W) float32
    dq : (H, W) uint32 (a new plane: ``ff.dq`` is not changed)
    """
    validate_method(normalisation, NORMALISATIONS, "two-point normalisation")
    out_dq = np.array(ff.dq, DQ_DTYPE) if dq is None else ff.dq | np.asarray(dq, DQ_DTYPE)
    scale = 1.0
    if normalisation == "paper":
        scale = paper_scale(test, ff.flat_mean, band_map=band_map, good=out_dq == 0)
    return two_point_apply(subtract_dark(test, dark), ff.gain, scale, dq=out_dq), out_dq


def uniformity(image, mask=None) -> float:
    """Non-uniformity of eq. (6): ``100 * std / mean`` in percent over the (masked) pixels.

    Parameters
    ----------
    image : array_like, DN
        Any shape; non-finite values are left out.
    mask : bool array of the same shape, optional
        Pixels to use.

    Returns
    -------
    float, percent
        NaN with fewer than 2 usable pixels. On a single frame this includes temporal noise;
        :func:`fixed_pattern_nonuniformity` takes it out.

    Examples
    --------
    >>> uniformity(np.array([9.0, 11.0]))
    10.0
    """
    v = np.asarray(image, np.float64)
    if mask is not None:
        v = v[np.asarray(mask, bool)]
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    return float(100.0 * v.std() / v.mean())


def uniformity_per_band(image, band_map, *, dq=None) -> np.ndarray:
    """Eq. (6) per band of a mosaic frame (pixels with any DQ bit set are left out).

    Parameters
    ----------
    image : (H, W) array_like, DN
    band_map : (H, W) int array
        Band index of every pixel (``Mosaic.band_map``).
    dq : (H, W) uint32 array, optional

    Returns
    -------
    (n_bands,) float64 ndarray, percent

    Examples
    --------
    >>> uniformity_per_band(np.array([[9., 20], [11, 20]]), np.array([[0, 1], [0, 1]])).tolist()
    [10.0, 0.0]
    """
    v = np.asarray(image)
    if v.dtype not in (np.float32, np.float64):
        v = v.astype(np.float64)
    bm, period, n = band_layout(v, band_map, dq, "dq")
    as2d = (lambda a: np.reshape(a, (1, -1) if a.ndim < 2 else (-1, a.shape[-1])))
    good = None if dq is None else as2d(np.asarray(dq) == 0)
    # two compiled passes over the good, finite pixels: the mean per band, then the mean
    # squared deviation from it (stable, unlike E[v^2] - mean^2); population std as np.std
    sums, counts = band_sums(as2d(v), as2d(bm), good, n, period)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sums / counts
        dev = np.square(v - mean[bm])
        var = band_sums(as2d(dev), as2d(bm), good, n, period)[0] / counts
        return np.where(counts >= 2, 100.0 * np.sqrt(var) / mean, np.nan)


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
