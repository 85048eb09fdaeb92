"""Compiled inversion of the leakage model: the light rate k that explains a response Y.

Scaled by e^{bY} at the target Y, the model reads H(x) = e^{beta - x} + C phi(x) - 1 = 0 with
beta = b (Y - d), C = a b t e^{bY}, x = b k t. H is convex and decreasing in x (phi is
completely monotone), and H(x) = e^{b (Y - Y(x))} - 1, so |H| <= b tol means |Y(x) - Y| <=
tol (to first order). Y <= d + k t gives x >= beta; above the dark level Y <= ln(k/a)/b
gives x >= C: from x0 = max(beta, C) Newton climbs monotonically to the root, Halley's
correction makes it cubic.

The kernels work per block of :data:`~hsiffc.kernels.leakage.BLOCK` pixels. A branch-free
round of two Halley steps and a check of H at the result (vectorised by LLVM) settles most
pixels: in the linear regime the start is within a step of the root. Where a block has
pixels left, up to two more rounds of one step and a check continue them, packed together
with the values they carry (no second setup), still vectorised. Pixels still
unsettled, and those the vector form cannot take (non-finite input, zero light, extreme
parameters), get the bracketed scalar iteration :func:`invert_point`. Everything in float64;
the result converges to ``tol_dn + 8 eps |y|`` in DN (tests: against bisection and the
former numpy results).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.extending import overload

from ..data.dq import DQ
from .launch import JIT_OPTIONS, Kernel
from .leakage import BLOCK
from .operands import at, part
from .vmath import exp, exp_expm1, log

__all__ = ["PENDING", "ROUNDS", "STATE_ROWS", "VECTOR_STEPS", "carried", "first_finish",
           "first_setup", "invert_again", "invert_kernel", "invert_point", "invert_rounds",
           "keep"]

# per-point functions are compiled into each kernel that uses them (see leakage.py)
_JIT = {**JIT_OPTIONS, "cache": False}
_INL = {**_JIT, "inline": "always"}
_EPS = 2.220446049250313e-16
_BIG = 1.7976931348623157e308
_E700 = math.exp(700.0)
_NONFINITE = int(DQ.NONFINITE)
_SATURATED = int(DQ.SATURATED)
_BELOW_DARK = int(DQ.BELOW_DARK)
_UNREACHABLE = int(DQ.UNREACHABLE)
_NOT_CONVERGED = int(DQ.NOT_CONVERGED)


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
    """Flags known before iterating, target Y, beta, whether ``ln C <= 700``, C, e^beta, H(0)
    and the start x.

    ``C = a b t e^{bY}``: the vector form multiplies (one exponential); where ``a b t`` is
    not a normal number, or beta or bY exceeds 700 (an exponential would overflow), it
    leaves the pixel to the scalar form (``ok`` False), which sums the logs one by one.
    """
    flags = 0
    finite = (abs(y) < np.inf) and (abs(a) < np.inf) and (abs(b) < np.inf) and (abs(d) < np.inf)
    sat = finite and y >= full_scale
    target = full_scale if sat else y
    flags = (_SATURATED if sat else 0) | (0 if finite else _NONFINITE)
    beta = b * (target - d)
    abt = a * b * t
    ok = finite and abt >= 1e-300 and abt < 1e300
    if vec:
        by = b * target
        c = abt * exp(min(by, 700.0))
        c_ok = by <= 700.0 and c <= _E700
    else:
        lnc = _log(a, vec) + _log(b, vec) + _log(t, vec) + b * target
        c = _exp(min(lnc, 700.0), vec)
        c_ok = lnc <= 700.0
    eb = _exp(min(beta, 700.0), vec)
    h0 = eb + c - 1.0  # H at zero light
    x0 = max(beta, c) if target > d else 0.0
    return flags, ok and beta <= 700.0, target, beta, c_ok, c, eb, h0, x0


@njit(**_JIT)
def invert_point(y, t, a, b, d, full_scale, k_max, tol_dn, max_iter):
    """Light rate k (DN/ms), DQ flags and iterations for one pixel (scalar code).

    Semantics as :func:`hsiffc.leakage.model.invert_response`; a bracketed Halley iteration.
    """
    flags, _, target, beta, c_ok, c, eb, h0, x0 = _setup(y, t, a, b, d, full_scale, False)
    if flags & _NONFINITE:
        return 0.0, flags, 0
    if h0 <= 0.0:  # at or below what zero light gives
        if h0 < 0.0:
            flags |= _BELOW_DARK
        return 0.0, flags | (_UNREACHABLE if k_max < 0.0 else 0), 0
    if not c_ok:  # needs more light than a double can hold
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


VECTOR_STEPS = 2  # Halley steps of the first vectorised round; later rounds take one each
ROUNDS = 3  # vectorised rounds per block before the scalar iteration takes what is left
PENDING = 1 << 31  # scratch flag inside the kernels: left to the scalar iteration
#: values a pixel carries from one round to the next (x, beta, e^beta, C, tolerance, b t,
#: flags)
STATE_ROWS = 7


@njit(**_INL)
def _rate(x, c, bt, k_max, flags):
    """(k, flags, alpha) at ``x`` (``bt = b t``): alpha is the model leakage percentage at
    the target response, ``100 a e^{bY} / k = 100 C / x``."""
    k = x / bt
    over = k > k_max
    return (k_max if over else k), flags | (_UNREACHABLE if over else 0), 100.0 * c / x


@njit(**_INL)
def _residual(x, beta, eb, c):
    """H(x) alone, vector form: what :func:`_halley` computes first (the derivative terms it
    does not use are compiled away)."""
    ex, phi, _, _ = _phi_derivs(x, True)
    return eb * ex + c * phi - 1.0


@njit(**_INL)
def first_setup(y, t, a, b, d, full_scale, tol_dn):
    """The first round's start for one pixel, branch-free (vectorisable): (x0, beta,
    e^beta, C, the tolerance, the flags of the setup, ``solvable``). ``solvable`` is False
    where the vector form cannot take the pixel (solve it with :func:`invert_point`)."""
    flags, ok, target, beta, c_ok, c, eb, h0, x0 = _setup(y, t, a, b, d, full_scale, True)
    tol = b * (tol_dn + 8.0 * _EPS * abs(target))
    return x0, beta, eb, c, tol, flags, ok and c_ok and h0 > 0.0


@njit(**_INL)
def first_finish(x, beta, eb, c, tol, bt, flags, solvable, k_max):
    """The first round's end for one pixel, after its first Halley step from
    :func:`first_setup`'s x0 (vectorisable): the second step and H at its result: (k,
    flags, done, alpha, retry, x). ``done`` where H is within the tolerance; ``retry`` where
    the pixel is solvable but not there yet: :func:`invert_again` continues from the carried
    values (store them with :func:`keep`). Neither: solve with :func:`invert_point`."""
    x = _halley(x, beta, eb, c, True)[1]
    near = abs(_residual(x, beta, eb, c)) <= tol
    k, fl, alpha = _rate(x, c, bt, k_max, flags)
    return k, fl, solvable and near, alpha, solvable and not near, x


@njit(**_INL)
def invert_again(x, beta, eb, c, tol, bt, flags, k_max):
    """The next round for a pixel a round left with ``retry``, from the values it carries
    (vectorisable): one Halley step and H at its result: (k, flags, done, alpha, x)."""
    x = _halley(x, beta, eb, c, True)[1]
    k, fl, alpha = _rate(x, c, bt, k_max, flags)
    return k, fl, abs(_residual(x, beta, eb, c)) <= tol, alpha, x


def keep(state, j, x, beta, eb, c, tol, bt, flags):
    """Store pixel ``j``'s carried values in ``state`` (flat, :data:`STATE_ROWS` per pixel,
    interleaved); ``x`` -1 says there is nothing to continue. Compiled code inlines it at
    numba's IR level (an overload, like ``at``): an array handed to an inlined *function* is
    reference-counted in the loop, which stops LLVM from vectorising it."""
    s = STATE_ROWS * j
    state[s] = x
    state[s + 1] = beta
    state[s + 2] = eb
    state[s + 3] = c
    state[s + 4] = tol
    state[s + 5] = bt
    state[s + 6] = flags


def carried(state, j):
    """Pixel ``j``'s carry as :func:`keep` stored it (``x`` -1: nothing to continue)."""
    s = STATE_ROWS * j
    return (state[s], state[s + 1], state[s + 2], state[s + 3], state[s + 4], state[s + 5],
            np.int64(state[s + 6]))


@overload(keep, inline="always")
def _keep_overload(state, j, x, beta, eb, c, tol, bt, flags):
    return keep


@overload(carried, inline="always")
def _carried_overload(state, j):
    return carried


@njit(**_JIT)
def invert_rounds(y, t, a, b, d, full_scale, k_max, tol_dn, rounds, k_out, flags_out,
                  alpha_out):
    """The vectorised rounds (see the module) for one block, operands as
    :func:`~.operands.part` gives them: k, flags (:data:`PENDING` where left to
    :func:`invert_point`) and model alpha per pixel. Returns the Halley steps taken.

    The pixels the first round leaves are packed (their carried values side by side), so
    that the later rounds compute only them, still vectorised, and their results are put
    back at the end."""
    m = k_out.shape[0]
    if rounds <= 0:
        return 0
    state = np.empty(STATE_ROWS * m)
    # The first round as three loops (set-up, first step, second step and check) through
    # block-sized buffers: in one loop its vector code has more values live than AVX2 has
    # registers and spills them (the split gives the same bits).
    xs = np.empty(m)
    betas = np.empty(m)
    ebs = np.empty(m)
    cs = np.empty(m)
    tols = np.empty(m)
    f0s = np.empty(m, np.int64)
    solvable = np.empty(m, np.bool_)
    for j in range(m):
        xs[j], betas[j], ebs[j], cs[j], tols[j], f0s[j], solvable[j] = first_setup(
            at(y, j), at(t, j), at(a, j), at(b, j), at(d, j), full_scale, tol_dn)
    for j in range(m):
        xs[j] = _halley(xs[j], betas[j], ebs[j], cs[j], True)[1]
    again = 0
    go_on_ok = rounds > 1
    for j in range(m):
        beta, eb, c, tol, f0 = betas[j], ebs[j], cs[j], tols[j], f0s[j]
        bt = at(b, j) * at(t, j)
        k, f, done, alpha, retry, x = first_finish(xs[j], beta, eb, c, tol, bt, f0,
                                                   solvable[j], k_max)
        go_on = retry and go_on_ok
        keep(state, j, x if go_on else -1.0, beta, eb, c, tol, bt, f0)
        k_out[j] = k
        alpha_out[j] = alpha
        flags_out[j] = f | (0 if done or go_on else PENDING)
        again += 1 if go_on else 0
    if again == 0:
        return VECTOR_STEPS
    todo = np.empty(again, np.int64)  # pack the pixels left
    packed = np.empty(STATE_ROWS * again)
    n = 0
    for j in range(m):
        if state[STATE_ROWS * j] >= 0.0:
            todo[n] = j
            for r in range(STATE_ROWS):
                packed[STATE_ROWS * n + r] = state[STATE_ROWS * j + r]
            n += 1
    k2 = np.empty(n)
    alpha2 = np.empty(n)
    f2 = np.empty(n, np.int64)
    steps = VECTOR_STEPS
    for r in range(1, rounds):
        if again == 0:
            break
        steps += 1
        go_further = r + 1 < rounds
        again = 0
        for q in range(n):  # every packed pixel computed, kept where it is continued
            x, beta, eb, c, tol, bt, f0 = carried(packed, q)
            redo = x >= 0.0
            k, f, done, alpha, x = invert_again(x, beta, eb, c, tol, bt, f0, k_max)
            go_on = redo and not done and go_further
            keep(packed, q, x if go_on else -1.0, beta, eb, c, tol, bt, f0)
            k2[q] = k if redo else k2[q]
            alpha2[q] = alpha if redo else alpha2[q]
            f_new = f | (0 if done or go_on else PENDING)
            f2[q] = f_new if redo else f2[q]
            again += 1 if go_on else 0
    for q in range(n):
        k_out[todo[q]] = k2[q]
        alpha_out[todo[q]] = alpha2[q]
        flags_out[todo[q]] = f2[q]
    return steps


@njit(**_JIT)
def _invert_block(y, t, a, b, d, full_scale, k_max, tol_dn, max_iter, k_out, flags_out):
    """:func:`invert_point` for one block: :func:`invert_rounds`, then the scalar iteration
    for what they leave. Returns the most iterations a pixel took."""
    m = k_out.shape[0]
    rounds = min(ROUNDS, max_iter - VECTOR_STEPS + 1) if max_iter >= VECTOR_STEPS else 0
    most = invert_rounds(y, t, a, b, d, full_scale, k_max, tol_dn, rounds, k_out, flags_out,
                         np.empty(m))
    for j in range(m):
        if rounds > 0 and not (flags_out[j] & PENDING):
            continue
        k, f, it = invert_point(at(y, j), at(t, j), at(a, j), at(b, j), at(d, j), full_scale,
                                k_max, tol_dn, max_iter)
        k_out[j] = k
        flags_out[j] = f
        most = max(most, it)
    return most


def _invert_loop(y, t, a, b, d, full_scale, k_max, tol_dn, max_iter, k_out, flags_out,
                 iterations):
    """:func:`invert_point` over flat operands, per block of :data:`BLOCK` pixels;
    ``iterations[block]`` gets each block's max (``ceil(n / BLOCK)`` entries)."""
    n = k_out.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        iterations[blk] = _invert_block(
            part(y, i0, i1), part(t, i0, i1), part(a, i0, i1), part(b, i0, i1),
            part(d, i0, i1), full_scale, k_max, tol_dn, max_iter, k_out[i0:i1],
            flags_out[i0:i1])


invert_kernel = Kernel(_invert_loop, 9)
