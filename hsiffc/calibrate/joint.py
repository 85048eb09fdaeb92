"""Joint per-pixel fit of the leakage model to a whole sweep: the public fit API.

Every pixel p and sample s share one model::

    Y[s, p] = response(t[s], g[p] * r[s] + dc[p], a[p], b[p], d[p])        (dark in the well)
    Y[s, p] = response(t[s], g[p] * r[s], a[p], b[p], d[p]) + dc[p] t[s]   (additive dark)

with ``t`` the exposure (ms), ``r`` the sample's relative light rate (photons per ms in EMVA
1288 data; 1 for a single illumination; 0 for dark samples), per-pixel unknowns ``g`` (DN per
unit of r, so ``k = g r`` in DN/ms), leakage ``a`` (DN/ms), ``b`` (1/DN), dark level ``d`` (DN)
and a dark current ``dc`` (DN/ms) measured from the dark samples.

:func:`fit_pixels` runs the per-pixel kernel of :mod:`hsiffc.kernels.pixelfit` (dark model, linear
model, start values, Levenberg-Marquardt with bounds and a fallback to the linear model);
:func:`model_and_jacobian` and :func:`predict` evaluate the model for per-pixel parameters
``theta = (ln g, ln a, ln b, d)``. All build on :mod:`hsiffc.leakage.model`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..leakage import model
from ..kernels import pixelfit, pixelsamples

PRIOR_SIGMA = 3.0  # e-folds, on ln a and ln b
PARAMS = ("ln_g", "ln_a", "ln_b", "dark")
DARK_MODELS = ("in_well", "additive")
B_GRID = (0.002, 0.005, 0.01, 0.02, 0.05)  # 1/DN, start values tried for b
MARGIN_GRID = (0.5, 3.0)  # saturation placed this many 1/b above the highest valid sample


@dataclass(frozen=True, eq=False)
class JointFit:
    """Per-pixel result of :func:`fit_pixels` (arrays of shape (P,)).

    ``a`` is 0 where the linear model was used (see ``status`` and
    :data:`hsiffc.kernels.pixelfit.STATUS_REASONS`); parameters are NaN where no fit was possible.
    """

    g: np.ndarray  # DN/ms per unit relative light rate
    a: np.ndarray  # DN/ms
    b: np.ndarray  # 1/DN
    dark: np.ndarray  # DN
    sigma: np.ndarray  # (P, 4) standard errors of (ln g, ln a, ln b, dark)
    rms_dn: np.ndarray  # unweighted RMS residual over all valid samples, DN
    chi2_red: np.ndarray  # weighted residual sum of squares per degree of freedom
    n_valid: np.ndarray
    converged: np.ndarray
    leak_constrained: np.ndarray
    iterations: int
    status: np.ndarray  # uint8 fit status code per pixel
    dark_current: np.ndarray  # DN/ms used for each pixel
    chi2: np.ndarray  # weighted residual sum of squares of the model used
    chi2_linear: np.ndarray  # ... of the plain linear model on the same samples
    r_ref: np.ndarray  # highest relative light rate among the fitted light samples (0: none)

    @property
    def theta(self) -> np.ndarray:
        """(P, 4) parameters (ln g, ln a, ln b, d); ln a is -inf where the linear model was
        used."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.column_stack([np.log(self.g), np.log(self.a), np.log(self.b), self.dark])


def model_and_jacobian(theta, t_ms, r, dark_current=0.0):
    """Model response (P, S) and its Jacobian (P, S, 4) with respect to (ln g, ln a, ln b, d).

    Parameters
    ----------
    theta : (P, 4) float
        Per-pixel (ln g, ln a, ln b, dark) with g in DN/ms per unit of relative light rate,
        a in DN/ms, b in 1/DN, dark in DN.
    t_ms : (S,) or (P, S) float
        Exposure of each sample (ms, >= 0).
    r : (S,) or (P, S) float
        Relative light rate of each sample (0 for darks).
    dark_current : float or (P, 1) float
        Fixed dark current (DN/ms) added to the light rate, k = g r + dark_current.

    Returns
    -------
    y : (P, S) float64, DN
    jac : (P, S, 4) float64
        The derivative with respect to ln g acts on the light part of k only.
    """
    theta = np.asarray(theta, np.float64)
    ln_g, ln_a, ln_b, d = (theta[:, i:i + 1] for i in range(4))
    kg = np.exp(ln_g) * r
    k = kg + dark_current
    y, dlnk, dlna, dlnb, dd = model.response_and_gradient(t_ms, k, np.exp(ln_a), np.exp(ln_b), d)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(k > 0, kg / np.where(k > 0, k, 1.0), 0.0)
    return y, np.stack([dlnk * share, dlna, dlnb, dd], axis=-1)


def predict(theta, t_ms, r, dark_current=0.0):
    """Model response (P, S) in DN of per-pixel parameters ``theta`` (see
    :func:`model_and_jacobian`)."""
    theta = np.asarray(theta, np.float64)
    ln_g, ln_a, ln_b, d = (theta[:, i:i + 1] for i in range(4))
    with np.errstate(over="ignore", invalid="ignore"):
        return model.response(t_ms, np.exp(ln_g) * r + dark_current, np.exp(ln_a), np.exp(ln_b),
                              d)


def _kernel_inputs(y, t_ms, r, valid, weight):
    """(S, P) samples, validity and weights for the kernel, and the per-step arrays."""
    y = np.asarray(y, np.float64)
    if y.ndim != 2:
        raise ValueError(f"y must be (pixels, samples), got shape {y.shape}")
    s_count = y.shape[1]
    t = np.asarray(t_ms, np.float64)
    r = np.asarray(r, np.float64)
    if t.shape != (s_count,) or r.shape != (s_count,):
        raise ValueError(f"t_ms and r must be per sample, shape ({s_count},); got {t.shape} and "
                         f"{r.shape}")
    step_ok = np.isfinite(t) & (t >= 0) & np.isfinite(r) & (r >= 0)
    w = np.broadcast_to(np.asarray(weight, np.float64), y.shape)
    ok = np.asarray(valid, bool) & np.isfinite(y) & step_ok[None, :] & (w > 0) & np.isfinite(w)
    t_k = np.where(step_ok, t, 0.0)
    r_k = np.where(step_ok, r, 0.0)
    return {"y": np.ascontiguousarray(y.T), "valid": np.ascontiguousarray(ok.T),
            "w": np.ascontiguousarray(np.where(ok, w, 0.0).T), "t": t_k, "r": r_k,
            "light": step_ok & (r_k > 0), "dark": step_ok & (r_k == 0)}


def _dark_current_args(dark_current, p_count):
    """(estimate?, per-pixel dark current (P,)) for the kernels."""
    estimate = isinstance(dark_current, str)
    if estimate and dark_current != "estimate":
        raise ValueError(f"dark_current must be None, 'estimate' or per-pixel values, got "
                         f"{dark_current!r}")
    if dark_current is None or estimate:
        return estimate, np.zeros(p_count)
    # a writable copy: a read-only array (broadcast_to gives one) is another numba type, and
    # the fit kernel would compile a second build for it
    return estimate, np.array(np.broadcast_to(
        np.asarray(dark_current, np.float64).ravel(), (p_count,)))


def _weight_args(w, n_frames, noise, s_count):
    """(weights or an empty array, frames per step, gain, read variance) for the kernels."""
    if w is not None:
        return w, np.ones(s_count), 0.0, 1.0
    gain, read_var = noise if noise is not None else (0.0, 1.0)
    nfr = np.ones(s_count) if n_frames is None else np.asarray(n_frames, np.float64)
    return np.empty((0, 0)), nfr, gain, read_var


def run_kernel(y, valid, t, r, light, dark, *, w=None, n_frames=None, noise=None,
               dark_current=None, dark_model="in_well", theta0=None, b_start=None,
               margins=MARGIN_GRID, max_iter=200, tol=1e-9, prior_sigma=PRIOR_SIGMA,
               fallback=True, merge_darks=True, fix_dark=False) -> JointFit:
    """Run :func:`hsiffc.kernels.pixelfit.fit_block` on (S, P) samples; returns the fit.

    Weights are ``w`` (S, P), or come from ``noise = (gain DN/e-, read variance DN^2)`` and
    ``n_frames`` (S,) per step. See :func:`fit_pixels` for the other arguments.
    """
    if dark_model not in DARK_MODELS:
        raise ValueError(f"dark_model must be one of {DARK_MODELS}, got {dark_model!r}")
    s_count, p_count = y.shape
    estimate, dc_in = _dark_current_args(dark_current, p_count)
    th0 = (np.empty((0, 4)) if theta0 is None
           else np.ascontiguousarray(np.asarray(theta0, np.float64).reshape(p_count, 4)))
    b_starts = np.atleast_1d(np.asarray(B_GRID if b_start is None else b_start, np.float64))
    w, nfr, gain, read_var = _weight_args(w, n_frames, noise, s_count)
    out_f = np.empty((p_count, 13))
    out_i = np.empty((p_count, 3), np.int32)
    samples, steps, noise_model = _sample_groups(y, valid, w, nfr, gain, read_var, t, r, light,
                                                 dark)
    pixelfit.fit_block(
        samples, steps, noise_model,
        pixelfit.DarkModel(bool(merge_darks), estimate, dc_in, dark_model == "additive"),
        pixelfit.Starts(b_starts, np.atleast_1d(np.asarray(margins, np.float64)), th0),
        pixelfit.FitControl(float(prior_sigma), int(max_iter), float(tol), bool(fallback),
                            bool(fix_dark)),
        pixelfit.FitOutputs(out_f, out_i))
    return _to_fit(out_f, out_i)


def _sample_groups(y, valid, w, nfr, gain, read_var, t, r, light, dark):
    """The kernels' sample operands, contiguous and typed: (:class:`~.pixelsamples.SweepSamples`,
    :class:`~.pixelsamples.Steps`, :class:`~.pixelsamples.Noise`)."""
    f64 = (lambda a: np.ascontiguousarray(a, np.float64))
    flag = (lambda a: np.ascontiguousarray(a, np.bool_))
    return (pixelsamples.SweepSamples(f64(y), flag(valid), f64(w)),
            pixelsamples.Steps(f64(t), f64(r), flag(light), flag(dark), f64(nfr)),
            pixelsamples.Noise(float(gain), float(read_var)))


def prepared_samples(y, valid, t, r, light, dark, *, w=None, n_frames=None, noise=None,
                     dark_current=None) -> dict:
    """The samples and weights each pixel's fit sees (as :func:`run_kernel` prepares them).

    Returns a dict: ``y`` and ``w`` (P, S) step means (DN) and weights (DN^-2; 0 = left out),
    and per pixel ``dark_weight`` (summed weight of its dark samples), ``dark_t_ms`` and
    ``dark_dn`` (their weighted mean exposure and level: the merged dark sample) and
    ``dark_current`` (DN/ms).
    """
    s_count, p_count = y.shape
    estimate, dc_in = _dark_current_args(dark_current, p_count)
    w, nfr, gain, read_var = _weight_args(w, n_frames, noise, s_count)
    out_y = np.empty((p_count, s_count))
    out_w = np.empty((p_count, s_count))
    out_d = np.empty((p_count, 4))
    pixelsamples.pixel_samples(
        *_sample_groups(y, valid, w, nfr, gain, read_var, t, r, light, dark),
        estimate, dc_in, pixelsamples.SampleOutputs(out_y, out_w, out_d))
    return {"y": out_y, "w": out_w, "dark_weight": out_d[:, 0], "dark_t_ms": out_d[:, 1],
            "dark_dn": out_d[:, 2], "dark_current": out_d[:, 3]}


def _to_fit(out_f, out_i) -> JointFit:
    th = out_f[:, 0:4]
    sigma = out_f[:, 4:8]
    n_fit = out_i[:, 0]
    status = out_i[:, 1].astype(np.uint8)
    linear = status != pixelfit.LEAKAGE
    with np.errstate(invalid="ignore", over="ignore"):
        chi2_red = out_f[:, 9] / np.maximum(n_fit - np.where(linear, 2, 4), 1)
        return JointFit(g=np.exp(th[:, 0]), a=np.exp(th[:, 1]), b=np.exp(th[:, 2]),
                        dark=th[:, 3], sigma=sigma, rms_dn=out_f[:, 11], chi2_red=chi2_red,
                        n_valid=n_fit, converged=status == pixelfit.LEAKAGE,
                        leak_constrained=sigma[:, 2] < 0.5,
                        iterations=int(out_i[:, 2].max(initial=0)), status=status,
                        dark_current=out_f[:, 8], chi2=out_f[:, 9],
                        chi2_linear=out_f[:, 10], r_ref=out_f[:, 12])


def fit_pixels(y, t_ms, r, valid, weight, theta0=None, *, dark_current=None,
               dark_model: str = "in_well", b_start=None, max_iter: int = 200, tol: float = 1e-9,
               prior_sigma: float = PRIOR_SIGMA, fallback: bool = False,
               merge_darks: bool = False) -> JointFit:
    """Weighted per-pixel fit of the leakage model (numba, parallel over pixels).

    Per pixel: the dark samples (``r == 0``) give the dark model and are merged into one
    sample; the plain linear model is fitted in closed form; the leakage model is fitted by
    Levenberg-Marquardt from start values derived from the linear one (or ``theta0``), with
    bounded parameters and weak priors on ln b and the saturation level. Where the leakage fit
    does not converge or fits worse than the linear model, the linear model (a = 0) is used
    (``fallback``) and ``status`` says why.

    Parameters
    ----------
    y : (P, S) float
        Responses (DN) of P pixels at S samples (step means).
    t_ms : (S,) float
        Exposure of each sample, ms (>= 0).
    r : (S,) float
        Relative light rate of each sample (0 for dark samples; NaN: sample unusable).
    valid : (P, S) bool
        Samples that take part (clipped, full-well and non-finite samples are left out).
    weight : (P, S) float
        1 / variance of each sample (DN^-2).
    theta0 : (P, 4) float, optional
        Start values of (ln g, ln a, ln b, dark); default: derived per pixel.
    dark_current : None, "estimate" or (P,) float
        Dark current (DN/ms): none, the slope of each pixel's dark samples against exposure
        (clipped at 0), or given.
    dark_model : "in_well" or "additive"
        Whether the dark current adds to the light rate (it fills the well and leaks with the
        signal) or to the response after the leakage.
    b_start : float or sequence of float, optional
        Start values of b tried (1/DN); default :data:`B_GRID`.
    max_iter : int
        Iterations per pixel; 0 returns the start values.
    fallback : bool
        Where the leakage fit fits worse than the linear model or has too few samples, the
        linear model is returned: with ``fallback`` as ``a = 0``, otherwise as leakage
        parameters that give the same curve (b at its start value, the leakage e^-40 of the
        light rate at the highest sample), usable as a warm start. Where the leakage fit did
        not converge within ``max_iter``, ``fallback`` also returns the linear model; without
        it the last iterate is returned (``status`` says which).
    merge_darks : bool
        Replace each pixel's dark samples by their weighted mean (exact for the additive dark
        model, and fewer samples to evaluate); by default every dark sample is fitted.

    Returns
    -------
    JointFit
    """
    k = _kernel_inputs(y, t_ms, r, valid, weight)
    return run_kernel(k["y"], k["valid"], k["t"], k["r"], k["light"], k["dark"], w=k["w"],
                      dark_current=dark_current, dark_model=dark_model, theta0=theta0,
                      b_start=b_start, max_iter=max_iter, tol=tol, prior_sigma=prior_sigma,
                      fallback=fallback, merge_darks=merge_darks)


def initial_guess(y, t_ms, r, valid, weight, dark_current=None, *, b_grid=B_GRID,
                  dark_model: str = "in_well", merge_darks: bool = False) -> np.ndarray:
    """Start values (ln g, ln a, ln b, d) per pixel (P, 4), as :func:`fit_pixels` derives them.

    The dark level and g come from the linear model (g from the samples below half the pixel's
    highest level), b from ``b_grid`` and a so that the dynamic saturation at the pixel's
    highest light rate lies just above its highest valid sample (the best of a few margins).
    """
    k = _kernel_inputs(y, t_ms, r, valid, weight)
    fit = run_kernel(k["y"], k["valid"], k["t"], k["r"], k["light"], k["dark"], w=k["w"],
                     dark_current=dark_current, dark_model=dark_model, b_start=b_grid,
                     max_iter=0, merge_darks=merge_darks)
    return fit.theta


def residuals(fit: JointFit, y, t_ms, r, valid, dark_current=None,
              dark_model: str = "in_well") -> np.ndarray:
    """Residuals model - data (P, S) of a fit on any set of samples (invalid ones are 0)."""
    y = np.asarray(y, np.float64)
    dc = np.zeros((y.shape[0], 1)) if dark_current is None else np.asarray(
        dark_current, np.float64).reshape(-1, 1)
    t = np.asarray(t_ms, np.float64)
    r = np.nan_to_num(np.asarray(r, np.float64))
    if dark_model == "additive":
        m = predict(fit.theta, t, r) + dc * t
    else:
        m = predict(fit.theta, t, r, dc)
    ok = np.asarray(valid, bool) & np.isfinite(y) & np.isfinite(m)
    return np.where(ok, m - y, 0.0)
