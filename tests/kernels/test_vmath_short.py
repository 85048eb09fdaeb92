"""The short, range-restricted elementary functions of hsiffc.kernels.vmath (exp_clamped,
expm1_clamped, log_positive) and the closed-form response built on them, against 50-digit
decimal arithmetic (the standard library's decimal module): their polynomials' errors,
the functions' ulp bounds, and the response over the model's parameter ranges with extremes."""

from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np
import pytest
from numba import njit

from hsiffc.leakage import model
from hsiffc.kernels import vmath

D = Decimal


def _poly(coefficients, x):
    """The polynomial with these (double) coefficients, low to high, evaluated exactly."""
    p = D(0)
    for c in reversed(coefficients):
        p = p * x + D(c)
    return p


def test_exp_polynomial_error_is_below_a_tenth_of_an_ulp():
    # 1 + r + r^2 p(r) against e^r on the reduced range, with a margin for the rounding of n
    # and r: the bounds the comment on vmath._P states
    with localcontext() as ctx:
        ctx.prec = 50
        h = D(2).ln() / 2 * D("1.0001")
        worst_exp = worst_expm1 = D(0)
        for i in range(-2000, 2001):
            if i == 0:
                continue
            r = h * i / 2000
            em = r + r * r * _poly(vmath._P, r)
            exact = r.exp()
            worst_exp = max(worst_exp, abs((1 + em) / exact - 1))
            worst_expm1 = max(worst_expm1, abs(em / (exact - 1) - 1))
    assert worst_exp < D("1.0e-17")
    assert worst_expm1 < D("2.5e-17")


def test_log_polynomial_error_is_fdlibms_bound():
    # R(z) = z (Lg1 + ... + Lg7 z^6) against 2 atanh(s) / s - 2 on |s| <= 0.1716 (R is even
    # in s): below 2^-58.45, the bound fdlibm's e_log.c states for these coefficients
    with localcontext() as ctx:
        ctx.prec = 50
        worst = D(0)
        for i in range(1, 2001):
            s = D("0.1716") * i / 2000
            exact = ((1 + s) / (1 - s)).ln() / s - 2
            z = s * s
            worst = max(worst, abs(z * _poly(vmath._LG, z) - exact))
    assert worst < D(2) ** D("-58.45")


@njit(error_model="numpy")
def _log1p_by_log_positive(q, out):
    # as the response calls it: log(w + c) for w = 1 + q and c the rounding error of the sum
    for i in range(q.shape[0]):
        w = 1.0 + q[i]
        out[i] = vmath.log_positive(w, q[i] - (w - 1.0))


@njit(error_model="numpy")
def _plain_log_positive(x, out):
    for i in range(x.shape[0]):
        out[i] = vmath.log_positive(x[i], 0.0)


def _ulps(out, expect):
    return np.abs(out - expect) / np.spacing(np.abs(expect))


def test_clamped_exponentials_within_their_ulp_bounds(elementwise):
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-708.0, 708.0, 200_000), rng.uniform(-0.4, 0.4, 20_000),
                        -(10.0 ** rng.uniform(-300, 2.85, 50_000))])
    out = np.empty_like(x)
    elementwise(vmath.exp_clamped)(x, out)
    assert _ulps(out, np.exp(x)).max() <= 1
    elementwise(vmath.expm1_clamped)(x, out)
    nonzero = np.expm1(x) != 0
    assert _ulps(out[nonzero], np.expm1(x)[nonzero]).max() <= 2
    assert np.array_equal(out[~nonzero], x[~nonzero])  # expm1(0) = 0


def test_clamped_exponentials_clamp_and_pass_nan(elementwise):
    x = np.array([-1e4, -745.5, 800.0, 1e300, np.inf, -np.inf, np.nan])
    out = np.empty_like(x)
    bounds = np.empty(2)
    elementwise(vmath.exp_clamped)(np.array([-708.0, 708.0]), bounds)
    elementwise(vmath.exp_clamped)(x, out)
    lo, hi = bounds
    np.testing.assert_array_equal(out, [lo, lo, hi, hi, hi, lo, np.nan])
    elementwise(vmath.expm1_clamped)(x, out)
    np.testing.assert_array_equal(out[[0, 1, 5, 6]], [-1.0, -1.0, -1.0, np.nan])


def test_log_positive_within_one_ulp():
    rng = np.random.default_rng(1)
    x = np.concatenate([10.0 ** rng.uniform(-307.5, 308.0, 200_000),
                        rng.uniform(0.5, 2.0, 50_000), [1.0, 2.0, np.sqrt(0.5), np.sqrt(2.0)]])
    out = np.empty_like(x)
    _plain_log_positive(x, out)
    one = x == 1.0
    assert _ulps(out[~one], np.log(x[~one])).max() <= 1
    assert np.all(out[one] == 0.0)
    q = np.concatenate([rng.uniform(0.0, 1.0, 100_000), 10.0 ** rng.uniform(-300, 0, 100_000)])
    _log1p_by_log_positive(q, out := np.empty_like(q))
    assert _ulps(out, np.log1p(q)).max() <= 1


def _reference_response(t, k, a, b, d):
    """Y = -ln(e^{-bd-x} + a b t (1 - e^{-x}) / x) / b (x = b k t) in 50-digit decimals."""
    with localcontext() as ctx:
        ctx.prec = 50
        t, k, a, b, d = (D(float(v)) for v in (t, k, a, b, d))
        x = b * k * t
        phi = (1 - (-x).exp()) / x if x != 0 else D(1)
        y = -((-b * d - x).exp() + a * b * t * phi).ln() / b
        return float(y), float(d + k * t), float(y - (d + k * t))


def test_response_against_50_digit_arithmetic_over_the_parameter_ranges():
    # wide ranges: b k t from 0 to beyond 1e4, a / k from 0 to 1e30, dark levels above the
    # dynamic saturation level (d = 1.5 ln(k / a) / b for every 7th pixel)
    rng = np.random.default_rng(3)
    n = 4000
    t = 10.0 ** rng.uniform(-3, 5, n)
    k = 10.0 ** rng.uniform(-6, 3, n)
    k[::17] = 0.0
    a = 10.0 ** rng.uniform(-30, 1, n)
    a[::19] = 0.0
    b = 10.0 ** rng.uniform(-4, 0, n)
    d = rng.uniform(-50, 500, n)
    saturation = np.log(np.maximum(k, 1e-300) / np.maximum(a, 1e-300)) / b
    d[::7] = np.clip(1.5 * saturation[::7], -1e4, 1e6)
    ref = np.array([_reference_response(*v) for v in zip(t, k, a, b, d)])
    y = model.response(t, k, a, b, d)
    # the float64 forms round d + k t and the leakage term log1p(q) / b: error in ulps of the
    # largest of |Y|, |d + k t| and their difference (measured: at most 5, as the form this
    # one replaced; 99 % within 1)
    scale = np.abs(ref).max(axis=1)
    ulps = np.abs(y - ref[:, 0]) / np.spacing(scale)
    assert ulps.max() <= 8
    assert np.percentile(ulps, 99) <= 1


@pytest.mark.parametrize("t,k,a,b,d", [
    (25.0, 30.0, 9e-5, 0.0125, 32.0),  # the benchmark frame's typical pixel
    (1e-3, 1e-6, 1e-30, 1e-4, 0.0),  # b k t tiny, a / k tiny
    (1e5, 1e3, 10.0, 1.0, 500.0),  # b k t huge: deep saturation
    (2000.0, 50.0, 1e-12, 0.05, 5e3),  # far above saturation (e^{-bd-x} clamped)
    (10.0, 0.0, 1e-3, 0.01, 50.0),  # k = 0: pure leakage
    (10.0, 2.0, 0.0, 0.01, 50.0),  # a = 0: linear
])
def test_response_extremes_against_50_digit_arithmetic(t, k, a, b, d):
    y = float(model.response(t, k, a, b, d))
    ref, base, leak = _reference_response(t, k, a, b, d)
    assert abs(y - ref) <= 4 * np.spacing(max(abs(ref), abs(base), abs(leak)))
