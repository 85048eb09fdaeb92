"""Model-based flat-field correction (array functions): the calibration's responsivity map.

Two-point FFC (eq. 5) learns one gain per pixel from one flat level, with the flat's temporal
noise printed into every corrected frame and, once leakage bends the response, a gain that is
right only at the flat's own level. The calibration already holds each pixel's whole response
model, ``dY/dt = k - a e^{bY}`` with ``k = g r`` (responsivity g times the light's relative rate
r) from a fit over a whole sweep. The model-based correction uses it:

1. invert the model per pixel: the light rate k that explains the response Y at exposure t,
   starting from the dark level (:func:`hsiffc.leakage.model.invert_response`);
2. divide by the pixel's responsivity relative to its band's mean, ``g / mean_band(g)``;
3. return ``k t mean_band(g) / g``: DN above dark on the band-mean scale, linear in the light,
   at the frame's exposure. A uniform scene gives a uniform frame at every level the model
   describes, and a spectrum keeps its shape however far leakage bent the raw response.

The relative responsivity is estimated from all training data
(:func:`model_flat_fit`, below): the sweep fit's ``g`` (with its uncertainty
``sigma_ln_g``) and, where flat stacks are given (many frames at one level), each stack's own
estimate ``k_flat / mean_band(k_flat)`` with its temporal noise. They are combined per pixel
with inverse-variance weights in ln g. The spread of the difference between the two estimates
beyond their stated noise is a per-band model inconsistency; it is added to the sweep's
variance, so a flat stack is never outweighed by a model that does not match it at its own
level.

What limits it. Where the response is linear (model alpha up to ``flat_alpha_percent``) the
error of the combined factor and of the dark (:func:`correction_uncertainty`), which model_ffc
reaches on the simulated sensor of the tests. Where leakage bends the response the
correction rests on the sweep's fitted a and b, whose errors are strongly correlated with each
other (about -0.998) and with g; the calibration stores per-parameter sigmas only, so that part
of the floor cannot be computed from the calibration. :mod:`hsiffc.flatfield.floor` computes it from
the sweep's design (the fit's Cramer-Rao bound with the full covariance); model_ffc reaches it
too, and it rises with alpha. Lowering it needs more information on a and b (more frames or
light levels in the bent part of the sweep), not another estimator: shrinking each pixel's a
and b towards its band's makes their errors smaller but moves the model away from the samples,
which raises the fixed pattern where leakage bends the response.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..leakage import model
from ..spectral.bandstats import band_reduce
from ..data.dq import DQ, DQ_DTYPE
from ..errors import ParameterError
from ..kernels.leakage import BLOCK
from ..kernels.modelffc import (CorrectionLimits, CorrectionOutputs, Factors, PixelModel,
                                model_ffc_finish, model_ffc_kernel, pending_indices)
from ..kernels.operands import flat_operands

#: convergence tolerance (DN) of the leakage inversion inside the correction
_TOL_DN = 1e-9

__all__ = ["UNUSABLE", "FlatStack", "ModelFlat", "correction_uncertainty", "flat_responsivity",
           "log_gain_ratio", "model_ffc_apply", "model_flat_fit", "model_flat_of",
           "relative_responsivity"]

def log_gain_ratio(gain, gain_sweep) -> np.ndarray:
    """``ln(gain / gain_sweep)`` as :func:`model_ffc_apply` blends the two factors with it
    (float32: the ratio is near 1, so its error, below 1e-8 of the factor, is under the
    float32 output's resolution). A caller correcting many frames keeps it."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(np.asarray(gain, np.float64) / np.asarray(gain_sweep, np.float64)).astype(
            np.float32)


def model_ffc_apply(response, exposure_ms: float, a, b, dark, gain, *, gain_sweep=None,
                    flat_alpha_percent: float = 5.0, dark_current=0.0, full_scale_dn=None,
                    alpha_limit_percent: float = 50.0, below_dark_tolerance_dn: float = 1.0,
                    log_ratio=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correct one frame: ``k t * gain`` in DN above dark on the band-mean scale.

    Where the response is bent by leakage the correction rests on the fitted a and b, whose
    errors are correlated with the sweep fit's own g (one joint fit); a flat stack's g, measured
    where the response is linear, does not share them. So the factor moves from ``gain`` (all
    training data) to ``gain_sweep`` as the model alpha of the response grows:
    ``ln f = ln gain_sweep + w (ln gain - ln gain_sweep)`` with ``w = max(0, 1 - alpha /
    flat_alpha_percent)``. On the real EMVA 1288 sweep (held-out steps) the flat stack's weight
    that minimises the fixed pattern indeed falls from its noise-optimal value below 1 % alpha to
    zero near 6 % (see ``docs``/the FFC study).

    Parameters
    ----------
    response : (H, W) array_like, DN
        Raw response Y (dark not removed).
    exposure_ms : float, ms
    a, b : (H, W) array_like
        Leakage amplitude (DN/ms) and exponent (1/DN).
    dark : (H, W) array_like, DN
        Level the response starts from at t = 0 (a master dark, or the calibration's dark).
    gain : (H, W) array_like
        :attr:`~hsiffc.flatfield.model_based.ModelFlat.gain`.
    gain_sweep : (H, W) array_like, optional
        :attr:`~hsiffc.flatfield.model_based.ModelFlat.gain_sweep` (None: ``gain`` at every level).
    flat_alpha_percent : float
        Model alpha (percent) at which the flat stacks' share has gone to zero.
    dark_current : (H, W) array_like or float, DN/ms
        Subtracted from the recovered rate (0 when ``dark`` is a master dark at this exposure).
    full_scale_dn : float, optional
        Clipped responses (at or above it) are flagged SATURATED (value: the rate that just
        reaches full scale, a lower bound).
    alpha_limit_percent : float
        Responses whose model leakage percentage exceeds it are flagged LEAKAGE (noise is
        amplified like ``1 / (1 - alpha)`` there); their value is still the best estimate.
    below_dark_tolerance_dn : float
        Responses further than this below the zero-light level are flagged BELOW_DARK; closer
        ones are read noise and keep their (negative) linear value.
    log_ratio : (H, W) array_like, optional
        :func:`log_gain_ratio` of ``gain`` and ``gain_sweep``, if the caller keeps it (saves a
        logarithm per pixel and frame); computed here when not given.

    Returns
    -------
    corrected : (H, W) float32, DN (finite everywhere)
    dq : (H, W) uint32
    alpha : (H, W) float32, percent (model alpha; float32 max where undefined)
    """
    if not (np.isfinite(exposure_ms) and exposure_ms >= 0):
        raise ValueError(f"exposure_ms must be a finite time >= 0 in ms, got {exposure_ms!r}; "
                         "give the frame's exposure time in milliseconds")
    if exposure_ms == 0:  # no light was integrated: nothing to invert, only the offset
        with np.errstate(over="ignore"):  # beyond float32: flagged below
            out = ((np.asarray(response, np.float64) - np.asarray(dark, np.float64))
                   * np.asarray(gain, np.float64)).astype(np.float32)
        finite = np.isfinite(out)
        dq = np.zeros(out.shape, DQ_DTYPE)
        dq[~finite] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
        return np.where(finite, out, np.float32(0.0)), dq, np.zeros(out.shape, np.float32)
    has_sweep = gain_sweep is not None
    if has_sweep and log_ratio is None:
        log_ratio = log_gain_ratio(gain, gain_sweep)
    shape, ops = flat_operands(response, exposure_ms, a, b, dark,
                               gain_sweep if has_sweep else gain,
                               log_ratio if has_sweep else 0.0, dark_current,
                               names=("response", "exposure_ms", "a", "b", "dark",
                                      "gain_sweep" if has_sweep else "gain", "log_ratio",
                                      "dark_current"))
    full_scale = np.inf if full_scale_dn is None else float(full_scale_dn)
    limits = (float(flat_alpha_percent), float(alpha_limit_percent),
              float(below_dark_tolerance_dn))
    out = np.empty(shape, np.float32)
    dq = np.empty(shape, DQ_DTYPE)
    alpha = np.empty(shape, np.float32)
    flat = (out.reshape(-1), dq.reshape(-1), alpha.reshape(-1))
    left = np.zeros(max(1, -(-out.size // BLOCK)), np.int64)
    # the kernels' operands in named groups (hsiffc.kernels.modelffc)
    groups = (PixelModel(*ops[:5]), Factors(*ops[5:], has_sweep),
              CorrectionLimits(full_scale, *limits, _TOL_DN), CorrectionOutputs(*flat))
    if model_ffc_kernel(*groups, left):
        # what the vector steps left (scanned in the blocks that have some): the bracketed
        # inversion, then the same step
        idx = pending_indices(flat[1], left)
        y, t, a_, b_, d = (v if isinstance(v, float) else v[idx] for v in ops[:5])
        inv = model.invert_response(y, t, a_, b_, d, full_scale=full_scale_dn, tol_dn=_TOL_DN)
        model_ffc_finish(idx, np.atleast_1d(inv.k), np.atleast_1d(inv.flags), *groups)
    return out, dq, alpha


def correction_uncertainty(response, exposure_ms: float, a, b, dark, sigma_ln_gain, *,
                           sigma_dark_dn=0.0) -> np.ndarray:
    """1-sigma relative error (fraction) of each corrected pixel from the calibration's noise.

    The factor's own error (``sigma_ln_gain``) and the dark level's error propagated through
    the inversion at this response, ``d ln k = -(dY/d dark) d dark / (dY/d ln k)``, in
    quadrature. Its RMS over a band is the fixed-pattern floor the calibration sets for a
    uniform scene at this level: the dark term dominates at low signal, the factor's error in
    the linear range. Where leakage bends the response the errors of the fitted a and b add;
    they are not included (the calibration stores their sigmas but not their strong mutual
    correlation, and without it the propagated error is far too large): for that floor use
    :func:`hsiffc.flatfield.floor.sweep_floor` with the sweep's design.

    Parameters
    ----------
    response : (H, W) array_like, DN
    exposure_ms : float, ms (> 0)
    a, b, dark : (H, W) array_like
    sigma_ln_gain : (H, W) array_like
        :attr:`~hsiffc.flatfield.model_based.ModelFlat.sigma_ln_gain`.
    sigma_dark_dn : (H, W) array_like or float
        The calibration's ``sigma_dark_dn``.

    Returns
    -------
    (H, W) float64 (inf where the response cannot be inverted)
    """
    y = np.asarray(response, np.float64)
    a64, b64, d64 = (np.asarray(v, np.float64) for v in (a, b, dark))
    inv = model.invert_response(y, exposure_ms, a64, b64, d64)
    _, dy_lnk, _, _, dy_d = model.response_and_gradient(
        exposure_ms, np.maximum(inv.k, 1e-300), a64, b64, d64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dark_part = dy_d * np.nan_to_num(np.asarray(sigma_dark_dn, np.float64)) / dy_lnk
    out = np.sqrt(np.asarray(sigma_ln_gain, np.float64) ** 2 + dark_part ** 2)
    return np.where(np.isfinite(out) & (inv.k > 0), out, np.inf)


# -- the training: each pixel's responsivity relative to its band's ----------------------

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
    sigma_ln_sweep : (H, W) float32 or None
        The sweep fit's part (``sigma_ln_g`` of the calibration, plus the model inconsistency);
        None where it was taken from a calibration that carries the combined factors only
        (:func:`model_flat_of`).
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
    sigma_ln_sweep: np.ndarray | None
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


def model_flat_of(calibration, *, band_map=None, flats=(),
                  who: str = "flat-field method 'model'") -> ModelFlat:
    """What the model-based flat field learns from a calibration and any flat stacks: the
    ``learn`` of ``"model"`` in :data:`hsiffc.flatfield.FFC_METHODS` (no flat stack) and the
    fit of the ``model_ffc`` stage.

    Without flat stacks, a calibration that carries the flat stacks of its sweep
    (:func:`hsiffc.calibrate.flats.add_flat_stacks` folds them in) gives the factors combined
    then; otherwise :func:`model_flat_fit` combines the calibration's responsivity with
    ``flats``.

    Parameters
    ----------
    calibration : Calibration
        With a ``responsivity`` map (``hsiffc calibrate``, method joint).
    band_map : (H, W) int, optional
        Default: the calibration's mosaic over its frame (one band without a mosaic).
    flats : sequence of FlatStack
    who : str
        Names the caller in the error message.

    Returns
    -------
    ModelFlat

    Raises
    ------
    ParameterError
        The calibration has no ``responsivity`` map.
    """
    arrays = calibration.arrays
    if "responsivity" not in arrays:
        raise ParameterError(f"{who}: the calibration has no 'responsivity' map; make it with "
                             "'hsiffc calibrate' (method joint)")
    if not flats and "flat_gain" in arrays:
        return ModelFlat(arrays["flat_gain"], arrays["flat_gain_sweep"],
                         arrays["sigma_ln_flat_gain"], None, arrays["flat_weight"],
                         arrays["flat_dq"], calibration.fitted_on.get("flat_summary", {}))
    if band_map is None:
        band_map = (calibration.mosaic.band_map(calibration.frame_shape) if calibration.mosaic
                    else np.zeros(calibration.frame_shape, np.int64))
    return model_flat_fit(arrays["responsivity"], arrays.get("sigma_ln_g"), calibration.a,
                          calibration.b, band_map, flags=arrays.get("flags"), flats=flats)


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
