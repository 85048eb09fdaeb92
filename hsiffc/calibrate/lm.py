"""Levenberg-Marquardt for one pixel of the leakage model, as numba functions on locals.

Parameters inside the iteration are ``phi = (ln g, s, ln b, d)``: ``g`` the responsivity (DN/ms
per unit of relative light rate), ``s`` the dynamic saturation level (DN) at the pixel's highest
light rate ``r_ref`` (so ``ln a = ln(g r_ref) - b s``), ``b`` (1/DN) and the dark level ``d``
(DN). The leakage parameters a and b are strongly correlated (a tiny change of b moves ln a by
b times the signal level); s and b much less, so the iteration converges in a few steps. Weak
priors on s and ln b keep the normal matrix regular where the data do not show leakage; step
limits and bounds keep every iterate finite.

The model and its gradient come from :func:`hsiffc.model.response_gradient_kernel`. A pixel's
samples are passed as 1-D arrays (its step means ``yp``, weights ``wq``, and per-step ``t``,
``r``), plus an optional merged sample (``md_y, md_w, md_t``: the weighted mean of
its dark samples, which lies on the dark line). ``wq`` holds the weights of the samples in
the fit (0 for samples left out, and for dark samples when they are merged).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..model import response_gradient_kernel

B_MIN, B_MAX = 1e-6, 1.0  # bounds of b, 1/DN
CONVERGED_CHI2 = 1e-3  # chi-square gain below which a pixel is converged (~0.03 sigma)


@njit(cache=True, inline="always", error_model="numpy")
def sample(t, r, g, ln_a, c, dc, additive, s, b, d):
    """Model value and Jacobian with respect to (ln g, s, ln b, d) at one sample.

    ``c = exp(ln_a + b d)``; ``dc`` (DN/ms) adds to the light rate, or (``additive``) to the
    response as ``dc t``.
    """
    kg = g * r
    if additive or dc == 0.0:
        y, dlnk, dlna, dlnb, dd = response_gradient_kernel(t, kg, ln_a, b, d, c)
        if additive:
            y += dc * t
    else:
        k = kg + dc
        y, dlnk, dlna, dlnb, dd = response_gradient_kernel(t, k, ln_a, b, d, c)
        dlnk *= kg / k if k > 0 else 0.0
    return y, dlnk + dlna, -b * dlna, dlnb - b * s * dlna, dd


@njit(cache=True, inline="always", error_model="numpy")
def _accumulate(acc, wi, res, j0, j1, j2, j3):
    """Add one weighted sample to (chi2, g0..g3, h00, h10, h11, h20, h21, h22, h30..h33)."""
    w0, w1, w2, w3 = wi * j0, wi * j1, wi * j2, wi * j3
    return (acc[0] + wi * res * res, acc[1] + w0 * res, acc[2] + w1 * res, acc[3] + w2 * res,
            acc[4] + w3 * res, acc[5] + w0 * j0, acc[6] + w1 * j0, acc[7] + w1 * j1,
            acc[8] + w2 * j0, acc[9] + w2 * j1, acc[10] + w2 * j2, acc[11] + w3 * j0,
            acc[12] + w3 * j1, acc[13] + w3 * j2, acc[14] + w3 * j3)


@njit(cache=True, error_model="numpy")
def evaluate(ph, yp, wq, t, r, dc, additive, ln_rref, md_y, md_w, md_t, prior, h, gv):
    """Weighted cost (data chi-square + priors) at ``ph``, the normal matrix ``h`` (4 x 4) and
    the half gradient ``gv``. Returns (cost, chi2, unweighted SS).

    ``wq`` holds the weights of the samples in the fit (0: left out); ``prior`` = (s0, ln b0,
    weight of s, weight of ln b).
    """
    g = np.exp(ph[0])
    s, ln_b, d = ph[1], ph[2], ph[3]
    b = np.exp(ln_b)
    ln_a = ph[0] + ln_rref - b * s
    c = np.exp(ln_a + b * d)
    acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    ss = 0.0
    for i in range(t.size):
        wi = wq[i]
        if wi > 0.0:
            yi, j0, j1, j2, j3 = sample(t[i], r[i], g, ln_a, c, dc, additive, s, b, d)
            res = yi - yp[i]
            ss += res * res
            acc = _accumulate(acc, wi, res, j0, j1, j2, j3)
    if md_w > 0.0:
        yi, j0, j1, j2, j3 = sample(md_t, 0.0, g, ln_a, c, dc, additive, s, b, d)
        acc = _accumulate(acc, md_w, yi - md_y, j0, j1, j2, j3)
    chi2 = acc[0]
    ds = s - prior[0]
    db = ln_b - prior[1]
    h[0, 0] = acc[5]
    h[1, 1] = acc[7] + prior[2]
    h[2, 2] = acc[10] + prior[3]
    h[3, 3] = acc[14]
    h[0, 1] = h[1, 0] = acc[6]
    h[0, 2] = h[2, 0] = acc[8]
    h[1, 2] = h[2, 1] = acc[9]
    h[0, 3] = h[3, 0] = acc[11]
    h[1, 3] = h[3, 1] = acc[12]
    h[2, 3] = h[3, 2] = acc[13]
    gv[0] = acc[1]
    gv[1] = acc[2] + prior[2] * ds
    gv[2] = acc[3] + prior[3] * db
    gv[3] = acc[4]
    return chi2 + prior[2] * ds * ds + prior[3] * db * db, chi2, ss


@njit(cache=True, error_model="numpy")
def solve4(a, rhs, out, m):
    """Solve the 4 x 4 system ``a x = rhs`` into ``out`` (Gauss elimination with partial
    pivoting; ``m`` is a (4, 5) scratch array). Returns False if singular."""
    for i in range(4):
        for c in range(4):
            m[i, c] = a[i, c]
        m[i, 4] = rhs[i]
    for col in range(4):
        piv = col
        for i in range(col + 1, 4):
            if abs(m[i, col]) > abs(m[piv, col]):
                piv = i
        if not (abs(m[piv, col]) > 1e-300):
            return False
        if piv != col:
            for c in range(5):
                m[col, c], m[piv, c] = m[piv, c], m[col, c]
        for i in range(col + 1, 4):
            f = m[i, col] / m[col, col]
            for c in range(col, 5):
                m[i, c] -= f * m[col, c]
    for i in range(3, -1, -1):
        acc = m[i, 4]
        for c in range(i + 1, 4):
            acc -= m[i, c] * out[c]
        out[i] = acc / m[i, i]
    for i in range(4):
        if not np.isfinite(out[i]):
            return False
    return True


@njit(cache=True, error_model="numpy")
def levenberg_marquardt(ph, yp, wq, t, r, dc, additive, ln_rref, md_y, md_w, md_t, prior, lo,
                        hi, s_step_min, max_iter, tol, h, gv, hn, step, trial, scratch):
    """Iterate from ``ph`` (updated in place) to the minimum of :func:`evaluate`.

    ``lo``, ``hi`` (4,) bound the parameters. A step moves ln g by at most 2, ln b by at most
    1 and s by at most 3/b or ``s_step_min`` (DN), whichever is larger. On return ``h`` holds the normal matrix at
    ``ph``. Returns (converged, iterations, cost, chi2, unweighted SS).
    """
    cost, chi2, ss = evaluate(ph, yp, wq, t, r, dc, additive, ln_rref, md_y, md_w, md_t, prior,
                              h, gv)
    lam = 1e-3
    conv = False
    it = 0
    for it in range(1, max_iter + 1):
        for a in range(4):
            for c in range(4):
                hn[a, c] = h[a, c]
            hn[a, a] += lam * h[a, a] + 1e-12
            trial[a] = -gv[a]
        ok = solve4(hn, trial, step, scratch)
        # a parameter at a bound that the step pushes outward is held there (active set)
        fixed = False
        for a in range(4):
            if ok and ((ph[a] <= lo[a] and step[a] < 0) or (ph[a] >= hi[a] and step[a] > 0)):
                for c in range(4):
                    hn[a, c] = 0.0
                    hn[c, a] = 0.0
                hn[a, a] = 1.0
                trial[a] = 0.0
                fixed = True
        if fixed:
            ok = solve4(hn, trial, step, scratch)
        if not ok:
            lam *= 8.0
            if lam >= 1e9:
                break
            continue
        # the quadratic model predicts a chi-square gain of -g.step: below CONVERGED_CHI2 the
        # point is converged without another evaluation
        pred = -(gv[0] * step[0] + gv[1] * step[1] + gv[2] * step[2] + gv[3] * step[3])
        if pred < CONVERGED_CHI2 and lam < 1.0:
            conv = True
            break
        b_now = np.exp(ph[2])
        step[0] = min(max(step[0], -2.0), 2.0)
        step[2] = min(max(step[2], -1.0), 1.0)
        s_step = max(3.0 / b_now, s_step_min)
        step[1] = min(max(step[1], -s_step), s_step)
        size = 0.0
        for a in range(4):
            trial[a] = min(max(ph[a] + step[a], lo[a]), hi[a])
            size = max(size, abs(trial[a] - ph[a]) * (b_now if a == 1 else 1.0))
        ct, chi2t, sst = evaluate(trial, yp, wq, t, r, dc, additive, ln_rref, md_y, md_w, md_t,
                                  prior, hn, step)
        gain = cost - ct
        if np.isfinite(ct) and ct < cost:
            rel = gain / max(cost, 1e-300)
            for a in range(4):
                ph[a] = trial[a]
                gv[a] = step[a]
                for c in range(4):
                    h[a, c] = hn[a, c]
            cost, chi2, ss = ct, chi2t, sst
            lam = max(lam / 5.0, 1e-9)
            if rel < tol or gain < CONVERGED_CHI2:
                conv = True
                break
        else:
            lam = min(lam * 8.0, 1e9)
            if (abs(gain) < CONVERGED_CHI2 and lam > 1e2) or lam >= 1e9:
                conv = True  # no better point within the resolution of the cost
                break
        if size < 1e-9:
            conv = True
            break
    return conv and np.isfinite(cost), it, cost, chi2, ss


@njit(cache=True, error_model="numpy")
def external_sigma(h, ph, chi2, dof, out, col, cov, scratch):
    """Standard errors of (ln g, ln a, ln b, d) into ``out`` (4,) from the normal matrix ``h``
    in (ln g, s, ln b, d) (``ln a = ln g + ln r_ref - b s``), inflated by the reduced
    chi-square where it exceeds 1. ``col`` (4,) and ``cov``, ``scratch`` are scratch arrays."""
    for c in range(4):
        for a in range(4):
            col[a] = 1.0 if a == c else 0.0
        if not solve4(h, col, out, scratch):
            out[:] = np.inf
            return
        for a in range(4):
            cov[a, c] = out[a]
    b = np.exp(ph[2])
    over = max(chi2 / max(dof, 1), 1.0)
    v1 = -b
    v2 = -b * ph[1]
    var_lna = (cov[0, 0] + v1 * v1 * cov[1, 1] + v2 * v2 * cov[2, 2] + 2 * v1 * cov[0, 1]
               + 2 * v2 * cov[0, 2] + 2 * v1 * v2 * cov[1, 2])
    out[0] = np.sqrt(max(cov[0, 0], 0.0) * over)
    out[1] = np.sqrt(max(var_lna, 0.0) * over)
    out[2] = np.sqrt(max(cov[2, 2], 0.0) * over)
    out[3] = np.sqrt(max(cov[3, 3], 0.0) * over)


def _refresh_cache():
    from .. import model
    from . import kcache

    kcache.refresh([sample, _accumulate, evaluate, solve4, levenberg_marquardt, external_sigma],
                   [model])


_refresh_cache()
