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

PRIOR_SIGMA = 3.0  # e-folds, on ln a and ln b
PARAMS = ("ln_g", "ln_a", "ln_b", "dark")


@dataclass(frozen=True, eq=False)
class JointFit:
    """Per-pixel result of :func:`fit_joint` (arrays of shape (P,))."""

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


def _model_and_jacobian(theta, t, r, dc=0.0):
    """Model (P, S) and Jacobian (P, S, 4) with respect to (ln g, ln a, ln b, d).

    ``dc`` (P, 1) is a fixed dark current (DN/ms) added to the light rate.
    """
    ln_g, ln_a, ln_b, d = (theta[:, i:i + 1] for i in range(4))
    b = np.exp(ln_b)
    with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
        kg = np.exp(ln_g) * r
        k = kg + dc
        x = b * k * t
        log_t = np.log(t)
        lp = model._log_phi(x)
        a1 = -b * d - x
        lterm = ln_a + ln_b + log_t + lp
        n = np.logaddexp(a1, lterm)
        y = -n / b
        w1 = np.exp(a1 - n)
        w2 = np.exp(lterm - n)
        w1 = np.where(np.isfinite(w1), w1, 1.0)
        w2 = np.where(np.isfinite(w2), w2, 0.0)
        small = x < 1e-6
        xs = np.where(small, 1.0, x)
        dlp = np.where(small, -0.5 + x / 12.0, 1.0 / np.expm1(xs) - 1.0 / xs)  # d lnphi / dx
        dn_dlnk = -w1 * x + w2 * x * dlp
        # d/d ln g acts on the light part of k only
        j_lng = np.where(k > 0, -dn_dlnk / b * (kg / np.where(k > 0, k, 1.0)), 0.0)
        j_lna = -w2 / b
        dn_dlnb = w1 * a1 + w2 * (1.0 + x * dlp)
        j_lnb = (n - dn_dlnb) / b
        j_d = w1
    jac = np.stack(np.broadcast_arrays(j_lng, j_lna, j_lnb, j_d), axis=-1)
    jac = np.where(np.isfinite(jac), jac, 0.0)
    return y, jac


def _model(theta, t, r, dc=0.0):
    ln_g, ln_a, ln_b, d = (theta[:, i:i + 1] for i in range(4))
    with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
        return model._response(t, np.exp(ln_g) * r + dc, np.exp(ln_a), np.exp(ln_b), d)


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
    """Chain rule from d/d(ln g, ln a, ln b, d) to d/d(ln g, s, ln b, d)."""
    b = np.exp(phi[:, 2])[:, None]
    s = phi[:, 1][:, None]
    j_lna = jac[..., 1]
    return np.stack([jac[..., 0] + j_lna, -b * j_lna, jac[..., 2] - b * s * j_lna, jac[..., 3]],
                    axis=-1)


def fit_joint(y, t_ms, r, valid, weight, theta0, *, dark_current=None, max_iter: int = 80,
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
    y = np.asarray(y, np.float64)
    p_count, s_count = y.shape
    t = np.broadcast_to(np.asarray(t_ms, np.float64), y.shape)
    r = np.broadcast_to(np.asarray(r, np.float64), y.shape)
    w = np.where(valid, np.asarray(weight, np.float64), 0.0)
    y = np.where(valid, y, 0.0)
    dc = np.zeros((p_count, 1)) if dark_current is None else np.asarray(
        dark_current, np.float64).reshape(p_count, 1)
    rref = np.where(valid, r, 0).max(axis=1)
    ln_rref = np.log(np.where(rref > 0, rref, 1.0))
    phi = _to_internal(np.asarray(theta0, np.float64), ln_rref)
    # weak priors: ln b within PRIOR_SIGMA e-folds, s within PRIOR_SIGMA / b0 DN of the start
    prior_mean = phi[:, 1:3].copy()
    prior_w = np.column_stack([(np.exp(phi[:, 2]) / prior_sigma) ** 2,
                               np.full(p_count, 1.0 / prior_sigma ** 2)])

    def cost(ph, idx):
        th = _to_external(ph, ln_rref[idx])
        res = _model(th, t[idx], r[idx], dc[idx]) - y[idx]
        c = np.einsum("ps,ps->p", w[idx] * res, res)
        return c + (prior_w[idx] * (ph[:, 1:3] - prior_mean[idx]) ** 2).sum(axis=1)

    lam = np.full(p_count, 1e-3)
    active = np.arange(p_count)
    current = cost(phi, active)
    converged = np.zeros(p_count, bool)
    it = 0
    eye = np.eye(4)
    for it in range(1, max_iter + 1):
        if active.size == 0:
            break
        ph = phi[active]
        ym, jac = _model_and_jacobian(_to_external(ph, ln_rref[active]), t[active], r[active],
                                      dc[active])
        jac = _internal_jacobian(jac, ph)
        res = ym - y[active]
        jw = jac * w[active][..., None]
        jtj = np.einsum("psi,psj->pij", jw, jac)
        grad = np.einsum("psi,ps->pi", jw, res)
        pw = prior_w[active]
        jtj[:, 1, 1] += pw[:, 0]
        jtj[:, 2, 2] += pw[:, 1]
        grad[:, 1:3] += pw * (ph[:, 1:3] - prior_mean[active])
        diag = np.einsum("pii->pi", jtj)
        lhs = jtj + lam[active, None, None] * (diag[:, :, None] * eye) + 1e-12 * eye
        step = -np.linalg.solve(lhs, grad[..., None])[..., 0]
        step = np.where(np.isfinite(step), step, 0.0)
        b_now = np.exp(ph[:, 2])
        step[:, 0] = np.clip(step[:, 0], -2.0, 2.0)
        step[:, 2] = np.clip(step[:, 2], -1.0, 1.0)
        step[:, 1] = np.clip(step[:, 1], -3.0 / b_now, 3.0 / b_now)
        trial = ph + step
        new = cost(trial, active)
        better = new < current[active]
        phi[active[better]] = trial[better]
        rel = (current[active] - new) / np.maximum(current[active], 1e-300)
        current[active[better]] = new[better]
        lam[active] = np.where(better, np.maximum(lam[active] / 5.0, 1e-9),
                               np.minimum(lam[active] * 8.0, 1e9))
        scale = np.array([1.0, 0.0, 1.0, 1.0])[None, :] * np.abs(step)
        scale[:, 1] = np.abs(step[:, 1]) * b_now
        done = (better & (rel < tol)) | (scale.max(axis=1) < 1e-8) | (lam[active] >= 1e9)
        converged[active[done]] = True
        active = active[~done]

    theta = _to_external(phi, ln_rref)
    # uncertainties of (ln g, ln a, ln b, d) from the weighted normal matrix at the solution
    ym, jac = _model_and_jacobian(theta, t, r, dc)
    res = np.where(valid, ym - y, 0.0)
    n_valid = valid.sum(axis=1)
    dof = np.maximum(n_valid - 4, 1)
    chi2 = np.einsum("ps,ps->p", w * res, res) / dof
    jw = jac * w[..., None]
    jtj = np.einsum("psi,psj->pij", jw, jac)
    # the same weak priors, expressed on (ln a, ln b), keep the matrix invertible
    jint = _internal_jacobian(jac, phi)
    jtj_int = np.einsum("psi,psj->pij", jint * w[..., None], jint)
    jtj_int[:, 1, 1] += prior_w[:, 0]
    jtj_int[:, 2, 2] += prior_w[:, 1]
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
    # leakage is constrained when the data, not the priors, pin s and ln b
    data_info = np.einsum("pii->pi", jtj_int)[:, 1:3] - prior_w
    leak_constrained = np.all(data_info > 25.0 * prior_w, axis=1)
    return JointFit(g=np.exp(theta[:, 0]), a=np.exp(theta[:, 1]), b=np.exp(theta[:, 2]),
                    dark=theta[:, 3], sigma=sigma, rms_dn=rms, chi2_red=chi2, n_valid=n_valid,
                    converged=converged, leak_constrained=leak_constrained, iterations=it)


B_GRID = (0.002, 0.005, 0.01, 0.02, 0.05)  # 1/DN, start values tried for b
MARGIN_GRID = (0.5, 3.0)  # saturation placed this many 1/b above the highest valid sample


def dark_current_from_darks(y, t_ms, r, valid, weight) -> np.ndarray:
    """Per-pixel dark current (DN/ms): weighted slope of the dark samples against exposure.

    Zero where the dark samples do not span two exposures.
    """
    y = np.asarray(y, np.float64)
    t = np.broadcast_to(np.asarray(t_ms, np.float64), y.shape)
    r = np.broadcast_to(np.asarray(r, np.float64), y.shape)
    w = np.where(valid & (r == 0), weight, 0.0)
    sw, st, sy = w.sum(1), (w * t).sum(1), (w * y).sum(1)
    stt, sty = (w * t * t).sum(1), (w * t * y).sum(1)
    den = sw * stt - st ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (sw * sty - st * sy) / den
    ok = np.isfinite(slope) & (den > 1e-12 * np.maximum(sw * stt, 1e-300))
    return np.where(ok, slope, 0.0)


def initial_guess(y, t_ms, r, valid, weight, dark_current=None) -> np.ndarray:
    """Start values (ln g, ln a, ln b, d) per pixel, vectorised.

    The dark level is the mean of valid dark samples (r = 0) or, without darks, the intercept of
    a line through the lowest light samples; g is the weighted slope of (Y - d) against r t over
    samples below half of the pixel's highest valid level; b is picked from a small grid by the
    residual cost, with a set so the dynamic saturation at the pixel's highest light rate lies just
    above its highest valid sample.
    """
    y = np.asarray(y, np.float64)
    t = np.broadcast_to(np.asarray(t_ms, np.float64), y.shape)
    r = np.broadcast_to(np.asarray(r, np.float64), y.shape)
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
    for b in B_GRID:
        for m in MARGIN_GRID:
            ln_a = np.log(kmax) - b * (ymax + m / b)
            th = np.column_stack([np.log(g0), ln_a, np.full_like(g0, np.log(b)), d0])
            res = _model(th, t, r, dc[:, None]) - y
            cost = np.where(valid, weight * res * res, 0).sum(axis=1)
            better = cost < best_cost
            best[better] = th[better]
            best_cost[better] = cost[better]
    return best
