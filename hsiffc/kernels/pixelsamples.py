"""The samples each pixel's fit sees, gathered from (steps x pixels) arrays by numba kernels.

:func:`gather` copies a block of pixels' step means and weights into per-pixel rows (streaming
the (S, P) inputs row by row); :func:`dark_line` fits a pixel's dark line and sets the
noise-model weights of its light samples (:func:`light_weights`). The per-pixel fit
(:mod:`hsiffc.kernels.pixelfit`) calls them pixel by pixel; :func:`pixel_samples` returns what
they prepare, for comparisons with other fitters.

The kernels take their operands in named groups (:class:`SweepSamples`, :class:`Steps`,
:class:`Noise`; numba types a named tuple per combination of its members' types); the compiled
per-pixel functions they call keep separate arguments.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .launch import cached_jit
from .lm import LOCALS_ONLY

BLOCK = 128  # pixels per parallel task


class SweepSamples(NamedTuple):
    """Every pixel's samples, one row per step (all C-contiguous)."""

    y: object  #: (S, P) float64 step means, DN
    valid: object  #: (S, P) bool, usable samples
    w: object  #: (S, P) float64 weights (1 / variance, DN^-2), or (0, 0): the noise model's


class Steps(NamedTuple):
    """What each step is: (S,) arrays."""

    t: object  #: float64 exposure, ms
    r: object  #: float64 relative light rate (0 for darks)
    light: object  #: bool, a light step
    dark: object  #: bool, a dark step
    nfr: object  #: float64 frames averaged into the step mean


class Noise(NamedTuple):
    """The photon-transfer noise model ``var = gain * signal + read_var`` (per frame)."""

    gain: float  #: DN/e-
    read_var: float  #: DN^2


class SampleOutputs(NamedTuple):
    """What :func:`pixel_samples` writes."""

    y: object  #: (P, S) float64 step means, DN
    w: object  #: (P, S) float64 weights (0: left out)
    dark: object  #: (P, 4) float64 summed dark weight, mean dark exposure and level, dc


@njit(**LOCALS_ONLY)
def gather(p0, p1, y, valid, w, nfr, read_var, light, dark, ty, tw):
    """Samples of pixels ``p0:p1`` into the rows of ``ty``; their weights into ``tw`` (0: left
    out; without given weights the darks' ``nfr / read_var``, the light ones set later). Reads
    ``y`` (S, P) row by row, so memory is streamed."""
    given = w.shape[0] > 0
    for i in range(light.size):
        use = light[i] or dark[i]
        for p in range(p0, p1):
            yi = y[i, p]
            ty[p - p0, i] = yi
            ok = use and valid[i, p] and np.isfinite(yi)
            if given:
                wi = w[i, p]
                tw[p - p0, i] = wi if ok and wi > 0 and np.isfinite(wi) else 0.0
            else:
                tw[p - p0, i] = nfr[i] / read_var if ok else 0.0


@njit(**LOCALS_ONLY)
def light_weights(yp, wp, t, light, nfr, gain, read_var, d_line, dc_line, has_dark):
    """Noise-model weights of the light samples: signal above the dark line (or above the
    lowest light sample without darks)."""
    n = t.size
    floor = np.inf
    if not has_dark:
        for i in range(n):
            if wp[i] > 0 and light[i]:
                floor = min(floor, yp[i])
    for i in range(n):
        if wp[i] > 0 and light[i]:
            dark_level = d_line + dc_line * t[i] if has_dark else floor
            wp[i] = nfr[i] / (gain * max(yp[i] - dark_level, 0.0) + read_var)


@njit(**LOCALS_ONLY)
def dark_line(yp, wp, t, light, dark, estimate_dc, dc_given, weights_given, nfr, gain,
             read_var):
    """Dark line of one pixel and its light weights (set in ``wp`` unless given).

    Returns (dark samples, light samples, summed dark weight, weighted mean dark exposure and
    level, dark current, unweighted dark sums t, y, tt, ty, yy, longest dark exposure, variance
    of the line's level at zero exposure in DN^2: of the weighted line's intercept with an
    estimated dark current, else of the weighted mean; inf without a dark sample)."""
    n = t.size
    sw = swt = swy = swtt = swty = 0.0
    ut = uy = utt = uty = uyy = 0.0
    t_dark_max = 0.0
    nd = nl = 0
    for i in range(n):
        wi = wp[i]
        if wi <= 0:
            continue
        if dark[i]:
            ti, yi = t[i], yp[i]
            nd += 1
            sw += wi
            swt += wi * ti
            swy += wi * yi
            swtt += wi * ti * ti
            swty += wi * ti * yi
            ut += ti
            uy += yi
            utt += ti * ti
            uty += ti * yi
            uyy += yi * yi
            t_dark_max = max(t_dark_max, ti)
        elif light[i]:
            nl += 1
    dc = dc_given
    md_t = swt / sw if sw > 0 else 0.0
    md_y = swy / sw if sw > 0 else 0.0
    var_d = 1.0 / sw if sw > 0 else np.inf
    if estimate_dc:
        dc = 0.0
        den = sw * swtt - swt * swt
        if nd >= 2 and den > 1e-12 * sw * swtt:
            dc = max((sw * swty - swt * swy) / den, 0.0)
            var_d = swtt / den
    if not weights_given:
        light_weights(yp, wp, t, light, nfr, gain, read_var, md_y - dc * md_t, dc, nd > 0)
    return nd, nl, sw, md_t, md_y, dc, ut, uy, utt, uty, uyy, t_dark_max, var_d


@cached_jit(parallel=True)
def pixel_samples(samples, steps, noise, estimate_dc, dc_in, outputs):
    """The samples each pixel's fit sees, as :func:`hsiffc.kernels.pixelfit.fit_block`
    prepares them (:class:`SweepSamples`, :class:`Steps`, :class:`Noise`; ``dc_in`` (P,) the
    dark current, DN/ms, unless ``estimate_dc``), into ``outputs`` (:class:`SampleOutputs`):
    step means and weights (P, S; weight 0 = left out) and, per pixel, the summed dark weight,
    weighted mean dark exposure (ms) and level (DN), dark current (DN/ms)."""
    y, valid, w = samples
    t, _, light, dark, nfr = steps
    gain, read_var = noise
    out_y, out_w, out_dark = outputs
    npx = y.shape[1]
    weights_given = w.shape[0] > 0
    for blk in prange((npx + BLOCK - 1) // BLOCK):
        p0 = blk * BLOCK
        p1 = min(npx, p0 + BLOCK)
        gather(p0, p1, y, valid, w, nfr, read_var, light, dark, out_y[p0:p1], out_w[p0:p1])
        for p in range(p0, p1):
            res = dark_line(out_y[p], out_w[p], t, light, dark, estimate_dc, dc_in[p],
                            weights_given, nfr, gain, read_var)
            out_dark[p, 0] = res[2]
            out_dark[p, 1] = res[3]
            out_dark[p, 2] = res[4]
            out_dark[p, 3] = res[5]
