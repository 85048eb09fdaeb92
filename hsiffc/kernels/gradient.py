"""The leakage model's response with its derivatives, per point, for fits (numba).

:func:`hsiffc.leakage.model.response_and_gradient` and the calibration's per-pixel fit
(:mod:`hsiffc.kernels.lm`) evaluate the model through these functions. The closed form of
:mod:`hsiffc.kernels.leakage` reads, with ``x = b k t`` and ``c = a e^{b d}`` (the leakage rate
at the dark level, DN/ms)::

    e^{-b (Y - d)} = Z = e^{-x} + c (1 - e^{-x}) / k        (c b t at k = 0)

Both terms are positive, so ``Y = d - ln Z / b`` has no cancellation. The derivatives follow
from ``w2 = L / Z``, the leakage term's share (``L`` the second term)::

    dY/d ln k = (x w1 - w2 (x e^{-x} / (1 - e^{-x}) - 1)) / b
    dY/d ln a = -w2 / b,    dY/d d = w1 = 1 - w2
    dY/d ln b = (ln Z + x w1 - w2 (b d + 1 + x e^{-x} / (1 - e^{-x}) - 1)) / b

:func:`response_gradient_fast` takes one exp and one log per point and reports where Z leaves
the safe range; :func:`response_gradient_point` then uses the log-domain form. (The fit's
loop over a pixel's ~20 samples ends in a reduction, which LLVM does not vectorise without
fastmath, so libm's scalar exp and log are the faster choice here.) Precision: float64, the
response within 1e-9 DN of :func:`hsiffc.leakage.model.response` (tests).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .launch import JIT_OPTIONS, Kernel
from .leakage import BLOCK
from .operands import at

__all__ = ["response_gradient_fast", "response_gradient_point", "response_gradient_kernel"]

_JIT = {**JIT_OPTIONS, "cache": False}  # compiled into the kernels that call them
_INL = {**_JIT, "inline": "always"}


@njit(**_INL)
def response_gradient_fast(t, k, b, d, c):
    """(Y, dY/d ln k, dY/d ln a, dY/d ln b, dY/d d, ok) at one point, branch-free.

    ``c = exp(ln a + b d)`` is per pixel (the caller computes it once). ``ok`` is False where
    Z under- or overflows (use :func:`response_gradient_point` there).
    """
    x = b * k * t
    if x < 1e-4:  # series of e^-x, (1 - e^-x) / k and x e^-x / (1 - e^-x) - 1
        ex = 1.0 - x * (1.0 - x * (0.5 - x / 6.0))
        em_over_k = b * t * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x / 24.0)))
        xdlp = x * (-0.5 + x / 12.0)
    else:
        ex = np.exp(-x)
        em = 1.0 - ex
        em_over_k = em / k
        xdlp = x * ex / em - 1.0
    leak = c * em_over_k
    z = ex + leak
    ln_z = np.log(z)
    w2 = leak / z
    w1 = 1.0 - w2
    inv_b = 1.0 / b
    y = d - ln_z * inv_b
    dlnk = (x * w1 - w2 * xdlp) * inv_b
    dlnb = (ln_z + x * w1 - w2 * (b * d + 1.0 + xdlp)) * inv_b
    ok = (z >= 1e-290) and (z <= 1e290)
    return y, dlnk, -w2 * inv_b, dlnb, w1, ok


@njit(**_JIT)
def response_gradient_point(t, k, ln_a, b, d):
    """(Y, dY/d ln k, dY/d ln a, dY/d ln b, dY/d d) at one point, valid for any input:
    the fast form where it holds, the log-domain form elsewhere."""
    c = np.exp(ln_a + b * d)
    y, dlnk, dlna, dlnb, dd, ok = response_gradient_fast(t, k, b, d, c)
    if ok:
        return y, dlnk, dlna, dlnb, dd
    x = b * k * t
    if x < 1e-4:
        em_over_k = b * t * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x / 24.0)))
        xdlp = x * (-0.5 + x / 12.0)
    else:
        em = -np.expm1(-x)
        em_over_k = em / k
        xdlp = x * np.exp(-x) / em - 1.0
    ln_leak = ln_a + b * d + np.log(em_over_k)  # ln L, -inf for a = 0 or t = 0
    if ln_leak > -x:
        ln_z = ln_leak + np.log1p(np.exp(-x - ln_leak))
    else:
        ln_z = -x + np.log1p(np.exp(ln_leak + x))
    w2 = np.exp(ln_leak - ln_z)
    w1 = 1.0 - w2
    return (d - ln_z / b, (x * w1 - w2 * xdlp) / b, -w2 / b,
            (ln_z + x * w1 - w2 * (b * d + 1.0 + xdlp)) / b, w1)


def _gradient_loop(t, k, a, b, d, out):
    """``out[:, i]`` = (Y, dY/d ln k, dY/d ln a, dY/d ln b, dY/d d) at point i; each input a
    scalar or a flat array of ``out.shape[1]``."""
    n = out.shape[1]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            ai = at(a, i)
            la = np.log(ai) if ai > 0 else -np.inf
            y, g0, g1, g2, g3 = response_gradient_point(at(t, i), at(k, i), la, at(b, i),
                                                        at(d, i))
            out[0, i] = y
            out[1, i] = g0
            out[2, i] = g1
            out[3, i] = g2
            out[4, i] = g3


response_gradient_kernel = Kernel(_gradient_loop, 5)
