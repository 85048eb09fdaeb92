"""The compiled kernels behind hsiffc.leakage.model: elementary functions, and the model functions
against the previous numpy formulas (re-derived here), solve_ivp and hypothesis properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.leakage import model
from hsiffc.data.dq import DQ
from hsiffc.kernels import inversion, launch, leakage, vmath


# -- the previous numpy implementation (reference values; not used by the package) ------------

def numpy_response(t, k, a, b, d):
    """The numpy closed form hsiffc used before the kernels: logaddexp of the two log terms."""
    t, k, a, b, d = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (t, k, a, b, d)))
    x = b * k * t
    with np.errstate(divide="ignore", invalid="ignore"):
        lphi = np.where(x < 1e-8, -0.5 * x, np.log(-np.expm1(-x) / x))
        leak = np.log(a) + np.log(b) + np.log(t) + lphi
    return -np.logaddexp(-b * d - x, leak) / b


def numpy_alpha_paper(y, t, a, b, d):
    y, t, a, b, d = (np.asarray(v, np.float64) for v in (y, t, a, b, d))
    s = y - d
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        alpha = 100.0 * np.exp(np.log(a) + b * y - np.log(s / t))
    return np.where((s > 0) & (t > 0), alpha, np.inf)


def bisect_k(y, t, a, b, d, iters=200):
    """k by bisection in ln k on the numpy response (slow, independent of the kernel)."""
    lo = np.full(np.shape(y), -40.0)
    hi = np.full(np.shape(y), 40.0)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        above = numpy_response(t, np.exp(mid), a, b, d) > y
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return np.exp(0.5 * (lo + hi))


# -- elementary functions ---------------------------------------------------------------------

@pytest.mark.parametrize("name,ref,lo,hi,log_scale,max_ulp", [
    ("exp", np.exp, -746.0, 710.0, False, 1),
    ("expm1", np.expm1, -40.0, 40.0, False, 2),
    ("expm1", np.expm1, -300.0, -0.01, True, 2),
    ("log", np.log, -310.0, 308.0, True, 1),
    ("log1p", np.log1p, -300.0, 300.0, True, 1),
])
def test_elementary_functions_within_their_ulp_bound(name, ref, lo, hi, log_scale, max_ulp,
                                                    elementwise):
    rng = np.random.default_rng(0)
    x = rng.uniform(lo, hi, 200_000)
    if log_scale:
        x = 10.0 ** x
    if name == "expm1":
        x = np.concatenate([x, -x, rng.uniform(-0.4, 0.4, 10_000)])
    if name == "log1p":
        x = np.concatenate([x, -rng.uniform(0, 1, 10_000), rng.uniform(-1e-3, 1e-3, 10_000)])
    out = np.empty_like(x)
    elementwise(getattr(vmath, name))(x, out)
    with np.errstate(over="ignore"):
        expect = ref(x)
    fin = np.isfinite(expect) & (expect != 0)
    ulps = np.abs(out[fin] - expect[fin]) / np.spacing(np.abs(expect[fin]))
    assert ulps.max() <= max_ulp
    assert np.array_equal(out[~fin], expect[~fin])


def test_elementary_functions_special_values(elementwise):
    x = np.array([0.0, np.inf, -np.inf, np.nan, -1.0, 5e-324, -800.0, 710.0])
    for name in ("exp", "expm1", "log", "log1p"):
        out = np.empty_like(x)
        elementwise(getattr(vmath, name))(x, out)
        with np.errstate(all="ignore"):
            expect = getattr(np, name)(x)
        assert np.array_equal(out, expect, equal_nan=True), name


def test_paper_alpha_at_the_limits_of_the_exponential():
    """alpha's e^{bY/2} is clamped at 708: beyond, alpha is inf (LEAKAGE), as the exact value
    overflows float32 by far; far below, 0; NaN stays NaN; in between within 1 ulp of numpy."""
    y = np.array([1000.0, 2000.0, 1e6, -1e6, np.nan, 500.0, -1e6])
    b = np.array([1.4, 0.709, 0.01, 0.01, 0.01, 0.01, 0.01])
    dark = np.array([100.0] * 6 + [-2e6])
    b_nan = np.array([np.nan])
    out = model.leakage_percentage_paper(y, 10.0, 1e-3, b, dark)
    assert np.all(out[:3] == np.inf)
    assert out[3] == np.inf and out[4] == np.inf  # signal not positive or NaN: no light rate
    ref = 100 * 1e-3 * 10.0 * np.exp(0.01 * 500.0) / 400.0
    assert abs(out[5] / ref - 1) < 1e-15
    assert out[6] == 0.0  # e^{-5000}: 0 in double, as the exact value is
    assert np.isnan(model.leakage_percentage_paper(500.0, 10.0, 1e-3, b_nan, 100.0))


# -- response ---------------------------------------------------------------------------------

def _frame(n=300_000, seed=1):
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.0, 40.0, n)
    a = 2.0 * np.exp(-8.0) * rng.lognormal(0, 1.0, n)
    b = rng.uniform(0.005, 0.03, n)
    d = rng.uniform(0.0, 100.0, n)
    return k, a, b, d


def test_response_equals_previous_numpy_form_on_a_frame():
    k, a, b, d = _frame()
    for t in (0.0, 0.5, 25.0, 400.0, 1e5):
        y = model.response(t, k, a, b, d)
        ref = numpy_response(t, k, a, b, d)
        assert np.allclose(y, ref, rtol=2e-14, atol=1e-11)


def test_response_parallel_and_serial_builds_agree_exactly():
    k, a, b, d = _frame(n=launch.PARALLEL_MIN + 777)
    out_p, out_s = np.empty(k.size), np.empty(k.size)
    leakage.response_kernel.parallel(25.0, k, a, b, d, out_p)
    leakage.response_kernel.serial(25.0, k, a, b, d, out_s)
    assert np.array_equal(out_p, out_s)


def test_response_kernel_equals_the_per_point_function_bit_for_bit():
    # the kernel runs the fast form's two halves in separate loops; other compiled code calls
    # response_point, which must give the same bits (promised in hsiffc.kernels.leakage)
    k, a, b, d = _frame(n=3000, seed=7)
    extreme = np.array([[0.0, 1e-300, 0.5, 1.5e3], [1e3, 0.0, 0.05, 10.0],
                        [2.0, 1e-3, 1.0, -800.0], [50.0, 1e-12, 0.05, 5e3]])
    k, a, b, d = (np.concatenate([v, extreme[:, i]]) for i, v in enumerate((k, a, b, d)))
    for t in (0.5, 25.0, 2000.0):
        out = np.empty(k.size)
        leakage.response_kernel.serial(t, k, a, b, d, out)
        point = np.array([leakage.response_point(t, *v) for v in zip(k, a, b, d)])
        assert np.array_equal(out, point)


@pytest.mark.parametrize("case,repaired", [
    (dict(t=1e4, k=0.0, a=1e-300, b=0.5, d=1.5e3), True),  # both terms below 1e-290
    (dict(t=1e6, k=1e3, a=0.0, b=0.05, d=10.0), True),  # a = 0 with b k t far beyond 745
    (dict(t=10.0, k=2.0, a=1e-3, b=1.0, d=-800.0), True),  # e^{-b d} overflows
    (dict(t=2000.0, k=50.0, a=1e-12, b=0.05, d=5e3), False),  # far above saturation
])
def test_response_extreme_parameters(case, repaired):
    y = model.response(**{("t_ms" if k == "t" else "dark" if k == "d" else k): v
                          for k, v in case.items()})
    ref = numpy_response(case["t"], case["k"], case["a"], case["b"], case["d"])
    assert np.isfinite(y)
    assert y == pytest.approx(float(ref), rel=1e-12, abs=1e-9)
    fast_ok = leakage.response_fast(float(case["t"]), float(case["k"]), float(case["a"]),
                                    float(case["b"]), float(case["d"]))[1]
    assert fast_ok != repaired  # the first three really exercise the repair pass


def test_float32_inputs_are_read_without_loss():
    k, a, b, d = (v.astype(np.float32) for v in _frame(n=5000))
    y32 = model.response(25.0, k, a, b, d)
    y64 = model.response(25.0, *(v.astype(np.float64) for v in (k, a, b, d)))
    assert y32.dtype == np.float64 and np.array_equal(y32, y64)


def test_broadcasting_matches_numpy_rules():
    t = np.array([1.0, 10.0, 100.0])[:, None, None]
    k = np.linspace(0.1, 5, 12).reshape(3, 4)
    y = model.response(t, k, 1e-3, 0.01, np.arange(4.0))
    assert y.shape == (3, 3, 4)
    assert np.allclose(y, numpy_response(t, k, 1e-3, 0.01, np.arange(4.0)), rtol=1e-14)


@settings(max_examples=60, deadline=None)
@given(t=st.floats(0.0, 1e4), k=st.floats(0.0, 100.0), log_a=st.floats(-60, 5),
       b=st.floats(1e-4, 0.1), d=st.floats(-50, 500))
def test_response_matches_numpy_form_everywhere(t, k, log_a, b, d):
    y = model.response(t, k, np.exp(log_a), b, d)
    ref = numpy_response(t, k, np.exp(log_a), b, d)
    assert np.isfinite(y)
    assert y == pytest.approx(float(ref), rel=1e-12, abs=1e-9)


# -- inversion --------------------------------------------------------------------------------

def test_inversion_equals_bisection_of_the_numpy_form():
    k, a, b, d = _frame(n=3000, seed=4)
    k = np.maximum(k, 0.05)
    for t in (2.0, 25.0, 400.0):
        y = numpy_response(t, k, a, b, d)
        inv = model.invert_response(y, t, a, b, d)
        assert np.all(inv.flags == 0)
        assert np.allclose(inv.k, bisect_k(y, t, a, b, d), rtol=1e-10)
        assert np.allclose(inv.k, k, rtol=1e-9)


@pytest.mark.slow  # compiles the parallel build (~30 s); bench_foundation checks it on a frame
def test_inversion_parallel_and_serial_builds_agree_and_flag_alike():
    k, a, b, d = _frame(n=launch.PARALLEL_MIN + 123, seed=5)
    y = model.response(25.0, k, a, b, d)
    y[997::997] = d[997::997] - 3.0  # below dark
    y[1009::1009] = np.nan
    y[1013::1013] = 5000.0  # clipped at full scale
    outs = []
    for build in (inversion.invert_kernel.parallel, inversion.invert_kernel.serial):
        kk, fl = np.empty(k.size), np.empty(k.size, np.uint32)
        it = np.zeros(-(-k.size // leakage.BLOCK), np.int64)
        build(y, 25.0, a, b, d, 4000.0, np.inf, 1e-9, 60, kk, fl, it)
        outs.append((kk, fl))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])
    fl = outs[0][1]
    assert np.all(fl[997::997] & DQ.BELOW_DARK) and np.all(outs[0][0][997::997] == 0)
    assert np.all(fl[1009::1009] & DQ.NONFINITE)
    assert np.all(fl[1013::1013] & DQ.SATURATED)
    rest = np.ones(k.size, bool)
    rest[997::997] = rest[1009::1009] = rest[1013::1013] = False
    assert np.all(fl[rest] == 0)


def test_inversion_with_fewer_iterations_than_the_vector_pass():
    y = model.response(25.0, 2.0, 2 * np.exp(-8.0), 0.01, 30.0)
    inv = model.invert_response(np.full(10, y), 25.0, 2 * np.exp(-8.0), 0.01, 30.0, max_iter=1)
    assert inv.iterations <= 1
    assert np.all((inv.flags == 0) | (inv.flags == DQ.NOT_CONVERGED))
    assert np.all(inv.flags[inv.flags == 0] == 0)
    full = model.invert_response(np.full(10, y), 25.0, 2 * np.exp(-8.0), 0.01, 30.0)
    assert np.allclose(full.k, 2.0, rtol=1e-12)



def test_inversion_rounds_do_not_depend_on_block_mates():
    """The vectorised rounds run for a whole block while any pixel of it needs them; a
    pixel's k and flags are the same whether its block mates need more rounds or not, and
    agree with bisection on every path (one round, more rounds, the scalar iteration)."""
    n = leakage.BLOCK
    k, a, b, d = _frame(n=n, seed=8)
    k = np.maximum(k, 0.05)
    easy = np.arange(n) % 2 == 0  # short exposures (near linear) beside long ones (leaking)
    t = np.where(easy, 2.0, 400.0)
    y = numpy_response(t, k, a, b, d)
    full = model.invert_response(y, t, a, b, d)
    alone = model.invert_response(y[easy], t[easy], a[easy], b[easy], d[easy])
    assert alone.iterations == inversion.VECTOR_STEPS < full.iterations
    assert np.array_equal(full.k[easy], alone.k)
    assert np.array_equal(full.flags[easy], alone.flags)
    hard = model.invert_response(y[~easy], t[~easy], a[~easy], b[~easy], d[~easy])
    assert np.array_equal(full.k[~easy], hard.k)
    assert np.all(full.flags == 0)
    assert np.allclose(full.k, bisect_k(y, t, a, b, d), rtol=1e-10)

# -- alpha ------------------------------------------------------------------------------------

def test_alpha_forms_equal_the_previous_numpy_forms():
    k, a, b, d = _frame(n=20000, seed=6)
    y = model.response(25.0, k, a, b, d)
    y[:50] = d[:50] - 1.0  # no positive signal: inf
    with np.errstate(divide="ignore", over="ignore"):
        ref_model = 100.0 * np.exp(np.log(a) + b * y - np.log(k))
    assert np.allclose(model.leakage_percentage(y, k, a, b), ref_model, rtol=1e-13,
                       equal_nan=True)
    paper = model.leakage_percentage_paper(y, 25.0, a, b, d)
    assert np.allclose(paper, numpy_alpha_paper(y, 25.0, a, b, d), rtol=1e-13)
    assert np.all(np.isinf(paper[:50]))
    out32 = np.empty(y.shape, np.float32)
    model.leakage_percentage_paper_into(out32, y.astype(np.float32), 25.0, a.astype(np.float32),
                                        b.astype(np.float32), d.astype(np.float32))
    fin = np.isfinite(paper)
    ref32 = numpy_alpha_paper(y.astype(np.float32), 25.0, a.astype(np.float32),
                              b.astype(np.float32), d.astype(np.float32))
    assert np.allclose(out32[fin], ref32[fin], rtol=2e-7)
    with pytest.raises(ValueError, match="out must be"):
        model.leakage_percentage_paper_into(np.empty(3), y, 25.0, a, b, d)


# -- validity flags (alpha and DQ in one pass) -------------------------------------------------

def test_alpha_and_flags_in_one_pass_equal_the_numpy_rule():
    from hsiffc.leakage.validity import leakage_dq

    rng = np.random.default_rng(7)
    n = launch.PARALLEL_MIN + 99
    y = rng.uniform(0, 1100, n).astype(np.float32)
    a = (2e-4 * rng.lognormal(0, 0.5, n)).astype(np.float32)
    b = rng.uniform(0.008, 0.012, n).astype(np.float32)
    d = rng.uniform(20, 40, n).astype(np.float32)
    pix = (rng.random(n) < 0.01).astype(np.uint32) * np.uint32(DQ.HOT)
    dq_in = (rng.random(n) < 0.01).astype(np.uint32) * np.uint32(DQ.NO_FLAT)
    alpha = np.empty(n, np.float32)
    dq = np.empty(n, np.uint32)
    for build in (leakage.alpha_flags_kernel.parallel, leakage.alpha_flags_kernel.serial):
        build(leakage.PixelModel(y, 25.0, a, b, d),
              leakage.FlagRule(12.0, 1023.0, int(DQ.OUT_OF_DOMAIN)),
              leakage.FlagPlanes(pix, dq_in, None), leakage.FlagOutputs(None, alpha, dq, None))
        ref_alpha = numpy_alpha_paper(y, 25.0, a, b, d).astype(np.float32)
        assert np.allclose(alpha, ref_alpha, rtol=1e-6)
        ref = np.zeros(n, np.uint32)  # the former numpy rule
        ref[~(ref_alpha <= 12.0)] |= np.uint32(DQ.LEAKAGE)
        ref[y >= 1023.0] |= np.uint32(DQ.SATURATED)
        ref |= np.uint32(DQ.OUT_OF_DOMAIN) | pix | dq_in
        near = np.isclose(ref_alpha, 12.0, rtol=1e-6)  # float32 rounding at the threshold
        assert np.array_equal(dq[~near], ref[~near])
    flags = leakage_dq(alpha, y, threshold_percent=12.0, full_scale_dn=1023.0, in_domain=False,
                       pixel_flags=pix, dq=dq_in)
    assert np.array_equal(flags, dq)
