"""The model-based flat field's training (array functions): each pixel's responsivity
relative to its band's, combined from the sweep fit and from flat stacks
(:func:`model_flat_fit`). The correction that uses it, and what limits both, are in
:mod:`hsiffc.flatfield.model_based`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..leakage import model
from ..data.bandstats import band_reduce
from ..data.dq import DQ, DQ_DTYPE

__all__ = ["UNUSABLE", "FlatStack", "ModelFlat", "flat_responsivity", "model_flat_fit",
           "relative_responsivity"]

#: calibration flags that make a pixel's responsivity unusable (gain 1 and NO_FLAT)
UNUSABLE = DQ.DO_NOT_USE | DQ.NOT_CONVERGED


@dataclass(frozen=True)
class FlatStack:
    """A flat stack as the fit needs it: many frames of one uniform light at one exposure.

    Attributes
    ----------
    mean_response : (H, W) float, DN
        Mean raw response of the frames (dark not removed).
    temporal_var : (H, W) float, DN^2
        Temporal variance of one frame (per pixel, over the frames).
    n_frames : int
    exposure_ms : float
    dark : (H, W) float, DN
        Level the response starts from (the dark removed, or the calibration's at ``t``).
    usable : (H, W) bool
        Pixels never clipped or flagged in any frame.
    """

    mean_response: np.ndarray
    temporal_var: np.ndarray
    n_frames: int
    exposure_ms: float
    dark: np.ndarray
    usable: np.ndarray

    @classmethod
    def from_arrays(cls, frames, exposure_ms: float, dark, *, usable=None) -> "FlatStack":
        """From a (N, H, W) stack of raw responses (DN) at one exposure."""
        s = np.asarray(frames, np.float64)
        if s.ndim != 3 or s.shape[0] < 2:
            raise ValueError(f"a flat stack is (N >= 2, H, W) frames, got shape {s.shape}")
        ok = np.isfinite(s).all(axis=0)
        if usable is not None:
            ok &= np.asarray(usable, bool)
        return cls(s.mean(axis=0), s.var(axis=0, ddof=1), int(s.shape[0]), float(exposure_ms),
                   np.broadcast_to(np.asarray(dark, np.float64), s.shape[1:]), ok)


@dataclass(frozen=True)
class ModelFlat:
    """Fitted model-based flat field.

    Attributes
    ----------
    gain : (H, W) float32
        ``mean_band(g) / g`` from all the training data: multiplies the linearised signal
        ``k t`` (1 where unusable).
    gain_sweep : (H, W) float32
        The same from the calibration's sweep alone (used where leakage bends the response;
        see :func:`model_ffc_apply`).
    sigma_ln_gain : (H, W) float32
        1-sigma relative uncertainty of ``gain`` (its contribution to the corrected frame's
        fixed pattern, as a fraction).
    sigma_ln_sweep : (H, W) float32
        The sweep fit's part (``sigma_ln_g`` of the calibration, plus the model inconsistency).
    flat_weight : (H, W) float32
        Share of the flat stacks in the combined estimate (0 without flats).
    dq : (H, W) uint32
        NO_FLAT where no responsivity could be estimated.
    summary : dict
        Per band: median uncertainties (percent), model inconsistency, flat levels (DN).
    """

    gain: np.ndarray
    gain_sweep: np.ndarray
    sigma_ln_gain: np.ndarray
    sigma_ln_sweep: np.ndarray
    flat_weight: np.ndarray
    dq: np.ndarray
    summary: dict


def relative_responsivity(responsivity, band_map, good) -> np.ndarray:
    """``g / mean_band(g)`` over the good pixels (NaN where g is not positive and finite)."""
    g = np.asarray(responsivity, np.float64)
    ok = np.asarray(good, bool) & np.isfinite(g) & (g > 0)
    mean = band_reduce(g, band_map, ok)[band_map]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, g / mean, np.nan)


def flat_responsivity(flat: FlatStack, a, b, band_map, good) -> tuple[np.ndarray, np.ndarray]:
    """Relative responsivity from one flat stack and its 1-sigma error in ln g.

    The stack's mean response is inverted with the pixel's leakage model (so a flat bent by
    leakage still gives the rate), ``k / mean_band(k)``; its error is the temporal noise of the
    mean, ``sqrt(var / N) / (dY / d ln k)``.

    Returns
    -------
    g_rel : (H, W) float64 (NaN where unusable)
    sigma_ln : (H, W) float64 (inf where unusable)
    """
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    inv = model.invert_response(flat.mean_response, flat.exposure_ms, a64, b64, flat.dark)
    k = inv.k
    ok = np.asarray(good, bool) & flat.usable & (inv.flags == 0) & (k > 0)
    _, dy_dlnk, *_ = model.response_and_gradient(flat.exposure_ms, np.where(ok, k, 1.0), a64,
                                                 b64, flat.dark)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma = np.sqrt(flat.temporal_var / flat.n_frames) / dy_dlnk
    ok &= np.isfinite(sigma) & (sigma > 0)
    g_rel = relative_responsivity(np.where(ok, k, np.nan), band_map, ok)
    return g_rel, np.where(ok, sigma, np.inf)


def _robust_var(x) -> float:
    x = x[np.isfinite(x)]
    if x.size < 10:
        return float("nan")
    return float((1.4826 * np.median(np.abs(x - np.median(x)))) ** 2)


def model_flat_fit(responsivity, sigma_ln_g, a, b, band_map, *, flags=None,
                   flats=()) -> ModelFlat:
    """Per-pixel correction factor from the calibration's responsivity and any flat stacks.

    Parameters
    ----------
    responsivity, sigma_ln_g : (H, W) array_like
        The calibration's ``responsivity`` (DN/ms per unit of relative light rate) and the 1-sigma
        error of its log from the sweep fit.
    a, b : (H, W) array_like
        Leakage amplitude (DN/ms) and exponent (1/DN), used to invert the flat stacks.
    band_map : (H, W) int
    flags : (H, W) uint32, optional
        Calibration DQ flags: DO_NOT_USE / NOT_CONVERGED pixels get gain 1 and NO_FLAT.
    flats : sequence of FlatStack

    Returns
    -------
    ModelFlat
    """
    bm = np.asarray(band_map)
    n_bands = int(bm.max()) + 1
    f = np.zeros(bm.shape, DQ_DTYPE) if flags is None else np.asarray(flags, DQ_DTYPE)
    good = (f & DQ_DTYPE(UNUSABLE)) == 0
    g_sweep = relative_responsivity(responsivity, bm, good)
    s_sweep = np.asarray(sigma_ln_g, np.float64)
    s_sweep = np.where(np.isfinite(s_sweep) & (s_sweep > 0), s_sweep, np.inf)
    s_sweep = np.where(np.isfinite(g_sweep), s_sweep, np.inf)
    excess = np.zeros(n_bands)
    flat_est = []
    for flat in flats:
        g_f, s_f = flat_responsivity(flat, a, b, bm, good)
        flat_est.append((flat, g_f, s_f))
        # how far the sweep model and this flat disagree beyond their stated noise
        both = np.isfinite(g_f) & np.isfinite(g_sweep) & np.isfinite(s_sweep) & np.isfinite(s_f)
        d = np.log(g_sweep) - np.log(g_f)
        for band in range(n_bands):
            sel = both & (bm == band)
            expected = float(np.median(s_sweep[sel] ** 2 + s_f[sel] ** 2)) if sel.any() else 0.0
            excess[band] = max(excess[band], _robust_var(d[sel]) - expected
                               if sel.sum() >= 10 else 0.0)
    s_sweep_eff = np.sqrt(s_sweep ** 2 + np.nan_to_num(excess)[bm])
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.isfinite(g_sweep), 1.0 / s_sweep_eff ** 2, 0.0)
        acc = np.where(w > 0, w * np.log(g_sweep), 0.0)
    w_flat = np.zeros(bm.shape)
    for _, g_f, s_f in flat_est:
        wf = np.where(np.isfinite(g_f), 1.0 / s_f ** 2, 0.0)
        acc = acc + np.where(wf > 0, wf * np.log(np.where(wf > 0, g_f, 1.0)), 0.0)
        w_flat = w_flat + wf
    total = w + w_flat
    usable = total > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_g = np.where(usable, acc / total, 0.0)
        sigma = np.where(usable, 1.0 / np.sqrt(total), 0.0)
        share = np.where(usable, w_flat / total, 0.0)
    # unweighted sweep case (no sigma_ln_g at all): fall back to the plain sweep estimate
    plain = ~usable & np.isfinite(g_sweep)
    ln_g = np.where(plain, np.log(np.where(plain, g_sweep, 1.0)), ln_g)
    usable |= plain
    g = np.where(usable, np.exp(ln_g), np.nan)
    g = relative_responsivity(g, bm, usable)  # back to band mean 1 after combining
    dq = np.zeros(bm.shape, DQ_DTYPE)
    dq[~np.isfinite(g)] |= DQ_DTYPE(DQ.NO_FLAT)
    gain = np.where(np.isfinite(g), 1.0 / g, 1.0)
    gain_sweep = np.where(np.isfinite(g_sweep) & np.isfinite(g), 1.0 / g_sweep, gain)
    summary = _summary(bm, n_bands, usable, sigma, s_sweep, s_sweep_eff, excess, flat_est)
    return ModelFlat(gain.astype(np.float32), gain_sweep.astype(np.float32),
                     sigma.astype(np.float32),
                     np.where(np.isfinite(s_sweep_eff), s_sweep_eff, 0).astype(np.float32),
                     share.astype(np.float32), dq, summary)


def _summary(bm, n_bands, usable, sigma, s_sweep, s_sweep_eff, excess, flat_est) -> dict:
    def med(x, band):
        v = x[usable & (bm == band) & np.isfinite(x)]
        return float(100 * np.median(v)) if v.size else float("nan")

    def rms(x, band):
        v = x[usable & (bm == band) & np.isfinite(x)]
        return float(100 * np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

    rows = []
    for band in range(n_bands):
        row = {"band": band, "sigma_combined_rms_percent": rms(sigma, band),
               "sigma_sweep_median_percent": med(s_sweep, band),
               "model_inconsistency_percent": float(100 * np.sqrt(max(excess[band], 0.0))),
               "sigma_sweep_effective_median_percent": med(s_sweep_eff, band)}
        for i, (flat, _, s_f) in enumerate(flat_est):
            sel = bm == band
            row[f"flat{i}_sigma_median_percent"] = med(s_f, band)
            row[f"flat{i}_level_dn"] = float(np.median((flat.mean_response - flat.dark)[sel]))
        rows.append(row)
    return {"bands": rows, "n_flat_stacks": len(flat_est),
            "flat_frames": [int(f.n_frames) for f, _, _ in flat_est]}
