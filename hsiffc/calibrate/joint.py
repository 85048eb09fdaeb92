"""Joint per-pixel fit of the leakage model to a whole sweep, vectorised over pixels.

Every pixel p and step s share one model::

    Y[s, p] = response(t[s], g[p] * r[s], a[p], b[p], d[p])

with ``t`` the exposure (ms), ``r`` the step's relative light rate (photons per ms in EMVA 1288
data; 1 for a single illumination; 0 for dark steps) and per-pixel unknowns ``g`` (DN per unit
of r, so ``k = g r`` in DN/ms), leakage ``a`` (DN/ms), ``b`` (1/DN) and dark level ``d`` (DN).

The fit is a weighted Levenberg-Marquardt on ``theta = (ln g, ln a, ln b, d)`` run on all
pixels of a chunk at once: analytic Jacobians from the closed form, a 4 x 4 normal system per
pixel solved in one batched call, a damping factor per pixel, and pixels that have converged
drop out of the iteration. No Python loop touches single pixels.

A weak Gaussian prior on ln a and ln b (sigma ``PRIOR_SIGMA`` e-folds around the start values)
keeps the normal equations regular for pixels whose leakage never shows inside the sweep; such
pixels are reported with ``leak_constrained == False`` and their a, b carry the prior's
uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import model

_TRACE = None  # debugging aid: set to a list to record the active-pixel count
PRIOR_SIGMA = 3.0  # e-folds, on ln a and ln b
PARAMS = ("ln_g", "ln_a", "ln_b", "dark")


@dataclass(frozen=True, eq=False)
class JointFit:
    """Per-pixel result of :func:`fit_pixels` (arrays of shape (P,))."""

    g: np.ndarray  # DN per unit relative light rate
    a: np.ndarray  # DN/ms
    b: np.ndarray  # 1/DN
    dark: np.ndarray  # DN
    sigma: np.ndarray  # (P, 4) standard errors of (ln g, ln a, ln b, dark)
    rms_dn: np.ndarray  # unweighted RMS residual over valid samples, DN
    chi2_red: np.ndarray  # weighted residual sum of squares per degree of freedom
    n_valid: np.ndarray
    converged: np.ndarray
    leak_constrained: np.ndarray
    iterations: int


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


def _sanitised(y, t_ms, r, valid, weight):
    """Neutralise invalid samples (NaN rates, zero exposures), which carry zero weight but must
    not turn sums into NaN. ``t`` and ``r`` stay 1-D (S,) when given per step, which keeps
    their logs and products cheap."""
    y = np.asarray(y, np.float64)
    valid = np.asarray(valid, bool)
    t = np.asarray(t_ms, np.float64)
    r = np.asarray(r, np.float64)
    step_ok = np.isfinite(t) & (t > 0) & np.isfinite(r)
    t = np.where(step_ok, t, 1.0)
    r = np.where(step_ok, r, 0.0)
    ok = valid & np.isfinite(y) & step_ok
    w = np.where(ok, np.broadcast_to(np.asarray(weight, np.float64), y.shape), 0.0)
    return np.where(ok, y, 0.0), t, r, w


def _rows(a, idx):
    """Rows ``idx`` of a per-pixel (P, S) array; per-step (S,) arrays are shared."""
    return a if a.ndim == 1 else a[idx]


def _to_internal(theta, ln_rref):
    """(ln g, ln a, ln b, d) -> (ln g, s, ln b, d) with s the saturation level at r_ref (DN)."""
    b = np.exp(theta[:, 2])
    s = (theta[:, 0] + ln_rref - theta[:, 1]) / b
    return np.column_stack([theta[:, 0], s, theta[:, 2], theta[:, 3]])


def _to_external(phi, ln_rref):
    b = np.exp(phi[:, 2])
    ln_a = phi[:, 0] + ln_rref - b * phi[:, 1]
    return np.column_stack([phi[:, 0], ln_a, phi[:, 2], phi[:, 3]])


def _internal_jacobian(jac, phi):
    """Chain rule from d/d(ln g, ln a, ln b, d) to d/d(ln g, s, ln b, d), in place."""
    b = np.exp(phi[:, 2])[:, None]
    s = phi[:, 1][:, None]
    j_lna = jac[..., 1].copy()
    jac[..., 0] += j_lna
    jac[..., 1] = -b * j_lna
    jac[..., 2] -= b * s * j_lna
    return jac


def fit_pixels(y, t_ms, r, valid, weight, theta0, *, dark_current=None, max_iter: int = 80,
              tol: float = 1e-9, prior_sigma: float = PRIOR_SIGMA) -> JointFit:
    """Weighted Levenberg-Marquardt fit of every pixel at once.

    Internally a and b are replaced by b and the dynamic saturation level s at the pixel's
    highest light rate (``ln a = ln(g r_ref) - b s``): the leakage parameters a and b are
    strongly correlated (a tiny change of b moves ln a by b times the signal level), the
    saturation level and b much less, so the iteration converges in a few steps.

    Parameters
    ----------
    y : (P, S) float
        Responses (DN) of P pixels at S samples (step means).
    t_ms : (S,) or (P, S)
        Exposure of each sample, ms (> 0).
    r : (S,) or (P, S)
        Relative light rate of each sample (0 for dark samples).
    valid : (P, S) bool
        Samples that take part (clipped and full-well samples are False).
    weight : (P, S) float
        1 / variance of each sample (DN^-2).
    theta0 : (P, 4)
        Start values of (ln g, ln a, ln b, dark).
    dark_current : (P,) float, optional
        Dark current (DN/ms) held fixed and added to the light rate (see
        :func:`dark_current_from_darks`); default 0.

    Returns
    -------
    JointFit
    """
    y, t, r, w = _sanitised(y, t_ms, r, valid, weight)
    valid = w > 0
    p_count, s_count = y.shape
    dc = np.zeros((p_count, 1)) if dark_current is None else np.asarray(
        dark_current, np.float64).reshape(p_count, 1)
    rref = np.where(valid, r, 0.0).max(axis=1)
    ln_rref = np.log(np.where(rref > 0, rref, 1.0))
    phi = _to_internal(np.asarray(theta0, np.float64), ln_rref)
    # weak priors: ln b within PRIOR_SIGMA e-folds, s within PRIOR_SIGMA / b0 DN of the start
    prior_mean = phi[:, 1:3].copy()
    prior_w = np.column_stack([(np.exp(phi[:, 2]) / prior_sigma) ** 2,
                               np.full(p_count, 1.0 / prior_sigma ** 2)])

    # The iteration evaluates the model in single precision (twice as fast; the response is
    # good to ~1e-4 DN there, far below the noise); steps, costs and the final uncertainties
    # are computed in double precision.
    f32 = np.float32
    y32, t32, r32, w32, dc32 = (np.asarray(v, f32) for v in (y, t, r, w, dc))

    def evaluate(ph, idx):
        """Residuals, internal Jacobian and cost of the pixels ``idx`` at ``ph``."""
        ym, jac = model_and_jacobian(_to_external(ph, ln_rref[idx]).astype(f32),
                                      _rows(t32, idx), _rows(r32, idx), dc32[idx])
        res = ym - y32[idx]
        c = np.einsum("ps,ps->p", w32[idx] * res, res, dtype=np.float64)
        c += (prior_w[idx] * (ph[:, 1:3] - prior_mean[idx]) ** 2).sum(axis=1)
        return res, _internal_jacobian(jac, ph.astype(f32)), c

    # state of the active pixels, compacted as pixels converge: the model and Jacobian at an
    # accepted trial point are reused for the next step, so each iteration costs one evaluation
    active = np.arange(p_count)
    res_a, jac_a, cost_a = evaluate(phi, active)
    lam_a = np.full(p_count, 1e-3)
    converged = np.zeros(p_count, bool)
    it = 0
    eye = np.eye(4)
    for it in range(1, max_iter + 1):
        if active.size == 0:
            break
        ph = phi[active]
        w_a = w32[active]
        jw = jac_a * w_a[..., None]
        jtj = np.matmul(jw.transpose(0, 2, 1), jac_a).astype(np.float64)
        grad = np.einsum("psi,ps->pi", jw, res_a, dtype=np.float64)
        pw = prior_w[active]
        jtj[:, 1, 1] += pw[:, 0]
        jtj[:, 2, 2] += pw[:, 1]
        grad[:, 1:3] += pw * (ph[:, 1:3] - prior_mean[active])
        diag = np.einsum("pii->pi", jtj)
        lhs = jtj + lam_a[:, None, None] * (diag[:, :, None] * eye) + 1e-12 * eye
        step = -np.linalg.solve(lhs, grad[..., None])[..., 0]
        step = np.where(np.isfinite(step), step, 0.0)
        b_now = np.exp(ph[:, 2])
        step[:, 0] = np.clip(step[:, 0], -2.0, 2.0)
        step[:, 2] = np.clip(step[:, 2], -1.0, 1.0)
        step[:, 1] = np.clip(step[:, 1], -3.0 / b_now, 3.0 / b_now)
        trial = ph + step
        res_t, jac_t, cost_t = evaluate(trial, active)
        better = cost_t < cost_a
        gain = cost_a - cost_t
        rel = gain / np.maximum(cost_a, 1e-300)
        phi[active[better]] = trial[better]
        res_a[better] = res_t[better]
        jac_a[better] = jac_t[better]
        cost_a[better] = cost_t[better]
        lam_a = np.where(better, np.maximum(lam_a / 5.0, 1e-9), np.minimum(lam_a * 8.0, 1e9))
        size = np.abs(step)
        size[:, 1] *= b_now
        # converged: the cost (a chi-square) no longer moves by a meaningful amount (1e-3 in
        # chi-square moves a parameter by ~0.03 sigma), or the steps stall at single-precision
        # resolution (rejected although tiny)
        done = ((better & ((rel < tol) | (gain < 1e-3))) | (size.max(axis=1) < 1e-7)
                | (~better & (np.abs(gain) < 1e-3) & (lam_a > 1e2)) | (lam_a >= 1e9))
        converged[active[done]] = True
        keep = ~done
        active, res_a, jac_a = active[keep], res_a[keep], jac_a[keep]
        cost_a, lam_a = cost_a[keep], lam_a[keep]
        if _TRACE is not None:
            _TRACE.append(active.size)

    theta = _to_external(phi, ln_rref)
    # uncertainties of (ln g, ln a, ln b, d) from the weighted normal matrix at the solution
    ym, jac = model_and_jacobian(theta, t, r, dc)
    res = np.where(valid, ym - y, 0.0)
    n_valid = valid.sum(axis=1)
    dof = np.maximum(n_valid - 4, 1)
    chi2 = np.einsum("ps,ps->p", w * res, res) / dof
    # the same weak priors, expressed on (ln a, ln b), keep the matrix invertible
    jint = _internal_jacobian(jac, phi)
    jtj_int = np.matmul((jint * w[..., None]).transpose(0, 2, 1), jint)
    jtj_int[:, 1, 1] += prior_w[:, 0]
    jtj_int[:, 2, 2] += prior_w[:, 1]
    try:
        cov_int = np.linalg.inv(jtj_int)
    except np.linalg.LinAlgError:
        cov_int = np.linalg.pinv(jtj_int)
    # d(ln g, ln a, ln b, d)/d(ln g, s, ln b, d)
    b = np.exp(phi[:, 2])
    tr = np.zeros((p_count, 4, 4))
    tr[:, 0, 0] = 1.0
    tr[:, 1, 0] = 1.0
    tr[:, 1, 1] = -b
    tr[:, 1, 2] = -b * phi[:, 1]
    tr[:, 2, 2] = 1.0
    tr[:, 3, 3] = 1.0
    cov = tr @ cov_int @ np.transpose(tr, (0, 2, 1))
    over = np.maximum(chi2, 1.0)  # inflate where the model is over-dispersed (real data)
    sigma = np.sqrt(np.clip(np.einsum("pii->pi", cov), 0, None) * over[:, None])
    rms = np.sqrt((res ** 2).sum(axis=1) / np.maximum(n_valid, 1))
    # leakage is constrained when the data pin b to better than a factor 1.65 (1 sigma)
    leak_constrained = sigma[:, 2] < 0.5
    return JointFit(g=np.exp(theta[:, 0]), a=np.exp(theta[:, 1]), b=np.exp(theta[:, 2]),
                    dark=theta[:, 3], sigma=sigma, rms_dn=rms, chi2_red=chi2, n_valid=n_valid,
                    converged=converged, leak_constrained=leak_constrained, iterations=it)


def residuals(fit: JointFit, y, t_ms, r, valid, dark_current=None) -> np.ndarray:
    """Residuals model - data (P, S) of a fit on any set of samples (invalid ones are 0)."""
    y, t, r, w = _sanitised(y, t_ms, r, valid, np.ones(np.shape(y)))
    theta = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark])
    dc = 0.0 if dark_current is None else np.asarray(dark_current, np.float64)[:, None]
    return np.where(w > 0, predict(theta, t, r, dc) - y, 0.0)


B_GRID = (0.002, 0.005, 0.01, 0.02, 0.05)  # 1/DN, start values tried for b
MARGIN_GRID = (0.5, 3.0)  # saturation placed this many 1/b above the highest valid sample


def dark_current_from_darks(y, t_ms, r, valid, weight) -> np.ndarray:
    """Per-pixel dark current (DN/ms): weighted slope of the dark samples against exposure.

    Zero where the dark samples do not span two exposures.
    """
    y, t, r, w = _sanitised(y, t_ms, r, valid, weight)
    w = np.where(r == 0, w, 0.0)
    sw, st, sy = w.sum(1), (w * t).sum(1), (w * y).sum(1)
    stt, sty = (w * t * t).sum(1), (w * t * y).sum(1)
    den = sw * stt - st ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (sw * sty - st * sy) / den
    ok = np.isfinite(slope) & (den > 1e-12 * np.maximum(sw * stt, 1e-300))
    return np.where(ok, slope, 0.0)


def merge_dark_samples(y, t_ms, r, valid, weight, dark_current=None):
    """Replace all dark samples (r = 0) of each pixel by their weighted mean.

    The dark samples' leakage term is negligible, so they only pin the dark level (and, with a
    fixed dark current, lie on the line ``d + dc t``): one sample with the summed weight at the
    mean dark exposure carries the same information and the fit has fewer samples to evaluate.
    ``t_ms`` and ``r`` must be per step (1-D).

    Returns y, t, r, valid, weight with the dark columns merged into the last column.
    """
    t = np.asarray(t_ms, np.float64)
    r = np.asarray(r, np.float64)
    dark = (r == 0) & np.isfinite(t) & (t > 0)
    if dark.sum() < 2:
        return y, t, r, valid, weight
    w = np.where(valid, weight, 0.0)
    wd = w[:, dark]
    sw = wd.sum(axis=1)
    t_mean = t[dark].mean()
    yd = np.where(valid[:, dark], y[:, dark], 0.0)
    if dark_current is not None:  # move every dark sample along d + dc t to the mean exposure
        dc = np.asarray(dark_current, np.float64)[:, None]
        yd = yd + dc * (t_mean - t[dark])[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        ym = np.where(sw > 0, (wd * yd).sum(axis=1) / sw, 0.0)
    keep = ~dark
    y2 = np.column_stack([y[:, keep], ym])
    w2 = np.column_stack([w[:, keep], sw])
    v2 = np.column_stack([valid[:, keep], sw > 0])
    t2 = np.append(t[keep], t_mean)
    r2 = np.append(r[keep], 0.0)
    return y2, t2, r2, v2, w2


def initial_guess(y, t_ms, r, valid, weight, dark_current=None, *, b_grid=B_GRID,
                  margin_grid=MARGIN_GRID) -> np.ndarray:
    """Start values (ln g, ln a, ln b, d) per pixel, vectorised.

    The dark level is the mean of valid dark samples (r = 0) or, without darks, the intercept of
    a line through the lowest light samples; g is the weighted slope of (Y - d) against r t over
    samples below half of the pixel's highest valid level; b is picked from a small grid by the
    residual cost, with a set so the dynamic saturation at the pixel's highest light rate lies just
    above its highest valid sample.
    """
    y, t, r, weight = _sanitised(y, t_ms, r, valid, weight)
    valid = weight > 0
    dark_s = valid & (r == 0)
    light_s = valid & (r > 0)
    n_dark = dark_s.sum(axis=1)
    u = r * t  # light dose in rate units x ms
    dc = np.zeros(y.shape[0]) if dark_current is None else np.asarray(dark_current, np.float64)
    y_nodc = y - dc[:, None] * t  # dark current removed for the linear start values
    with np.errstate(invalid="ignore", divide="ignore"):
        d_dark = np.where(dark_s, y_nodc, 0).sum(axis=1) / np.maximum(n_dark, 1)
        ymax = np.where(light_s, y, -np.inf).max(axis=1)
        ymin_light = np.where(light_s, y, np.inf).min(axis=1)
    d0 = np.where(n_dark > 0, d_dark, np.where(np.isfinite(ymin_light), ymin_light, 0.0))
    half = light_s & ((y - d0[:, None]) <= 0.5 * (ymax - d0)[:, None])
    few = half.sum(axis=1) < 2
    half = np.where(few[:, None], light_s, half)
    wl = np.where(half, weight, 0.0)
    if np.any(n_dark == 0):
        # no darks: line through the low samples gives both slope and intercept
        sw, su, sy = wl.sum(1), (wl * u).sum(1), (wl * y_nodc).sum(1)
        suu, suy = (wl * u * u).sum(1), (wl * u * y_nodc).sum(1)
        den = sw * suu - su ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            slope = (sw * suy - su * sy) / den
            icpt = (sy - slope * su) / sw
        d0 = np.where((n_dark == 0) & np.isfinite(icpt), icpt, d0)
    with np.errstate(invalid="ignore", divide="ignore"):
        g0 = (wl * u * (y_nodc - d0[:, None])).sum(1) / (wl * u * u).sum(1)
    g0 = np.where(np.isfinite(g0) & (g0 > 0), g0, 1e-3)
    rmax = np.where(light_s, r, 0).max(axis=1)
    kmax = np.maximum(g0 * rmax, 1e-6)
    ymax = np.where(np.isfinite(ymax), ymax, d0 + 1.0)
    best_cost = np.full(y.shape[0], np.inf)
    best = np.zeros((y.shape[0], 4))
    for b in b_grid:
        for m in margin_grid:
            ln_a = np.log(kmax) - b * (ymax + m / b)
            th = np.column_stack([np.log(g0), ln_a, np.full_like(g0, np.log(b)), d0])
            res = predict(th, t, r, dc[:, None]) - y
            cost = np.where(valid, weight * res * res, 0).sum(axis=1)
            better = cost < best_cost
            best[better] = th[better]
            best_cost[better] = cost[better]
    return best
