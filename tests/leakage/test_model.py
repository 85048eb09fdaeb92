"""The leakage model: closed form against the ODE, stability, inversion, alpha."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.leakage import model
from hsiffc.data.dq import DQ

# Paper-like parameters: 2 DN/ms of leakage at 800 DN, b = 0.0125 / DN, dark 32 DN
B = 0.0125
A = 2.0 * np.exp(-B * 800.0)
D = 32.0

params = st.fixed_dictionaries({
    "k": st.floats(0.05, 50.0),
    "log_a_over_k": st.floats(-12 * np.log(10), 3 * np.log(10)),
    "b": st.floats(1e-3, 0.05),
    "dark": st.floats(0.0, 100.0),
    "t_end": st.floats(1.0, 2000.0),
})


@settings(max_examples=40, deadline=None)
@given(params)
def test_closed_form_satisfies_the_ode(p):
    a = p["k"] * np.exp(p["log_a_over_k"])
    t = np.linspace(0.0, p["t_end"], 7)
    closed = model.response(t, p["k"], a, p["b"], p["dark"])
    ode = model.solve_ode(t, p["k"], a, p["b"], p["dark"], rtol=1e-11, atol=1e-9)
    scale = max(1.0, float(np.abs(ode).max()))
    assert np.allclose(closed, ode, rtol=0, atol=2e-6 * scale)


@settings(max_examples=40, deadline=None)
@given(params)
def test_closed_form_derivative_is_k_minus_leakage(p):
    a = p["k"] * np.exp(p["log_a_over_k"])
    t = p["t_end"] / 3
    h = 1e-4 * t
    y = model.response(t, p["k"], a, p["b"], p["dark"])
    dydt = (model.response(t + h, p["k"], a, p["b"], p["dark"])
            - model.response(t - h, p["k"], a, p["b"], p["dark"])) / (2 * h)
    rhs = p["k"] - model.leakage_rate(y, a, p["b"])
    assert dydt == pytest.approx(rhs, abs=1e-5 * max(1.0, p["k"], abs(rhs)))


def test_paper_form_with_c_equals_starting_level_form():
    k = np.array([0.5, 2.0, 30.0])
    c = model.c_from_dark(k, A, B, D)
    t = np.linspace(0, 800, 9)[:, None]
    assert np.allclose(model.response_from_c(t, k, A, B, c), model.response(t, k, A, B, D),
                       atol=1e-9)
    assert np.allclose(model.dark_from_c(k, A, B, c), D, atol=1e-9)


def test_printed_eq3_agrees_where_it_does_not_overflow():
    k, t = 2.0, np.array([5.0, 50.0, 200.0])
    c = float(model.c_from_dark(k, A, B, D))
    e = np.exp(B * k * (t + c))
    printed = np.log(k * e / (1 + A * e)) / B
    assert np.allclose(model.response_from_c(t, k, A, B, c), printed, atol=1e-9)


def test_c_is_undefined_above_saturation():
    # dark above the saturation level for this light: no c exists, the result says so (NaN)
    k = 1e-3
    assert model.dynamic_saturation_level(k, A, B) < D + 1000
    assert np.isnan(model.c_from_dark(k, A, B, 2000.0))


@pytest.mark.parametrize("bkt", [1e-6, 1.0, 1e2, 1e4])
@pytest.mark.parametrize("a_over_k", [1e-12, 1e-6, 1.0, 1e3])
def test_finite_and_accurate_over_the_required_range(bkt, a_over_k):
    k, b, dark = 2.0, 0.01, 0.0
    t = bkt / (b * k)
    a = a_over_k * k
    y = model.response(t, k, a, b, dark)
    assert np.isfinite(y)
    ysat = model.dynamic_saturation_level(k, a, b)
    if bkt >= 1e2:
        # far past the time constant the response sits at the dynamic saturation level,
        # which may lie below the start (a/k > 1): then it decays towards it
        assert y == pytest.approx(ysat, abs=1e-6 * max(1.0, abs(ysat)))
    # the paper's printed form, evaluated in extended precision where it is representable
    c = model.c_from_dark(k, a, b, dark)
    if np.isfinite(c):
        assert model.response_from_c(t, k, a, b, c) == pytest.approx(y, abs=1e-7 * max(1, abs(y)))
    if bkt <= 1.0:
        ode = model.solve_ode([t], k, a, b, dark, rtol=1e-12, atol=1e-12)[0]
        assert y == pytest.approx(ode, abs=1e-7 * max(1.0, abs(y)))


def test_zero_leakage_is_the_linear_model():
    t = np.linspace(0, 1e3, 11)
    k = 3.7
    assert np.allclose(model.response(t, k, 0.0, B, D), model.linear_response(t, k, D), atol=1e-9)
    # and a -> 0 converges to it: the deviation shrinks in proportion to a
    dev = [np.abs(model.response(t, k, a, B, D) - (k * t + D)).max() for a in (1e-30, 1e-40)]
    assert dev[0] > 0 and dev[1] < 1e-9 * dev[0] * 1.01 + 1e-12
    assert np.allclose(model.response(t, k, 1e-60, B, D), k * t + D, rtol=1e-12)


def test_zero_light_leaks_down_from_the_dark_level():
    t = np.array([0.0, 10.0, 1e4])
    y = model.response(t, 0.0, A, B, D)
    assert y[0] == pytest.approx(D)
    assert np.all(np.diff(y) <= 0)


def test_saturation_level_matches_the_paper_numbers():
    # Fig. 5: k ~ 2 DN/ms, saturation ~ 800 DN, leakage ~ 2 DN/ms at 800 DN
    assert model.dynamic_saturation_level(2.0, A, B) == pytest.approx(800.0)
    assert model.leakage_rate(800.0, A, B) == pytest.approx(2.0)
    assert model.response(1e5, 2.0, A, B, D) == pytest.approx(800.0)


def test_exposure_at_leakage_percentage_round_trips():
    k = np.array([1.0, 2.0, 30.0])
    for alpha in (0.5, 12.0, 50.0, 99.0):
        t = model.exposure_at_leakage_percentage(alpha, k, A, B, D)
        y = model.response(t, k, A, B, D)
        assert np.allclose(model.leakage_percentage(y, k, A, B), alpha, rtol=1e-9)
    assert np.all(np.isinf(model.exposure_at_leakage_percentage(100.0, k, A, B, D)))
    assert model.exposure_at_leakage_percentage(1e-9, 2.0, A, B, D) == 0.0


def test_alpha_grows_with_exposure_and_paper_alpha_exceeds_100_in_saturation():
    t = np.array([10, 100, 300, 450, 700, 2000.0])
    y = model.response(t, 2.0, A, B, D)
    alpha_model = model.leakage_percentage(y, 2.0, A, B)
    alpha_paper = model.leakage_percentage_paper(y, t, A, B, dark=D)
    assert np.all(np.diff(alpha_model) >= 0) and np.all(alpha_model <= 100 + 1e-9)
    assert np.all(np.diff(alpha_paper) > 0)
    assert alpha_paper[-1] > 100  # like the paper's 173.5 % triangle
    # (Y - d)/t underestimates k, so the paper's alpha is never below the model's
    assert np.all(alpha_paper >= alpha_model * 0.999)
    assert np.isinf(model.leakage_percentage_paper(D - 1, 10.0, A, B, dark=D))


@settings(max_examples=60, deadline=None)
@given(k=st.floats(0.01, 100.0), t=st.floats(0.1, 3000.0), log_a=st.floats(-30, 2),
       b=st.floats(1e-3, 0.05), dark=st.floats(0, 200))
def test_inversion_round_trips(k, t, log_a, b, dark):
    a = np.exp(log_a)
    y = model.response(t, k, a, b, dark)
    inv = model.invert_response(y, t, a, b, dark)
    assert inv.flags == 0
    # a response that moves less than ~1e-9 DN over the whole k change cannot pin k better
    sens = (model.response(t, k * 1.001, a, b, dark) - y) / 1e-3  # dY / dlnk
    assert abs(np.log(inv.k / k)) * sens <= 1e-5 + 1e-9 * abs(y)


def test_inversion_of_whole_frames_and_flags():
    rng = np.random.default_rng(3)
    k = rng.uniform(0.1, 40, size=(64, 48))
    a = A * rng.lognormal(0, 0.2, size=k.shape)
    t = 25.0
    y = model.response(t, k, a, B, D)
    y[0, 0] = 1023.0  # clipped
    y[0, 1] = D - 5.0  # below anything zero light can give
    y[0, 2] = np.nan
    inv = model.invert_response(y, t, a, B, D, full_scale=1023.0, k_max=1e3)
    assert inv.k.shape == k.shape and np.all(np.isfinite(inv.k))
    assert inv.flags[0, 0] & DQ.SATURATED
    assert inv.flags[0, 1] & DQ.BELOW_DARK and inv.k[0, 1] == 0
    assert inv.flags[0, 2] & DQ.NONFINITE
    good = inv.flags == 0
    assert good.sum() == k.size - 3
    assert np.allclose(inv.k[good], k[good], rtol=1e-7)
    # the clipped pixel's k is the rate that just reaches full scale: a lower bound
    assert model.response(t, inv.k[0, 0], a[0, 0], B, D) == pytest.approx(1023.0, abs=1e-4)


def test_inversion_flags_unreachable_above_k_max():
    y = model.response(10.0, 50.0, A, B, D)
    inv = model.invert_response(y, 10.0, A, B, D, k_max=20.0)
    assert inv.flags & DQ.UNREACHABLE and inv.k == 20.0


def test_inversion_recovers_k_in_dynamic_saturation():
    # deep in dynamic saturation Y ~ ln(k/a)/b still depends on k: inversion recovers it
    t = 5000.0
    k = np.array([1.0, 2.0, 4.0])
    y = model.response(t, k, A, B, D)
    assert np.allclose(y, model.dynamic_saturation_level(k, A, B), atol=1e-6)
    inv = model.invert_response(y, t, A, B, D)
    assert np.allclose(inv.k, k, rtol=1e-6)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="b"):
        model.response(1.0, 1.0, 1.0, -0.1, 0.0)
    with pytest.raises(ValueError, match="t_ms"):
        model.invert_response(10.0, 0.0, A, B, D)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.just(np.nan)),
                max_size=20))
def test_smallest_below_zero_means_any_below_zero(values):
    """The input checks use smallest(x) < 0 (one pass, no temporary) for np.any(x < 0)."""
    from hsiffc.leakage.model import smallest

    x = np.array(values, np.float64)
    assert (smallest(x) < 0) == bool(np.any(x < 0))
    assert (smallest(x) <= 0) == bool(np.any(x <= 0))


@pytest.mark.parametrize("n", [7, 70000])  # the serial and the parallel build of the kernel
def test_response_refuses_inputs_outside_the_domain_wherever_they_are(n):
    """The kernel counts the inputs outside the model's domain in its own pass (no separate
    numpy passes): one bad value anywhere is refused with the message that names it; NaN is
    not a domain error (it gives NaN)."""
    rng = np.random.default_rng(5)
    k = rng.uniform(0.5, 20.0, n)
    a = np.full(n, 2e-4)
    b = np.full(n, 0.01)
    d = np.full(n, 40.0)
    y = model.response(25.0, k, a, b, d)
    assert np.all(np.isfinite(y))
    for name, arr, value, match in [("k", k, -1e-9, "k and a must be >= 0"),
                                    ("a", a, -1.0, "k and a must be >= 0"),
                                    ("b", b, 0.0, "b \\(1/DN\\) must be > 0")]:
        bad = arr.copy()
        bad[n - 2] = value
        args = {"k": k, "a": a, "b": b} | {name: bad}
        with pytest.raises(ValueError, match=match):
            model.response(25.0, args["k"], args["a"], args["b"], d)
    with pytest.raises(ValueError, match="t_ms"):
        model.response(np.where(np.arange(n) == 3, -1.0, 25.0), k, a, b, d)
    nan_b = b.copy()
    nan_b[1] = np.nan
    out = model.response(25.0, k, a, nan_b, d)
    assert np.isnan(out[1]) and np.array_equal(out[2:], y[2:])
