"""The compiled model_ffc kernel against a plain numpy statement of the same correction.

``_reference`` is the numpy form model_ffc_apply had before it became one compiled pass (kept
here only as the test's reference): inversion by :func:`hsiffc.leakage.model.invert_response`, then the
signal, the model alpha, the alpha-blended factor and the DQ bits as whole-array operations.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.leakage import model
from hsiffc.data.dq import DQ, DQ_DTYPE
from hsiffc.flatfield.model_based import log_gain_ratio, model_ffc_apply


def _reference(y, t, a, b, d, gain, gain_sweep, flat_alpha, full_scale, alpha_limit=50.0,
               below_tol=1.0, dark_current=0.0):
    y, a, b, d = (np.asarray(v, np.float64) for v in (y, a, b, d))
    inv = model.invert_response(y, t, a, b, d, full_scale=full_scale)
    below = (inv.flags & DQ_DTYPE(DQ.BELOW_DARK)) != 0
    signal = np.where(below | (inv.k <= 0), y - d, (inv.k - dark_current) * t)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        alpha = model.leakage_percentage(y, np.maximum(inv.k, 1e-300), a, b)
    w = np.clip(1.0 - np.nan_to_num(alpha, nan=np.inf) / flat_alpha, 0.0, 1.0)
    ln_s = np.log(np.asarray(gain_sweep, np.float64))
    out = signal * np.exp(ln_s + w * (np.log(np.asarray(gain, np.float64)) - ln_s))
    dq = (inv.flags & ~DQ_DTYPE(DQ.BELOW_DARK)).astype(DQ_DTYPE)
    dq[below & (y < d - below_tol)] |= DQ_DTYPE(DQ.BELOW_DARK)
    dq[~(alpha <= alpha_limit) & ~below] |= DQ_DTYPE(DQ.LEAKAGE)
    finite = np.isfinite(out)
    dq[~finite] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
    alpha = np.minimum(np.nan_to_num(alpha, nan=np.inf), np.finfo(np.float32).max)
    return np.where(finite, out, 0.0).astype(np.float32), dq, alpha.astype(np.float32)


def _case(n, seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(1e-4, 5e-2, n)
    b = rng.uniform(0.005, 0.02, n)
    d = rng.uniform(40, 80, n)
    k = rng.uniform(0, 60, n)
    t = 12.0
    y = np.minimum(model.response(t, k, a, b, d) + rng.normal(0, 1.5, n), 1023)
    y[:50] = d[:50] - rng.uniform(0, 5, 50)  # at and below the dark level
    y[50:60] = 1023  # clipped
    y[60] = np.nan
    gain = rng.uniform(0.9, 1.1, n)
    sweep = gain * rng.uniform(0.99, 1.01, n)
    return y, t, a, b, d, gain, sweep


# the serial build; the parallel one (compile ~45 s on a clean machine) with -m slow and in
# bench_pipeline, which checks it against the serial build on a full frame
@pytest.mark.parametrize("n", [5000, pytest.param(300_000, marks=pytest.mark.slow)])
def test_kernel_equals_the_numpy_statement(n):
    y, t, a, b, d, gain, sweep = _case(n, n)
    out, dq, alpha = model_ffc_apply(y, t, a, b, d, gain, gain_sweep=sweep, full_scale_dn=1023)
    ref_out, ref_dq, ref_alpha = _reference(y, t, a, b, d, gain, sweep, 5.0, 1023)
    assert np.array_equal(dq, ref_dq)
    np.testing.assert_allclose(out, ref_out, rtol=2e-7, atol=1e-6)
    np.testing.assert_allclose(alpha, ref_alpha, rtol=2e-7, atol=1e-30)
    assert np.isfinite(out).all()
    for bit in (DQ.BELOW_DARK, DQ.SATURATED, DQ.LEAKAGE, DQ.NONFINITE):  # every path is hit
        assert (dq & DQ_DTYPE(bit)).any(), bit


def test_without_a_sweep_factor_the_gain_is_used_at_every_level():
    y, t, a, b, d, gain, _ = _case(2000, 7)
    out, dq, _ = model_ffc_apply(y, t, a, b, d, gain, full_scale_dn=1023)
    ref_out, ref_dq, _ = _reference(y, t, a, b, d, gain, gain, 5.0, 1023)
    assert np.array_equal(dq, ref_dq)
    np.testing.assert_allclose(out, ref_out, rtol=2e-7, atol=1e-6)



def test_a_kept_log_ratio_gives_the_same_frame():
    """A caller that keeps ln(gain / gain_sweep) (the model_ffc stage does, per fit) gets the
    very frame the function computes without it; the blend reads it per pixel."""
    y, t, a, b, d, gain, sweep = _case(3000, 11)
    plain = model_ffc_apply(y, t, a, b, d, gain, gain_sweep=sweep, full_scale_dn=1023)
    ratio = log_gain_ratio(gain, sweep)
    assert ratio.dtype == np.float32
    kept = model_ffc_apply(y, t, a, b, d, gain, gain_sweep=sweep, full_scale_dn=1023,
                           log_ratio=ratio)
    for p, k in zip(plain, kept):
        assert np.array_equal(p, k)
    flat_only = model_ffc_apply(y, t, a, b, d, gain, gain_sweep=sweep, full_scale_dn=1023,
                                log_ratio=np.zeros_like(ratio))  # zeros: the sweep factor alone
    assert not np.array_equal(flat_only[0], plain[0])

@settings(max_examples=60, deadline=None)
@given(k=st.floats(0.0, 200.0), a=st.floats(1e-6, 1.0), b=st.floats(1e-3, 0.05),
       d=st.floats(0.0, 200.0), t=st.floats(0.05, 500.0), g=st.floats(0.5, 2.0))
def test_noise_free_response_is_corrected_to_k_t_times_the_factor(k, a, b, d, t, g):
    y = float(model.response(t, k, a, b, d))
    out, dq, _ = model_ffc_apply(np.array([y]), t, a, b, d, np.array([g]))
    # at the zero-light level (k near 0) the documented value is the linear y - d, which sits
    # below k t by what leakage takes from the dark level in the exposure
    drop = d - float(model.response(t, 0.0, a, b, d))
    if dq[0] == 0:  # well inside the model: exact up to float32 rounding
        assert out[0] == pytest.approx(k * t * g, rel=2e-6, abs=2e-4 + g * drop)
