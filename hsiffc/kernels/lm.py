"""Levenberg-Marquardt for one pixel of the leakage model, as numba functions on locals.

Parameters inside the iteration are ``phi = (ln g, s, ln b, d)``: ``g`` the responsivity (DN/ms
per unit of relative light rate), ``s`` the dynamic saturation level (DN) at the pixel's highest
light rate ``r_ref`` (so ``ln a = ln(g r_ref) - b s``), ``b`` (1/DN) and the dark level ``d``
(DN). The leakage parameters a and b are strongly correlated (a tiny change of b moves ln a by
b times the signal level); s and b much less, so the iteration converges in a few steps. Weak
priors on s and ln b keep the normal matrix regular where the data do not show leakage; step
limits and bounds keep every iterate finite.

The model and its gradient come from :mod:`hsiffc.kernels.gradient`. A pixel's samples are
passed as 1-D arrays: step means ``yq``, weights ``wq`` (0: left out), exposures ``tq`` and
relative light rates ``rq``; the last entry may be the merged dark sample (the weighted mean
of the pixel's dark samples, which lies on its dark line).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .gradient import response_gradient_fast, response_gradient_point

#: Options of the numba functions that run once or more per pixel on arrays their caller owns
#: (they allocate nothing): compiled without numba's reference counting (``_nrt=False``), so
#: that a call does not increment and decrement the count of every array argument with atomic
#: instructions (a pixel's fit makes hundreds of such calls, and the atomic updates contend
#: when the threads share the arrays). Allocating, or returning an array, fails to
#: compile here: keep those in the calling kernel. Not cached on their own: they are compiled
#: into the cached entry points that call them (:func:`hsiffc.kernels.pixelfit.fit_block`,
#: :func:`hsiffc.kernels.pixelsamples.pixel_samples`), whose names carry the source digest
#: (:mod:`hsiffc.kernels.launch`).
LOCALS_ONLY = {"cache": False, "error_model": "numpy", "_nrt": False}
B_MIN, B_MAX = 1e-6, 1.0  # bounds of b, 1/DN
CONVERGED_CHI2 = 1e-3  # chi-square gain below which a pixel is converged (~0.03 sigma)
#: a step predicted to gain less chi-square than this (0.3 sigma of a parameter) while the
#: damping is below TAKEN_LAMBDA (the last steps were accepted) is taken without evaluating
#: the model at its end
TAKEN_CHI2 = 0.1
TAKEN_LAMBDA = 1e-2


@njit(**LOCALS_ONLY, inline="always")
def _internal(y, dlnk, dlna, dlnb, dd, t, kg, k, dc, additive, s, b):
    """Response and Jacobian in (ln g, s, ln b, d) from the model's point derivatives."""
    share = kg / (k if k > 0.0 else 1.0) if k > 0.0 else 0.0
    y_out = y + dc * t if additive else y
    return y_out, dlnk * share + dlna, -b * dlna, dlnb - b * s * dlna, dd


@njit(**LOCALS_ONLY, inline="always")
def sample(t, r, g, ln_a, dc, additive, s, b, d):
    """Model value and Jacobian with respect to (ln g, s, ln b, d) at one sample, any input.

    ``dc`` (DN/ms) adds to the light rate, or (``additive``) to the response as ``dc t``.
    """
    kg = g * r
    k = kg if additive else kg + dc
    y, dlnk, dlna, dlnb, dd = response_gradient_point(t, k, ln_a, b, d)
    return _internal(y, dlnk, dlna, dlnb, dd, t, kg, k, dc, additive, s, b)


@njit(**LOCALS_ONLY)
def evaluate(ph, yq, wq, tq, rq, dc, additive, ln_rref, prior, h, gv, buf, n):
    """Weighted cost (data chi-square + priors) at ``ph``, the normal matrix ``h`` (4 x 4) and
    the half gradient ``gv``. Returns (cost, chi2, unweighted SS).

    ``yq``, ``wq``, ``tq``, ``rq`` are the pixel's samples, the first ``n`` of them used (the
    caller packs the fitted ones there; weight 0: left out); ``prior`` =
    (s0, ln b0, weight of s, weight of ln b); ``buf`` a (5, >= n) scratch array. The model is
    evaluated for all samples in one branch-free loop (vectorised), repaired by the
    log-domain form where it cannot hold, then accumulated.
    """
    g = np.exp(ph[0])
    s, ln_b, d = ph[1], ph[2], ph[3]
    b = np.exp(ln_b)
    ln_a = ph[0] + ln_rref - b * s
    c = np.exp(ln_a + b * d)
    bad = 0
    for i in range(n):
        kg = g * rq[i]
        k = kg if additive else kg + dc
        y, dlnk, dlna, dlnb, dd, ok = response_gradient_fast(tq[i], k, b, d, c)
        y, j0, j1, j2, j3 = _internal(y, dlnk, dlna, dlnb, dd, tq[i], kg, k, dc, additive, s, b)
        buf[0, i] = y - yq[i]
        buf[1, i] = j0
        buf[2, i] = j1
        buf[3, i] = j2
        buf[4, i] = j3
        bad += 0 if ok else 1
    if bad:  # rare: the whole pixel in the log-domain form
        for i in range(n):
            y, j0, j1, j2, j3 = sample(tq[i], rq[i], g, ln_a, dc, additive, s, b, d)
            buf[0, i] = y - yq[i]
            buf[1, i] = j0
            buf[2, i] = j1
            buf[3, i] = j2
            buf[4, i] = j3
    chi2 = ss = 0.0
    h00 = h10 = h11 = h20 = h21 = h22 = h30 = h31 = h32 = h33 = 0.0
    g0 = g1 = g2 = g3 = 0.0
    for i in range(n):
        wi = wq[i]
        if wi > 0.0:
            res, j0, j1, j2, j3 = buf[0, i], buf[1, i], buf[2, i], buf[3, i], buf[4, i]
            ss += res * res
            chi2 += wi * res * res
            w0, w1, w2, w3 = wi * j0, wi * j1, wi * j2, wi * j3
            g0 += w0 * res
            g1 += w1 * res
            g2 += w2 * res
            g3 += w3 * res
            h00 += w0 * j0
            h10 += w1 * j0
            h11 += w1 * j1
            h20 += w2 * j0
            h21 += w2 * j1
            h22 += w2 * j2
            h30 += w3 * j0
            h31 += w3 * j1
            h32 += w3 * j2
            h33 += w3 * j3
    ds = s - prior[0]
    db = ln_b - prior[1]
    h[0, 0] = h00
    h[1, 1] = h11 + prior[2]
    h[2, 2] = h22 + prior[3]
    h[3, 3] = h33
    h[0, 1] = h[1, 0] = h10
    h[0, 2] = h[2, 0] = h20
    h[1, 2] = h[2, 1] = h21
    h[0, 3] = h[3, 0] = h30
    h[1, 3] = h[3, 1] = h31
    h[2, 3] = h[3, 2] = h32
    gv[0] = g0
    gv[1] = g1 + prior[2] * ds
    gv[2] = g2 + prior[3] * db
    gv[3] = g3
    return chi2 + prior[2] * ds * ds + prior[3] * db * db, chi2, ss


@njit(**LOCALS_ONLY)
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


@njit(**LOCALS_ONLY)
def levenberg_marquardt(ph, yq, wq, tq, rq, dc, additive, ln_rref, prior, lo, hi, s_step_min,
                        max_iter, tol, h, gv, hn, step, trial, scratch, buf, n):
    """Iterate from ``ph`` (updated in place) to the minimum of :func:`evaluate` over the first
    ``n`` samples.

    ``lo``, ``hi`` (4,) bound the parameters. A step moves ln g by at most 2, ln b by at most
    1 and s by at most 3/b or ``s_step_min`` (DN), whichever is larger. On return ``h`` holds the normal matrix at
    ``ph``. Returns (converged, iterations, cost, chi2, unweighted SS).
    """
    cost, chi2, ss = evaluate(ph, yq, wq, tq, rq, dc, additive, ln_rref, prior, h, gv, buf, n)
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
        if pred < TAKEN_CHI2 and lam < TAKEN_LAMBDA:
            # a Gauss-Newton step in the quadratic regime: its gain is the predicted one (to
            # about pred^2), so it is taken without evaluating the model at its end (the
            # evaluation would only confirm it); chi2, SS and the normal matrix stay those of
            # the last evaluated point (chi2 higher by at most pred)
            for a in range(4):
                ph[a] = trial[a]
            conv = True
            break
        ct, chi2t, sst = evaluate(trial, yq, wq, tq, rq, dc, additive, ln_rref, prior, hn, step,
                                  buf, n)
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


@njit(**LOCALS_ONLY)
def external_sigma(h, ph, chi2, dof, out, col, cov, scratch):
    """Standard errors of (ln g, ln a, ln b, d) into ``out`` (4,) from the normal matrix ``h``
    in (ln g, s, ln b, d) (``ln a = ln g + ln r_ref - b s``), inflated by the reduced
    chi-square where it exceeds 1: with ``h = L L^T`` (Cholesky, into ``cov``), the variance
    of ``v . phi`` is ``|L^-1 v|^2``. ``col`` (4,) and ``scratch`` are scratch arrays."""
    for a in range(4):
        for c in range(a + 1):
            acc = h[a, c]
            for m in range(c):
                acc -= cov[a, m] * cov[c, m]
            if a == c:
                if not acc > 0.0:
                    out[:] = np.inf
                    return
                cov[a, a] = np.sqrt(acc)
            else:
                cov[a, c] = acc / cov[c, c]
    b = np.exp(ph[2])
    over = max(chi2 / max(dof, 1), 1.0)
    for q in range(4):
        # v: ln g; ln a (d ln a = d ln g - b ds - b s d ln b); ln b; d
        for a in range(4):
            col[a] = 0.0
        if q == 1:
            col[0], col[1], col[2] = 1.0, -b, -b * ph[1]
        else:
            col[q] = 1.0
        var = 0.0
        for a in range(4):  # forward substitution L z = v, var = z . z
            acc = col[a]
            for m in range(a):
                acc -= cov[a, m] * scratch[0, m]
            scratch[0, a] = acc / cov[a, a]
            var += scratch[0, a] * scratch[0, a]
        out[q] = np.sqrt(var * over)

