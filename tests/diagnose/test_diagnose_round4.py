"""Diagnose, round four (issue 53): an offset common to the pixels of a frame that follows the
frame's signal (a black-level clamp, outside the library) where the pixels of a frame see
nearly one signal, so that a light error per step or a readout nonlinearity can stand in for
it."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.diagnose import effects as fx


def _data(y, y_ho, t):
    from hsiffc.diagnose.fitting import Data

    s = y.shape[1]
    valid, w = np.ones(y.shape, bool), np.ones(y.shape)
    return Data(y=y, y_ho=y_ho, t=t, r=np.ones(s), valid=valid, valid_ho=valid, w=w,
                order=np.linspace(-1, 1, s), prev_index=np.arange(s) - 1,
                light=np.ones(s, bool), full_scale=4095.0, frame_gap=1.0)


def _sweep(kind, seed, n_pix=400, s=24, spread=0.3, sd=1.0):
    """A linear sensor whose pixels see nearly one signal (responsivity within +-``spread`` of
    10 DN/ms), a shuffled exposure sweep up to 2000 DN, ``sd`` DN of noise, and one of: ``clamp`` (an offset
    common to the pixels of a frame, -0.2 DN per DN of the frame's mean signal above 1000 DN),
    ``light`` (a random light error of 1 % RMS per step) or ``readout`` (a compressive
    quadratic and cubic bend of each pixel's own signal, -60 DN at 2000 DN)."""
    rng = np.random.default_rng(seed)
    t = rng.permutation(np.geomspace(2.0, 200.0, s))
    g = rng.uniform(10.0 - spread, 10.0 + spread, (n_pix, 1))
    signal = g * t
    if kind == "clamp":
        change = np.broadcast_to(-0.2 * np.maximum(signal.mean(axis=0) - 1000.0, 0.0),
                                 signal.shape)
    elif kind == "light":
        change = 0.01 * rng.normal(0.0, 1.0, s) * signal
    else:
        x = signal / 2000.0
        change = -30.0 * x ** 2 - 30.0 * x ** 3
    clean = 40.0 + signal + change
    y, y_ho = (clean + rng.normal(0.0, sd, clean.shape) for _ in range(2))
    return _data(y, y_ho, t)


def _fitted(data, names):
    from hsiffc.diagnose.bases import LinearBase
    from hsiffc.diagnose.fitting import State, fitpredict
    from hsiffc.diagnose.select import evaluate

    base = LinearBase(False)
    st = State(base, base.start(data.y, data.t, data.r, data.valid, data.w))
    return evaluate(fitpredict(names, data, st), names, data, data.y.shape[0], data.y.shape[1])


@pytest.mark.parametrize("seed", [11, 12])
@pytest.mark.parametrize("kind", ["clamp", "light"])
def test_light_factors_that_follow_the_frames_signal_stand_in_for_an_offset(kind, seed):
    """Where every pixel of a frame sees one signal, an offset common to the frame and a light
    error per step are the same thing one step at a time (the offset per step of the probe
    before this round cannot tell them apart). A clamp's factors follow the signal level,
    though: an offset that follows the frame's mean signal (five parameters) predicts the
    held-out frames as well as one factor per step, and the light error is a stand-in. A
    random light error is no function of the signal."""
    from hsiffc.diagnose.select import offset_stand_in

    data = _sweep(kind, seed=seed, spread=0.0, sd=3.0)
    found = offset_stand_in(_fitted(data, ["illumination_error"]), "illumination_error", data)
    assert (found is not None) == (kind == "clamp"), found
    if found:
        assert "follow the frame's signal" in found["reason"]
        assert found["explained_dn2"] > 10 * found["standard_error_dn2"]


@pytest.mark.parametrize("kind", ["clamp", "readout"])
def test_a_readout_bend_that_stands_in_for_a_clamp(kind):
    """A readout nonlinearity (a polynomial in each pixel's signal) takes most of a clamp that
    sets in above one level of the frame's mean signal, but not its kink, which an offset
    that follows the frame's signal with changes of slope fits; where the bend is true, the
    offset misses what differs between the pixels of a frame."""
    from hsiffc.diagnose.select import offset_stand_in

    data = _sweep(kind, seed=12)
    fitted = _fitted(data, ["readout_nonlinearity"])
    found = offset_stand_in(fitted, "readout_nonlinearity", data)
    assert (found is not None) == (kind == "clamp"), found
    if found:
        assert found["gain_dn2"] > 2 * found["standard_error_dn2"]


def test_the_frame_signal_probe_follows_the_frames_mean_signal():
    """The probe's columns are the same for every pixel of a step (a function of the step's
    mean signal, not each pixel's), zero in the dark, and change slope at every eighth of the
    brightest light step's mean signal."""
    s = 5
    signal = np.array([[0.0, 100.0, 200.0, 300.0, 400.0],
                       [0.0, 300.0, 600.0, 900.0, 1200.0]])
    light = np.array([False, True, True, True, True])
    ctx = fx.Context(t=np.ones((2, s)), k=np.ones((2, s)), signal=signal,
                     order=np.linspace(-1, 1, s), prev_signal=signal, light=light,
                     full_scale=1000.0, dydt=np.ones((2, s)), dydlnk=signal)
    x = fx.FRAME_SIGNAL_OFFSET.columns(ctx)
    assert x.shape == (2, s, 7)
    np.testing.assert_array_equal(x[0], x[1])
    np.testing.assert_array_equal(x[:, 0], 0.0)
    mean = signal.mean(axis=0) / 1000.0  # 0, 0.2, 0.4, 0.6, 0.8: the top is 0.8
    np.testing.assert_allclose(x[0, :, 0], np.maximum(mean - 0.1, 0.0))
    np.testing.assert_allclose(x[0, :, 6], np.maximum(mean - 0.7, 0.0))
    assert fx.OFFSET_PROBES["readout_nonlinearity"] is fx.FRAME_SIGNAL_OFFSET
    assert fx.OFFSET_PROBES["lamp_drift"] is fx.FRAME_SIGNAL_OFFSET
    assert set(fx.SMOOTH_PROBES) == {"illumination_error"}
