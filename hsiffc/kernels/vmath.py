"""Elementary functions in double precision that LLVM can vectorise inside numba loops.

numba lowers ``math.exp`` and friends to scalar libm calls, which keep a per-pixel loop from
being vectorised (a scalar libm call is several times slower than numpy's SIMD ufuncs). These
versions are straight-line arithmetic (range reduction, a polynomial, an exponent bit
trick), with selects instead of branches, so a loop that calls them runs 8 pixels per
instruction (4 on AVX2). Accuracy (measured against numpy over the whole double range in
``tests/kernels/test_kernels.py``): ``exp``, ``log`` and ``log1p`` within 1 ulp, ``expm1``
within 2 ulp.
Special values follow IEEE 754 (``exp(-inf) = 0``, ``log(0) = -inf``, ``log(-1) = nan``, NaN
in gives NaN out).

Polynomials are evaluated by Estrin's scheme with fused multiply-adds (:func:`fma`, LLVM's
``llvm.fma``: one rounding per step, so the result is the same on every machine, and on one
with FMA units, e.g. any AVX2 x86, a step is one instruction instead of two). ``exp`` uses the Taylor series of
e^r to degree 13 on ``|r| <= ln 2 / 2`` (truncation below 2e-17 relative); ``log`` the
series of ``2 atanh(s)`` in ``s = f / (2 + f)`` on ``sqrt(1/2) <= 1 + f < sqrt(2)``
(``|s| < 0.1716``, truncation below 1e-18).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

__all__ = ["as_float64", "as_int64", "exp", "exp_clamped", "exp_expm1", "expm1", "expm1_clamped",
           "fma", "log", "log1p", "log_corrected", "log_positive", "logaddexp"]

# Not cached on purpose: a cached function is stored as machine code, which LLVM cannot inline
# into (and vectorise with) a caller compiled later. The kernels that call these are cached.
_JIT = {"cache": False, "fastmath": False, "error_model": "numpy"}
_INL = {**_JIT, "inline": "always"}


@intrinsic
def as_int64(typingctx, x):
    """Bits of a float64 as an int64 (no conversion)."""
    if x != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def as_float64(typingctx, x):
    """An int64 bit pattern read as a float64 (no conversion)."""
    if x != types.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@intrinsic
def fma(typingctx, x, y, z):
    """``x * y + z`` with one rounding (IEEE 754 fusedMultiplyAdd) for float64 operands."""
    if not (x == y == z == types.float64):
        return None

    def codegen(context, builder, signature, args):
        dbl = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [dbl],
                                              ir.FunctionType(dbl, [dbl, dbl, dbl]))
        return builder.call(fn, args)

    return types.float64(types.float64, types.float64, types.float64), codegen


_INV_LN2 = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 split so that n * _LN2_HI is exact for |n| < 2^11
_LN2_LO = 1.90821492927058770002e-10
_SHIFT = 6755399441055744.0  # 1.5 * 2^52: adding it rounds to an integer
_SHIFT_BITS = 0x4338000000000000  # the bits of _SHIFT; (bits of n + _SHIFT) - these = n
_F = [1.0 / math.factorial(i) for i in range(14)]
_E2, _E3, _E4, _E5, _E6, _E7, _E8, _E9, _E10, _E11, _E12, _E13 = _F[2:]
_SQRT2 = 1.4142135623730951
_TINY = 2.2250738585072014e-308  # smallest normal double
_L = [2.0 / (2 * i + 1) for i in range(1, 11)]  # 2 atanh(s) = 2 s + s * sum_i 2 s^2i / (2i + 1)
_L1, _L2, _L3, _L4, _L5, _L6, _L7, _L8, _L9, _L10 = _L


@njit(**_INL)
def _exp_poly(r):
    """e^r - 1 - r for |r| <= 0.35 (Taylor, degree 13), as r^2 * q(r); q by Estrin's scheme
    (pairs, then powers r^2, r^4, r^8: 4 dependent steps instead of Horner's 11, which in these
    long kernels is what bounds the speed: a latency chain, not the instruction count)."""
    r2 = r * r
    q0 = fma(fma(_E5, r, _E4), r2, fma(_E3, r, _E2))
    q1 = fma(fma(_E9, r, _E8), r2, fma(_E7, r, _E6))
    q2 = fma(fma(_E13, r, _E12), r2, fma(_E11, r, _E10))
    r4 = r2 * r2
    q = fma(q2, r4 * r4, fma(q1, r4, q0))
    return r2 * q


@njit(**_INL)
def _reduced(x):
    """(w, s1, s2) with ``e^x = (1 + w) s1 s2``: ``x = n ln 2 + r``, ``w = e^r - 1`` by the
    polynomial, ``2^n = s1 s2`` as two factors (2^n alone may be subnormal or overflow)."""
    xc = min(max(x, -1100.0), 1100.0)
    shifted = xc * _INV_LN2 + _SHIFT
    n = shifted - _SHIFT
    r = (xc - n * _LN2_HI) - n * _LN2_LO
    w = r + _exp_poly(r)
    # n as an integer from the low bits of the shifted sum (a vector integer subtraction;
    # a float-to-int64 conversion has no AVX2 instruction and runs lane by lane)
    ni = as_int64(shifted) - _SHIFT_BITS
    h = ni >> 1
    return w, as_float64((h + 1023) << 52), as_float64((ni - h + 1023) << 52)


@njit(**_INL)
def exp_expm1(x):
    """``(e^x, e^x - 1)`` from one range reduction and one polynomial (1 and 2 ulp): for code
    that needs both, e.g. ``e^{-x}`` and ``1 - e^{-x}``.

    ``e^x - 1 = (2^n - 1) + 2^n w``, ``2^n - 1`` exact for n >= -53 (below, it rounds to -1,
    the right answer). For ``|x| < ln 2 / 2``, n = 0 and r = x, so the same expression is
    ``w`` itself: one polynomial serves every x. Above 40 the -1 is below the last bit.
    """
    w, s1, s2 = _reduced(x)
    ex = ((1.0 + w) * s1) * s2
    mid = (s1 * s2 - 1.0) + s1 * (s2 * w)
    em = ex if x > 40.0 else mid
    nan = x != x
    return (x if nan else ex), (x if nan else em)


@njit(**_JIT)
def exp(x):
    """e^x for a float64 (1 ulp)."""
    return exp_expm1(x)[0]


@njit(**_JIT, inline="always")
def expm1(x):
    """e^x - 1, accurate for small |x| (2 ulp)."""
    return exp_expm1(x)[1]


@njit(**_JIT)
def log_corrected(x, c):
    """``log(x + c)`` for a correction ``c`` of at most a few ulp of ``x`` (0 for a plain log):
    the rounding error of the sum that gave ``x``, folded into the mantissa before the
    polynomial, so that ``log1p`` costs one division like ``log``. 1 ulp; ``-inf`` at 0, NaN
    below 0 (``c`` is ignored for non-finite, zero and negative ``x``)."""
    sub = x < _TINY
    xs = x * 18014398509481984.0 if sub else x  # 2^54 lifts subnormals
    ix = as_int64(xs)
    e = ((ix >> 52) & 0x7FF) - 1023 - (54 if sub else 0)
    m = as_float64((ix & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)
    big = m > _SQRT2
    m = m * 0.5 if big else m
    ie = e + (1 if big else 0)
    ef = np.float64(ie)
    # c / 2^ie, with the scale kept finite (c is 0 wherever ie is out of this range)
    f = (m - 1.0) + c * as_float64((1023 - min(max(ie, -1000), 1000)) << 52)
    s = f / (2.0 + f)
    z = s * s
    z2 = z * z  # Estrin's scheme, as in _exp_poly
    q0 = fma(fma(_L4, z, _L3), z2, fma(_L2, z, _L1))
    q1 = fma(fma(_L8, z, _L7), z2, fma(_L6, z, _L5))
    z4 = z2 * z2
    rr = fma(fma(_L10, z, _L9), z4 * z4, fma(q1, z4, q0)) * z
    hfsq = 0.5 * f * f
    res = ef * _LN2_HI + (f - (hfsq - (s * (hfsq + rr) + ef * _LN2_LO)))
    res = res if x < np.inf else x
    res = res if x > 0.0 else (-np.inf if x == 0.0 else np.nan)
    return res if x == x else x


@njit(**_JIT)
def log(x):
    """Natural log of a float64 (1 ulp); -inf at 0, NaN below 0."""
    return log_corrected(x, 0.0)


@njit(**_JIT)
def log1p(x):
    """log(1 + x), accurate for small |x| (1 ulp)."""
    u = 1.0 + x
    # the rounding error of 1 + x, exact while u < 2^53 (beyond it, below the last bit)
    c = x - (u - 1.0) if (u > 0.0 and u < 9007199254740992.0) else 0.0
    res = log_corrected(u, c)
    return x if u == 1.0 else res


@njit(**_JIT)
def logaddexp(u, v):
    """log(e^u + e^v) without overflow (-inf when both are -inf)."""
    hi = max(u, v)
    lo = min(u, v)
    res = hi + log1p(exp(lo - hi))
    return hi if (lo == -np.inf or hi == np.inf) else res


# -- shorter forms for arguments known to be in range -----------------------------------------
# The closed-form response (hsiffc.kernels.leakage) calls two exponentials and a logarithm per
# pixel and screens every result it keeps (a sum within [1e-290, 1e290], else its log-domain
# repair), so it needs neither the special values nor the subnormal range handled above. These
# forms drop them and use shorter polynomials, for the same accuracy class (errors of the
# approximations below 0.1 ulp, checked by tests/kernels/test_vmath_short.py against 50-digit
# decimal
# arithmetic on a grid of 4000 points; the functions within 1 ulp, expm1 2, against numpy):
# the response's chain of dependent operations is shorter with them.

# e^r ~ 1 + r + r^2 p(r) on |r| <= 1.0001 ln 2 / 2, p of degree 9: a fit of p to
# (e^r - 1 - r) / r^2 weighted by r^2 e^-r (one Remez step from 11 Chebyshev points, mpmath at
# 50 digits), coefficients rounded to double. Relative error with these doubles: 9.9e-18 for
# e^r, 2.4e-17 for e^r - 1 (the degree-13 Taylor form above: 4e-18).
_P = [0.5000000000000006, 0.1666666666666667, 0.041666666666573066, 0.008333333333326136,
      0.001388888893251478, 0.00019841269874820627, 2.480150431378554e-05,
      2.7557255400206422e-06, 2.7626371065696354e-07, 2.5105217004720745e-08]
_P0, _P1, _P2, _P3, _P4, _P5, _P6, _P7, _P8, _P9 = _P
# 2 atanh(s) = 2 s + s R(s^2), R(z) = z (Lg1 + Lg2 z + ... + Lg7 z^6): fdlibm's e_log.c
# (|R - exact| < 2^-58.45 on |s| < 0.1716), in place of the 10-term series above
_LG = [6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01,
       2.222219843214978396e-01, 1.818357216161805012e-01, 1.531383769920937332e-01,
       1.479819860511658591e-01]
_LG1, _LG2, _LG3, _LG4, _LG5, _LG6, _LG7 = _LG
_EXP_CLAMP = 708.0  # e^x and 2^n (n = round(x / ln 2), |n| <= 1021) stay normal doubles
_HALF_SQRT2_UP = 0x3FE6A09E667F3BCE  # bits of sqrt(1/2) (as rounded in _SQRT2 / 2) plus one


@njit(**_INL)
def _reduced_clamped(x):
    """(w, s) with ``e^x = (1 + w) s`` for x clamped to [-708, 708] (NaN: anything): ``x = n
    ln 2 + r`` (fused multiply-adds), ``w = e^r - 1`` by the degree-11 polynomial, ``s = 2^n``
    one normal double."""
    xc = min(max(x, -_EXP_CLAMP), _EXP_CLAMP)
    shifted = fma(xc, _INV_LN2, _SHIFT)
    n = shifted - _SHIFT
    r = fma(-n, _LN2_LO, fma(-n, _LN2_HI, xc))
    r2 = r * r
    r4 = r2 * r2
    p0 = fma(fma(_P3, r, _P2), r2, fma(_P1, r, _P0))
    p1 = fma(fma(_P7, r, _P6), r2, fma(_P5, r, _P4))
    p = fma(fma(fma(_P9, r, _P8), r4, p1), r4, p0)
    w = fma(r2, p, r)
    return w, as_float64((as_int64(shifted) - _SHIFT_BITS + 1023) << 52)


@njit(**_INL)
def exp_clamped(x):
    """e^x for ``|x| <= 708`` (1 ulp); ``e^{+-708}`` beyond, NaN for NaN. For code that
    screens its results (e^{-708} is 3.3e-308: added to a term of 1e-290 or more it is below
    the last bit, so a sum kept only from 1e-290 up is exactly what e^x would give)."""
    w, s = _reduced_clamped(x)
    e = fma(s, w, s)
    return e if x == x else x


@njit(**_INL)
def expm1_clamped(x):
    """e^x - 1 for ``x <= 708`` (2 ulp; -1 below -37.5, as e^x - 1 rounds there); ``e^708 -
    1`` beyond, NaN for NaN."""
    w, s = _reduced_clamped(x)
    e = fma(s, w, s - 1.0)
    return e if x == x else x


@njit(**_INL)
def log_positive(x, c):
    """``log(x + c)`` (1 ulp) as :func:`log_corrected`, for a positive normal finite ``x`` only
    (anything else gives a meaningless number, not inf or NaN: the caller screens ``x``).
    The exponent and mantissa by integer arithmetic alone (no selects), fdlibm's 7-term
    polynomial."""
    ix = as_int64(x)
    ie = (ix - _HALF_SQRT2_UP) >> 52  # m = x / 2^ie in (sqrt(1/2), sqrt(2)]
    m = as_float64(ix - (ie << 52))
    ef = as_float64(ie + _SHIFT_BITS) - _SHIFT  # ie as a double (no int64 conversion on AVX2)
    f = fma(c, as_float64((1023 - ie) << 52), m - 1.0)  # m - 1 exact; c / 2^ie exact
    s = f / (2.0 + f)
    z = s * s
    z2 = z * z
    q0 = fma(fma(_LG4, z, _LG3), z2, fma(_LG2, z, _LG1))
    q1 = fma(_LG7, z2, fma(_LG6, z, _LG5))
    rr = fma(q1, z2 * z2, q0) * z
    hfsq = 0.5 * f * f
    return ef * _LN2_HI + (f - (hfsq - (s * (hfsq + rr) + ef * _LN2_LO)))
