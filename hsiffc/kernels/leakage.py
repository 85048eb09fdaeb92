"""Compiled per-pixel kernels of the leakage model ``dY/dt = k - a e^{bY}`` (paper eq. 2).

These are *the* implementations behind :mod:`hsiffc.model` (its public functions validate and
broadcast, then call a kernel here); the per-point functions (``response_point``,
``invert_point``, ...) are public so that other compiled code (e.g. a per-pixel calibration
fit) evaluates the model with exactly the same arithmetic.

Precision: everything is computed in float64 (inputs may be float32 or float64). The
response keeps ~1e-13 DN (tests: against ``solve_ivp`` and against the previous numpy form);
the inversion converges to ``tol_dn + 8 eps |y|`` in DN like before; alpha is computed in
float64 and may be stored as float32 (1e-7 relative, far below any threshold's meaning).

Kernels run a branch-free ``prange`` loop over the pixels (vectorised by LLVM, 8 doubles per
instruction on AVX-512) for the common case and a second pass repairs the rare pixels it
cannot (over/underflow: the log-domain form; inversions that did not converge in the
vectorised iterations: a bracketed Halley iteration).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..dq import DQ
from .launch import JIT_OPTIONS, Kernel
from .operands import at
from .vmath import exp, exp_expm1, expm1, log, log_corrected, logaddexp

__all__ = ["BLOCK", "PENDING", "VECTOR_STEPS", "alpha_flags_kernel", "alpha_model_kernel",
           "alpha_model_point", "alpha_paper_kernel", "alpha_paper_point", "invert_kernel",
           "invert_point", "invert_vector", "leakage_bits", "response_fast", "response_kernel",
           "response_point", "response_robust"]

BLOCK = 4096
# Only the kernels (entry points, see launch.Kernel) are cached on disk. The per-point
# functions are compiled into each kernel that uses them: a cached function is machine code,
# which LLVM cannot inline (and vectorise) into a caller compiled later, and would go stale
# when a file it inlines changes. The vector-path ones are inlined already in numba's IR.
_JIT = {**JIT_OPTIONS, "cache": False}
_INL = {**_JIT, "inline": "always"}
_EPS = 2.220446049250313e-16
_BIG = 1.7976931348623157e308

# DQ bits as plain ints for compiled code
_NONFINITE = int(DQ.NONFINITE)
_SATURATED = int(DQ.SATURATED)
_BELOW_DARK = int(DQ.BELOW_DARK)
_UNREACHABLE = int(DQ.UNREACHABLE)
_NOT_CONVERGED = int(DQ.NOT_CONVERGED)
_LEAKAGE = int(DQ.LEAKAGE)


# -- the response ----------------------------------------------------------------------------

@njit(**_INL)
def response_fast(t, k, a, b, d):
    """(Y, ok): the response in the linear domain, branch-free.

    With x = b k t, ``e^{-bY} = e^{-bd-x} + a b t phi(x)``, phi(x) = (1 - e^{-x}) / x. While
    the leakage term q (relative to the first) is at most 1, ``Y = d + k t - log1p(q) / b``
    (exact in the linear regime); beyond it ``Y = -log(sum) / b``. ``ok`` is False where the
    sum under/overflows (then use :func:`response_robust`).
    """
    # Reciprocals and exponentials depend on the inputs only, so they run side by side; the
    # dependent chain (expm1, log) is what bounds the speed of this loop, not its length.
    x = b * k * t
    ix = 1.0 / x
    ib = 1.0 / b
    em = -expm1(-x)
    phi = em * ix if x > 0.0 else 1.0
    leak = a * b * t * phi
    e0 = exp(-b * d - x)
    q = leak * exp(b * d + x)  # leak / e0, without a division on the chain
    z = e0 + leak
    lin = q <= 1.0
    w = 1.0 + q if lin else z
    # log1p(q) in the linear domain (the rounding error of 1 + q folded in), log(z) beyond
    lw = log_corrected(w, (q - (w - 1.0)) if lin else 0.0)
    y = ((d + k * t) if lin else 0.0) - lw * ib
    ok = (z >= 1e-290) and (z <= 1e290)
    return y, ok


@njit(**_JIT)
def response_robust(t, k, a, b, d):
    """The response in the log domain: finite for any b k t, a/k, k = 0 and starting levels
    above the dynamic saturation level (``logaddexp`` of the two log terms)."""
    x = b * k * t
    lphi = -0.5 * x if x < 1e-8 else log(-expm1(-x) / x)
    return -logaddexp(-b * d - x, log(a) + log(b) + log(t) + lphi) / b


@njit(**_JIT)
def response_point(t, k, a, b, d):
    """Model response (DN) at one point: the fast form, the log-domain form where it fails."""
    y, ok = response_fast(t, k, a, b, d)
    return y if ok else response_robust(t, k, a, b, d)


def _response_loop(t, k, a, b, d, out):
    """``out[i] = Y(t, k, a, b, d)[i]``; each input a scalar or a flat array like ``out``."""
    n = out.shape[0]
    for i in prange(n):  # vectorised; NaN marks what the fast form cannot do
        y, ok = response_fast(at(t, i), at(k, i), at(a, i), at(b, i), at(d, i))
        out[i] = y if ok else np.nan
    for i in prange(n):
        if out[i] != out[i]:
            out[i] = response_robust(at(t, i), at(k, i), at(a, i), at(b, i), at(d, i))


response_kernel = Kernel(_response_loop, 5)


# -- the inversion ---------------------------------------------------------------------------
# Scaled by e^{bY} at the target Y, the model reads H(x) = e^{beta - x} + C phi(x) - 1 = 0 with
# beta = b (Y - d), C = a b t e^{bY}, x = b k t. H is convex and decreasing in x (phi is
# completely monotone), and H(x) = e^{b (Y - Y(x))} - 1, so |H| <= b tol means |Y(x) - Y| <=
# tol (to first order). Y <= d + k t gives x >= beta; above the dark level Y <= ln(k/a)/b
# gives x >= C: from x0 = max(beta, C) Newton climbs monotonically to the root, Halley's
# correction makes it cubic.

@njit(**_INL)
def _exp(x, vec):
    """e^x: the vectorisable form in vector loops, libm in scalar code (3 x lower latency).
    ``vec`` is a constant at every call site, so the other branch is compiled away."""
    return exp(x) if vec else math.exp(x)


@njit(**_INL)
def _log(x, vec):
    return log(x) if vec else (math.log(x) if x > 0.0 else (-np.inf if x == 0.0 else np.nan))


@njit(**_INL)
def _phi_derivs(x, vec):
    """(e^{-x}, phi, phi', phi'') at x >= 0 (series below 0.05, where the closed forms
    cancel). One reduction gives e^{-x} and 1 - e^{-x}, and one reciprocal, computed beside
    it rather than after it, serves the three quotients: the iteration's speed is bound by
    its chain of dependent operations."""
    if vec:
        ex, em = exp_expm1(-x)
        em = -em
    else:
        em = -math.expm1(-x)
        ex = 1.0 - em
    ix = 1.0 / x
    phi = em * ix if x > 0.0 else 1.0
    d1 = -(em - x * ex) * (ix * ix)
    d2 = (2.0 * em - x * ex * (x + 2.0)) * (ix * ix * ix)
    d1s = -0.5 + x * (1.0 / 3.0 - x * (0.125 - x * (1.0 / 30.0 - x / 144.0)))
    d2s = 1.0 / 3.0 - x * (0.25 - x * (0.1 - x * (1.0 / 36.0 - x / 168.0)))
    small = x < 0.05
    return ex, phi, (d1s if small else d1), (d2s if small else d2)


@njit(**_INL)
def _halley(x, beta, eb, c, vec):
    """H(x) and the next iterate (Halley, Newton when Halley's denominator is not positive).

    ``eb`` is ``e^beta``: the vector form takes ``e^{beta - x} = e^beta e^{-x}`` with
    ``e^{-x}`` from the reduction that gives phi (callers keep beta <= 700 there); scalar code
    takes ``e^{beta - x}`` directly (libm).
    """
    ex, phi, p1, p2 = _phi_derivs(x, vec)
    e = eb * ex if vec else math.exp(beta - x)
    h = e + c * phi - 1.0
    h1 = -e + c * p1
    h2 = e + c * p2
    den = 2.0 * h1 * h1 - h * h2
    halley = den > 0.0
    step = x - (2.0 * h * h1 if halley else h) / (den if halley else h1)
    step = step if step >= 0.0 else 0.5 * x
    return h, step


@njit(**_INL)
def _setup(y, t, a, b, d, full_scale, vec):
    """Flags known before iterating, target Y, beta, ln C, C, e^beta, H(0) and the start x.

    ``ln C = ln(a b t) + b Y``; where ``a b t`` is not a normal number the vectorised pass
    leaves the pixel to the scalar one (``ok`` False), which takes the logs one by one; so
    it does where beta > 700 (e^beta would overflow).
    """
    flags = 0
    finite = (abs(y) < np.inf) and (abs(a) < np.inf) and (abs(b) < np.inf) and (abs(d) < np.inf)
    sat = finite and y >= full_scale
    target = full_scale if sat else y
    flags = (_SATURATED if sat else 0) | (0 if finite else _NONFINITE)
    beta = b * (target - d)
    abt = a * b * t
    ok = finite and abt >= 1e-300 and abt < 1e300
    lnc = (_log(abt, vec) if vec else _log(a, vec) + _log(b, vec) + _log(t, vec)) + b * target
    c = _exp(min(lnc, 700.0), vec)
    eb = _exp(min(beta, 700.0), vec)
    h0 = eb + c - 1.0  # H at zero light
    x0 = max(beta, c) if target > d else 0.0
    return flags, ok and beta <= 700.0, target, beta, lnc, c, eb, h0, x0


@njit(**_JIT)
def invert_point(y, t, a, b, d, full_scale, k_max, tol_dn, max_iter):
    """Light rate k (DN/ms), DQ flags and iterations for one pixel (scalar code).

    Semantics as :func:`hsiffc.model.invert_response`; a bracketed Halley iteration.
    """
    flags, _, target, beta, lnc, c, eb, h0, x0 = _setup(y, t, a, b, d, full_scale, False)
    if flags & _NONFINITE:
        return 0.0, flags, 0
    if h0 <= 0.0:  # at or below what zero light gives
        if h0 < 0.0:
            flags |= _BELOW_DARK
        return 0.0, flags | (_UNREACHABLE if k_max < 0.0 else 0), 0
    if lnc > 700.0:  # needs more light than a double can hold
        return min(k_max, _BIG), flags | _NOT_CONVERGED | (_UNREACHABLE if k_max < _BIG else 0), 0
    tol = b * (tol_dn + 8.0 * _EPS * abs(target))
    lo, hi = x0, np.inf  # H(lo) >= 0 >= H(hi)
    xi = x0
    it = 0
    converged = False
    while True:
        h, nxt = _halley(xi, beta, eb, c, False)
        if abs(h) <= tol:
            converged = True
            break
        if it >= max_iter:
            break
        if h > 0.0:
            lo = max(lo, xi)
        else:
            hi = min(hi, xi)
        if not (nxt > lo and nxt < hi):
            nxt = 0.5 * (lo + hi) if hi < np.inf else max(2.0 * lo, lo + 1.0)
        xi = nxt
        it += 1
    k = xi / (b * t)
    if not converged:
        flags |= _NOT_CONVERGED
    if k > k_max:
        k = k_max
        flags |= _UNREACHABLE
    return k, flags, it


VECTOR_STEPS = 3
PENDING = 1 << 31  # scratch flag inside invert_kernel: left to the scalar pass


@njit(**_INL)
def invert_vector(y, t, a, b, d, full_scale, k_max, tol_dn):
    """(k, flags, done, alpha): three branch-free Halley steps from the lower bounds
    (vectorisable).

    ``done`` is False where the result is not trusted (non-finite input, zero light, extreme
    parameters, slow convergence): solve those pixels again with :func:`invert_point`.
    ``alpha`` is the model leakage percentage at the target response, ``100 a e^{bY} / k``,
    which the iteration has at hand: ``100 C / x`` (``C = a b t e^{bY}``, ``x = b k t``).
    """
    flags, ok, target, beta, lnc, c, eb, h0, x0 = _setup(y, t, a, b, d, full_scale, True)
    x = _halley(x0, beta, eb, c, True)[1]
    x = _halley(x, beta, eb, c, True)[1]
    x = _halley(x, beta, eb, c, True)[1]
    h = _halley(x, beta, eb, c, True)[0]
    tol = b * (tol_dn + 8.0 * _EPS * abs(target))
    done = ok and lnc <= 700.0 and h0 > 0.0 and abs(h) <= tol
    k = x / (b * t)
    over = k > k_max
    return (k_max if over else k), flags | (_UNREACHABLE if over else 0), done, 100.0 * c / x


def _invert_loop(y, t, a, b, d, full_scale, k_max, tol_dn, max_iter, k_out, flags_out,
                 iterations):
    """:func:`invert_point` over flat operands; ``iterations[block]`` gets each block's max
    (``ceil(n / BLOCK)`` entries).

    A branch-free pass (:func:`invert_vector`) runs three Halley steps from the lower bounds
    for every pixel (vectorised) and accepts those that then match the response within the
    tolerance; the others are solved again by :func:`invert_point`.
    """
    n = k_out.shape[0]
    vector = max_iter >= VECTOR_STEPS
    if vector:
        for i in prange(n):
            k, flags, done, _ = invert_vector(at(y, i), at(t, i), at(a, i), at(b, i),
                                              at(d, i), full_scale, k_max, tol_dn)
            k_out[i] = k
            flags_out[i] = flags | (0 if done else PENDING)
    for blk in prange((n + BLOCK - 1) // BLOCK):
        most = VECTOR_STEPS if vector else 0
        for i in range(blk * BLOCK, min(n, blk * BLOCK + BLOCK)):
            if vector and not (flags_out[i] & PENDING):
                continue
            k, f, it = invert_point(at(y, i), at(t, i), at(a, i), at(b, i), at(d, i),
                                    full_scale, k_max, tol_dn, max_iter)
            k_out[i] = k
            flags_out[i] = f
            most = max(most, it)
        iterations[blk] = most


invert_kernel = Kernel(_invert_loop, 9)


# -- the leakage percentage alpha ------------------------------------------------------------

@njit(**_INL)
def alpha_model_point(y, k, a, b):
    """Model alpha ``100 a e^{bY} / k`` (percent, eq. 4 with the model's k), log domain."""
    return 100.0 * exp(log(a) + b * y - log(k))


@njit(**_INL)
def alpha_paper_point(y, t, a, b, d):
    """Paper alpha ``100 a e^{bY} / ((Y - d) / t)`` (percent); inf where the signal or t is
    not positive (no light rate can be estimated).

    One exponential and one division (the log-domain form took two logs more on the pixel's
    chain of dependent operations): ``e^{bY}`` as the square of ``E = e^{bY / 2}``, applied
    as ``((100 a t / s) E) E`` so that no factor overflows before the result does (``E`` is
    finite for ``bY`` up to 1418).
    """
    s = y - d
    e = exp(0.5 * b * y)
    alpha = ((100.0 * a * t / s) * e) * e
    return alpha if (s > 0.0 and t > 0.0) else np.inf


def _alpha_model_loop(y, k, a, b, out):
    """:func:`alpha_model_point` over flat operands into ``out``."""
    for i in prange(out.shape[0]):
        out[i] = alpha_model_point(at(y, i), at(k, i), at(a, i), at(b, i))


alpha_model_kernel = Kernel(_alpha_model_loop, 4)


def _alpha_paper_loop(y, t, a, b, d, out):
    """:func:`alpha_paper_point` over flat operands into ``out`` (float32 or float64)."""
    for i in prange(out.shape[0]):
        out[i] = alpha_paper_point(at(y, i), at(t, i), at(a, i), at(b, i), at(d, i))


alpha_paper_kernel = Kernel(_alpha_paper_loop, 5)


# -- validity flags ---------------------------------------------------------------------------

@njit(**_INL)
def leakage_bits(alpha, y, threshold, full_scale):
    """DQ bits of one response from its alpha: LEAKAGE where alpha is over the threshold or
    not a number, SATURATED where the response is at full scale."""
    bits = _LEAKAGE if not (alpha <= threshold) else 0
    return bits | (_SATURATED if y >= full_scale else 0)


def _alpha_flags_loop(y, t, a, b, d, threshold, full_scale, const_bits, pix, has_pix, dq_in,
                      has_dq_in, with_alpha, alpha_in, alpha_out, dq_out):
    """Paper alpha into ``alpha_out`` (if ``with_alpha``; else alpha is read from
    ``alpha_in``) and the DQ of every pixel: :func:`leakage_bits` | ``const_bits`` | ``pix``
    | ``dq_in``."""
    for i in prange(dq_out.shape[0]):
        yi = at(y, i)
        alpha = alpha_paper_point(yi, at(t, i), at(a, i), at(b, i), at(d, i))
        if with_alpha:
            alpha_out[i] = alpha
        else:
            alpha = np.float64(alpha_in[i])
        bits = leakage_bits(alpha, yi, threshold, full_scale) | const_bits
        bits |= pix[i] if has_pix else 0
        bits |= dq_in[i] if has_dq_in else 0
        dq_out[i] = bits


alpha_flags_kernel = Kernel(_alpha_flags_loop, 15)
