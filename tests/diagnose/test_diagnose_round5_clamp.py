"""Diagnose, round five (issue 53): a black-level clamp (an offset common to the pixels of a
frame that follows the frame's mean signal, outside the library) taken up by the leakage base
of a linear sensor."""

from __future__ import annotations

import numpy as np
import pytest

SD = 3.0  # DN of noise a sample


def _sweep(kind, seed, n_pix=200, s=30, spread=0.06):
    """A sensor whose pixels see signals within +-``spread`` of each other (responsivity
    10 DN/ms), shuffled exposures of 2-160 ms at light rates 0.15-1,
    3 DN of noise, and one of: ``clamp`` (a linear sensor, -0.3 DN per DN of the frame's mean
    signal above 700 DN), ``leaky`` (the leakage model, clean) or ``linear`` (clean).
    Returns the samples (hsiffc.diagnose.fitting.Data)."""
    from hsiffc.diagnose.fitting import Data
    from hsiffc.leakage.model import response

    rng = np.random.default_rng(seed)
    t = rng.permutation(np.geomspace(2.0, 160.0, s))
    r = np.exp(rng.uniform(np.log(0.15), 0.0, s))
    k = rng.uniform(10.0 * (1 - spread), 10.0 * (1 + spread), (n_pix, 1)) * r[None, :]
    signal = k * t[None, :]
    if kind == "leaky":
        clean = response(t[None, :], k, 10.0 * np.exp(-0.004 * 2000), 0.004, 40.0)
    elif kind == "clamp":
        clean = 40.0 + signal - 0.3 * np.maximum(signal.mean(axis=0) - 700.0, 0.0)
    else:
        clean = 40.0 + signal
    y, y_ho = (clean + rng.normal(0.0, SD, clean.shape) for _ in range(2))
    valid = np.ones(y.shape, bool)
    return Data(y=y, y_ho=y_ho, t=t, r=r, valid=valid, valid_ho=valid,
                w=np.full(y.shape, SD ** -2), order=np.linspace(-1, 1, s),
                prev_index=np.arange(s) - 1, light=np.ones(s, bool), full_scale=4095.0,
                frame_gap=1.0)


def _fitted(base, data, per_pixel=None):
    """``base`` fitted to convergence, then the linearised step every trial gets, evaluated on
    the held-out samples."""
    from hsiffc.diagnose.fitting import State, refit_base
    from hsiffc.diagnose.select import evaluate

    base.full_scale = data.full_scale
    kw = {} if per_pixel is None else {"per_pixel": per_pixel}
    theta = base.start(data.y, data.t, data.r, data.valid, data.w, **kw)
    if per_pixel is None:
        theta = base.fit(data.y, data.t, data.r, data.valid, data.w, theta, max_iter=40)
    state = refit_base(data.y, data, State(base, theta))
    return evaluate(state, [], data, data.y.shape[0], data.y.shape[1])


@pytest.mark.parametrize("kind", ["clamp", "leaky", "linear"])
def test_leakage_that_takes_up_a_clamp_stands_in_for_it(kind):
    """A clamp that moves the brightest steps of a linear sensor bends the top of every
    pixel's response, and per-pixel leakage takes it up. A linear response with an offset that
    follows the frame's mean signal predicts the held-out data far better than both leakage
    models there; on a leaky sensor (light rates that differ at equal signal) and on a clean
    linear one it does not beat the leakage model with one shape for the sensor, though it
    beats per-pixel leakage (four parameters a pixel follow the noise of the fit half)."""
    from hsiffc.diagnose.bases import LeakageBase, LinearBase, SharedLeakageBase
    from hsiffc.diagnose.select import leakage_stand_in, paired

    data = _sweep(kind, seed=1)
    leak = _fitted(LeakageBase(False), data)
    shared = _fitted(SharedLeakageBase(False), data, leak.state.theta)
    linear = _fitted(LinearBase(False), data)
    found = leakage_stand_in(leak, linear, shared, data, SD)
    assert (found is not None) == (kind == "clamp"), found
    if found:
        assert found["gain_dn2"] > 10 * found["standard_error_dn2"]
        assert "not shown to be leakage" in found["reason"]
    else:  # the comparison with one shape for the sensor is what keeps it
        assert leakage_stand_in(leak, linear, None, data, SD) is None
        gain, se = paired(shared, linear, data.valid_ho)
        assert gain < 5 * se or kind == "linear"
