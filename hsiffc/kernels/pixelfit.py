"""The per-pixel fit as one parallel numba kernel: weights, dark model, linear model, start
values, Levenberg-Marquardt, fallback.

Per pixel, in locals only (no (samples x pixels) temporaries):

1. **Samples and weights** (:mod:`hsiffc.kernels.pixelsamples`): the pixel's step means
   are gathered; weights are given, or come from the photon-transfer noise model
   ``var = gain * (signal above the dark line) + read_var`` divided by the frames per step.
2. **Dark model** from the dark samples (rate 0): weighted line ``d + dc t`` through them
   (``dc`` estimated when asked, else given); with ``merge`` they enter the light fit as one
   sample (their weighted mean, which lies on that line).
3. **Linear model** ``Y = d + (g r + dc) t``: closed-form weighted least squares on the same
   samples. It is the fallback and the yardstick (the leakage fit must not fit worse).
4. **Start values** of the leakage model: the dark level from the dark frames (the linear
   model's without them), g from the samples below half the pixel's highest level, b and the
   saturation margin from the caller (sensor-wide values) or small grids (the best by cost).
5. **Levenberg-Marquardt** (:mod:`hsiffc.kernels.lm`) with bounds on every parameter.
6. **Fallback**: where the leakage fit does not converge or fits worse than the linear model,
   the linear model is used (a = 0); each pixel gets a status code saying which and why.

:func:`fit_block` takes its operands in named groups (:class:`~.pixelsamples.SweepSamples`,
:class:`~.pixelsamples.Steps`, :class:`~.pixelsamples.Noise`, :class:`DarkModel`,
:class:`Starts`, :class:`FitControl`, :class:`FitOutputs`) and hands each pixel its per-block
scratch arrays as a :class:`Workspace`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .launch import cached_jit
from .lm import (
    B_MAX,
    B_MIN,
    LOCALS_ONLY,
    evaluate,
    external_sigma,
    levenberg_marquardt,
    sample,
)
from .pixelsamples import BLOCK, dark_line, gather

# fit status codes (one uint8 per pixel)
LEAKAGE = 0
LINEAR_WORSE = 1
LINEAR_NOT_CONVERGED = 2
TOO_FEW = 3
NO_LIGHT = 4
NO_SIGNAL = 5
UNDETERMINED = 6
NO_FIT = (NO_LIGHT, NO_SIGNAL, UNDETERMINED)  # statuses without any fitted parameters
STATUS_REASONS = {
    LEAKAGE: "leakage model fitted",
    LINEAR_WORSE: "linear model used: the leakage fit was worse than the plain linear model",
    LINEAR_NOT_CONVERGED: "linear model used: the leakage fit did not converge",
    TOO_FEW: "linear model used: too few valid samples for the leakage model (fewer than 5)",
    NO_LIGHT: "no valid light sample (all clipped, full-well, non-finite or missing)",
    NO_SIGNAL: "no signal: the response does not grow with the light (dead pixel)",
    UNDETERMINED: "fewer than two distinct valid light doses and no dark sample: the response "
                  "is undetermined",
}
MIN_LEAK_SAMPLES = 5
# columns of the float output (P, 13) and the integer output (P, 3)
F_THETA, F_SIGMA, F_DC, F_CHI2, F_CHI2_LIN, F_RMS, F_RREF = 0, 4, 8, 9, 10, 11, 12
I_N, I_STATUS, I_ITER = 0, 1, 2


class DarkModel(NamedTuple):
    """How the dark samples and the dark current enter the fit."""

    merge: bool  #: the dark samples enter the light fit as one (their weighted mean)
    estimate_dc: bool  #: dark current from the dark samples' line, else ``dc_in``
    dc_in: object  #: (P,) float64 dark current, DN/ms (read unless ``estimate_dc``)
    additive: bool  #: dark current added after the leakage, else to the light rate


class Starts(NamedTuple):
    """Start values of the leakage model."""

    b_starts: object  #: float64 start values of b, 1/DN
    margins: object  #: float64 saturation margins above the highest sample, in 1/b
    theta0: object  #: (P, 4) float64 start values instead, or (0, 4)


class FitControl(NamedTuple):
    """The Levenberg-Marquardt fit's settings."""

    prior_sigma: float  #: width of the prior on the saturation level and ln b
    max_iter: int  #: iterations (0: start values only)
    tol: float  #: relative cost change at convergence
    fallback: bool  #: the linear model (a = 0) where the leakage fit fails
    fix_dark: bool  #: the dark level held at the dark frames' line (where the pixel has them;
    #: its sigma is then that line's error at zero exposure)


class FitOutputs(NamedTuple):
    """Filled in place: ``out_f`` (P, 13) float64 and ``out_i`` (P, 3) int32 (columns
    ``F_*`` and ``I_*``)."""

    out_f: object
    out_i: object


class Workspace(NamedTuple):
    """Scratch arrays of one parallel task (a block of pixels fitted one after the other)."""

    yq: object  #: (S + 1,) the fit's samples: levels, weights, exposures, rates
    wq: object
    tq: object
    rq: object
    buf: object  #: (5, S + 1)
    h: object  #: (4, 4) normal matrix
    gv: object  #: (4,) gradient
    hn: object  #: (4, 4)
    step: object  #: (4,)
    ph: object  #: (4,) parameters
    trial: object  #: (4,)
    prior: object  #: (4,)
    cov: object  #: (4, 4)
    scratch: object  #: (4, 5)
    lo: object  #: (4,) bounds
    hi: object  #: (4,)


@njit(**LOCALS_ONLY)
def _fit_pixel(p, yp, wp, steps, infit, weights_given, noise, darks, starts, control, outputs,
               work):
    t, r, light, dark, nfr = steps
    gain, read_var = noise
    merge, estimate_dc, dc_in, additive = darks
    dc_given = dc_in[p]
    b_starts, margins, theta0 = starts
    prior_sigma, max_iter, tol, fallback, fix_dark = control
    out_f, out_i = outputs
    yq, wq, tq, rq, buf, h, gv, hn, step, ph, trial, prior, cov, scratch, lo, hi = work
    n = t.size
    (nd, nl, sw, md_t, md_y, dc, ut, uy, utt, uty, uyy, t_dark_max, var_d) = dark_line(
        yp, wp, t, light, dark, estimate_dc, dc_given, weights_given, nfr, gain, read_var)
    held = fix_dark and nd > 0  # the dark level held at the dark frames' line
    sigma_held = np.sqrt(var_d)  # its error: the dark frames' line's
    md_w = sw if merge else 0.0
    # the fit's samples, packed: the valid light ones (and unmerged darks), the merged dark
    # (samples left out are not evaluated)
    nq = 0
    for i in range(n):
        if infit[i] and wp[i] > 0:
            yq[nq] = yp[i]
            wq[nq] = wp[i]
            tq[nq] = t[i]
            rq[nq] = r[i]
            nq += 1
    if md_w > 0:
        yq[nq], wq[nq], tq[nq], rq[nq] = md_y, md_w, md_t, 0.0
        nq += 1
    out_f[p, F_DC] = dc
    out_i[p, I_N] = nl + nd
    out_i[p, I_ITER] = 0
    # -- linear model: z = y - dc t = d + g u (u = r t), same samples as the leakage fit ----
    s0 = s1 = s2 = z0 = z1 = 0.0
    ymax = -np.inf
    rref = 0.0
    for i in range(n + 1):
        if i < n:
            wi = wp[i]
            if wi <= 0 or not infit[i]:
                continue
            u = r[i] * t[i]
            z = yp[i] - dc * t[i]
            if light[i]:
                ymax = max(ymax, yp[i])
                rref = max(rref, r[i])
        else:
            wi = md_w
            if wi <= 0:
                continue
            u = 0.0
            z = md_y - dc * md_t
        s0 += wi
        s1 += wi * u
        s2 += wi * u * u
        z0 += wi * z
        z1 += wi * u * z
    out_f[p, F_RREF] = rref
    den = s0 * s2 - s1 * s1
    nfit = nl + ((1 if md_w > 0 else 0) if merge else nd)
    if nl == 0 or not (den > 1e-12 * s0 * s2) or rref <= 0:
        out_i[p, I_STATUS] = NO_LIGHT if nl == 0 else UNDETERMINED
        out_f[p, :F_DC] = np.nan
        out_f[p, F_SIGMA:F_SIGMA + 4] = np.inf
        out_f[p, F_SIGMA + 3] = sigma_held if held else np.inf
        out_f[p, F_CHI2:F_RREF] = np.nan
        return
    if held:  # the line through it: d = the dark frames' intercept, g by least squares
        d_lin = md_y - dc * md_t
        g_lin = (z1 - d_lin * s1) / s2
    else:
        g_lin = (s0 * z1 - s1 * z0) / den
        d_lin = (z0 - g_lin * s1) / s0
    chi2_lin = 0.0
    ss_lin = 0.0
    for i in range(n):
        wi = wp[i]
        if wi <= 0:
            continue
        res = d_lin + (g_lin * r[i] + dc) * t[i] - yp[i]
        ss_lin += res * res
        if infit[i]:
            chi2_lin += wi * res * res
    if md_w > 0:
        res = d_lin + dc * md_t - md_y
        chi2_lin += md_w * res * res
    out_f[p, F_CHI2_LIN] = chi2_lin
    if not g_lin > 0:
        out_i[p, I_STATUS] = NO_SIGNAL
        out_f[p, :F_DC] = np.nan
        out_f[p, F_SIGMA:F_SIGMA + 4] = np.inf
        out_f[p, F_SIGMA + 3] = sigma_held if held else np.inf
        out_f[p, F_CHI2] = out_f[p, F_RMS] = np.nan
        return
    ln_rref = np.log(rref)
    leak_ok = nfit >= MIN_LEAK_SAMPLES
    # -- start values ----------------------------------------------------------------------
    best = np.inf
    if theta0.shape[0] > 0 and np.isfinite(theta0[p, 0]) and np.isfinite(theta0[p, 2]):
        b0 = np.exp(theta0[p, 2])
        ph[0] = theta0[p, 0]
        ph[1] = (theta0[p, 0] + ln_rref - theta0[p, 1]) / b0
        ph[2] = theta0[p, 2]
        ph[3] = theta0[p, 3]
        if not np.isfinite(ph[1]):
            ph[1] = ymax + 30.0 / b0
    else:
        # the dark level measured by the dark frames (their line at t = 0), else the linear
        # model's; g from the samples below half the highest level (leakage bends the upper)
        d0 = md_y - dc * md_t if nd > 0 else d_lin
        su = sz = 0.0
        for i in range(n):
            wi = wp[i]
            if wi <= 0 or not light[i] or (yp[i] - d0) > 0.5 * (ymax - d0):
                continue
            u = r[i] * t[i]
            su += wi * u * u
            sz += wi * u * (yp[i] - dc * t[i] - d0)
        g0 = sz / su if su > 0 and sz > 0 else g_lin
        prior[:] = 0.0
        for bi in range(b_starts.size):
            for mi in range(margins.size):
                trial[0] = np.log(g0)
                trial[1] = ymax + margins[mi] / b_starts[bi]
                trial[2] = np.log(b_starts[bi])
                trial[3] = d0
                cst = np.inf
                if b_starts.size * margins.size > 1:
                    cst, _, _ = evaluate(trial, yq, wq, tq, rq, dc, additive, ln_rref, prior, h,
                                         gv, buf, nq)
                if cst <= best:
                    best = cst
                    for a in range(4):
                        ph[a] = trial[a]
    if max_iter <= 0:  # start values only
        b = np.exp(ph[2])
        out_f[p, 0] = ph[0]
        out_f[p, 1] = ph[0] + ln_rref - b * ph[1]
        out_f[p, 2] = ph[2]
        out_f[p, 3] = ph[3]
        out_f[p, F_SIGMA:F_SIGMA + 4] = np.nan
        out_f[p, F_CHI2] = best
        out_f[p, F_RMS] = np.nan
        out_i[p, I_STATUS] = LEAKAGE if leak_ok else TOO_FEW
        return
    status = TOO_FEW
    chi2 = ss = np.nan
    b_start = np.exp(ph[2])
    if leak_ok:
        prior[0] = ph[1]
        prior[1] = ph[2]
        prior[2] = (b_start / prior_sigma) ** 2
        prior[3] = 1.0 / prior_sigma ** 2
        # bounds: ln g within 20 e-folds of the linear slope, b in [B_MIN, B_MAX], d and s
        # within a wide band around the data
        span = max(ymax - d_lin, 1.0)
        lo[0], hi[0] = np.log(g_lin) - 20.0, np.log(g_lin) + 20.0
        lo[3], hi[3] = d_lin - 10.0 * span - 100.0, d_lin + 10.0 * span + 100.0
        lo[1], hi[1] = lo[3], ymax + 1e4 * span
        lo[2], hi[2] = np.log(B_MIN), np.log(B_MAX)
        if held:  # at the bounds: the iteration's active set never frees it
            lo[3] = hi[3] = d_lin
        for a in range(4):
            ph[a] = min(max(ph[a], lo[a]), hi[a])
        conv, it, _cost, chi2, ss = levenberg_marquardt(
            ph, yq, wq, tq, rq, dc, additive, ln_rref, prior, lo, hi, 0.2 * span, max_iter,
            tol, h, gv, hn, step, trial, scratch, buf, nq)
        out_i[p, I_ITER] = it
        status = LEAKAGE
        if not conv:
            status = LINEAR_NOT_CONVERGED
        elif chi2 > chi2_lin * (1.0 + 1e-9) + 1e-9:
            status = LINEAR_WORSE
    out_i[p, I_STATUS] = status
    if status == LINEAR_WORSE or status == TOO_FEW or (status != LEAKAGE and fallback):
        # the linear model: a = 0 with ``fallback``; otherwise the same curve in leakage
        # parameters (b at its start value, the saturation level 40/b above the highest
        # sample, where the leakage is e^-40 of the light rate), a finite warm start
        out_f[p, 0] = np.log(g_lin)
        out_f[p, 1] = -np.inf if fallback else np.log(g_lin) + ln_rref - b_start * ymax - 40.0
        out_f[p, 2] = np.log(b_start)
        out_f[p, 3] = d_lin
        out_f[p, F_CHI2] = chi2_lin
        out_f[p, F_RMS] = np.sqrt(ss_lin / max(nl + nd, 1))
        # sigmas of g and d from the 2-parameter normal matrix
        over = max(chi2_lin / max(nfit - (1 if held else 2), 1), 1.0)
        out_f[p, F_SIGMA] = np.sqrt((1.0 / s2 if held else s0 / den) * over) / g_lin
        out_f[p, F_SIGMA + 1] = np.inf
        out_f[p, F_SIGMA + 2] = np.inf
        out_f[p, F_SIGMA + 3] = sigma_held if held else np.sqrt(s2 / den * over)
        return
    b = np.exp(ph[2])
    d = ph[3]
    ln_a = ph[0] + ln_rref - b * ph[1]
    out_f[p, 0] = ph[0]
    out_f[p, 1] = ln_a
    out_f[p, 2] = ph[2]
    out_f[p, 3] = d
    out_f[p, F_CHI2] = chi2
    # unweighted RMS over all valid samples: the fitted ones come with the last evaluation;
    # merged dark samples lie on the model's dark line d + dc t to 1e-3 DN wherever the
    # leakage at the dark level is that small over the longest dark exposure (closed form),
    # else they are evaluated one by one
    if merge and nd > 0:
        g = np.exp(ph[0])
        y_end, _, _, _, _ = sample(t_dark_max, 0.0, g, ln_a, dc, additive, ph[1], b, d)
        if abs(y_end - (d + dc * t_dark_max)) < 1e-3:
            ss += max(uyy - 2 * d * uy - 2 * dc * uty + nd * d * d + 2 * d * dc * ut
                      + dc * dc * utt, 0.0)
        else:
            for i in range(n):
                if wp[i] > 0 and dark[i]:
                    yi, _, _, _, _ = sample(t[i], 0.0, g, ln_a, dc, additive, ph[1], b, d)
                    ss += (yi - yp[i]) ** 2
    out_f[p, F_RMS] = np.sqrt(ss / max(nl + nd, 1))
    if held:  # errors given the dark level (its own error is the dark frames')
        for a in range(3):
            h[a, 3] = h[3, a] = 0.0
        h[3, 3] = 1.0
    external_sigma(h, ph, chi2, nfit - (3 if held else 4), step, trial, cov, scratch)
    for a in range(4):
        out_f[p, F_SIGMA + a] = step[a]
    if held:
        out_f[p, F_SIGMA + 3] = sigma_held


@njit(**LOCALS_ONLY)
def _fit_range(p0, p1, ty, tw, steps, infit, weights_given, noise, darks, starts, control,
               outputs, work):
    """Pixels ``p0:p1`` one after the other (their samples in the rows of ``ty``, ``tw``)."""
    for p in range(p0, p1):
        _fit_pixel(p, ty[p - p0], tw[p - p0], steps, infit, weights_given, noise, darks, starts,
                   control, outputs, work)


@cached_jit(parallel=True)
def fit_block(samples, steps, noise, darks, starts, control, outputs):
    """Fit every pixel (column) of ``samples.y`` (S, P) in parallel; see the module docstring.

    ``samples`` (:class:`~.pixelsamples.SweepSamples`): ``valid`` (S, P) marks usable samples;
    ``w`` (S, P) gives their weights (1 / variance, DN^-2), or is (0, 0) to use the noise model
    ``nfr / (gain * signal + read_var)`` (``steps.nfr`` (S,) frames per step; ``noise``
    :class:`~.pixelsamples.Noise`). ``steps`` (:class:`~.pixelsamples.Steps`): ``t``, ``r``,
    ``light``, ``dark`` (S,): exposure (ms), relative light rate, sample kind. ``darks``
    (:class:`DarkModel`): ``merge`` replaces the dark samples by their weighted mean in the
    fit; ``dc_in`` (P,) is the dark current (DN/ms) unless ``estimate_dc``; ``additive`` adds
    it after the leakage instead of to the light rate. ``starts`` (:class:`Starts`):
    ``b_starts``, ``margins``: start values of b (1/DN) and of the saturation margin above the
    highest sample (in 1/b); ``theta0`` (P, 4) start values instead, or (0, 4). ``control``:
    :class:`FitControl`. Outputs (:class:`FitOutputs`) are filled in place: ``out_f`` (P, 13)
    float64 (theta 4, sigma 4, dc, chi2, chi2 of the linear model, RMS, highest light rate of
    the fitted samples) and ``out_i`` (P, 3) int32 (valid samples, status, iterations).
    """
    y, valid, w = samples
    t, _, light, dark, nfr = steps
    read_var = noise.read_var
    npx = y.shape[1]
    n = t.size
    infit = light | (dark & (not darks.merge))
    weights_given = w.shape[0] > 0
    nblocks = (npx + BLOCK - 1) // BLOCK
    for blk in prange(nblocks):
        p0 = blk * BLOCK
        p1 = min(npx, p0 + BLOCK)
        ty = np.empty((BLOCK, n))
        tw = np.empty((BLOCK, n))
        gather(p0, p1, y, valid, w, nfr, read_var, light, dark, ty, tw)
        work = Workspace(np.empty(n + 1), np.empty(n + 1), np.empty(n + 1), np.empty(n + 1),
                         np.empty((5, n + 1)), np.empty((4, 4)), np.empty(4), np.empty((4, 4)),
                         np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty((4, 4)),
                         np.empty((4, 5)), np.empty(4), np.empty(4))
        _fit_range(p0, p1, ty, tw, steps, infit, weights_given, noise, darks, starts, control,
                   outputs, work)
