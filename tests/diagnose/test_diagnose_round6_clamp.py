"""Diagnose, round six (issue 53): a black-level clamp (an offset the same for every pixel of a
frame, outside the library) that a library effect describes. A readout nonlinearity bends each
pixel's response by its own signal and a light error scales each pixel's signal, so between the
pixels of one frame they differ; the clamp does not. Where the pixels of a frame do not show
that part, the effect stands in for an offset common to the frame's pixels."""

from __future__ import annotations

import numpy as np
import pytest

SD = 3.0  # DN of noise a sample


def _sweep(kind, seed, n_pix=200, s=30, spread=0.2):
    """A linear sensor (dark level 40 DN) whose pixels see signals within +-``spread`` of each
    other, shuffled exposures of 2-160 ms at light rates 0.15-1 (responsivity 10 DN/ms), 3 DN
    of noise a sample, and one of: ``clamp`` (-0.3 DN per DN of the frame's mean signal above
    700 DN), ``readout`` (a compression of each pixel's own signal, -300 DN at 1600 DN) or
    ``light`` (the light of each step off by 2 % RMS). Returns the samples
    (hsiffc.diagnose.fitting.Data)."""
    from hsiffc.diagnose.fitting import Data

    rng = np.random.default_rng(seed)
    t = rng.permutation(np.geomspace(2.0, 160.0, s))
    r = np.exp(rng.uniform(np.log(0.15), 0.0, s))
    k = rng.uniform(10.0 * (1 - spread), 10.0 * (1 + spread), (n_pix, 1)) * r[None, :]
    signal = k * t[None, :]
    if kind == "clamp":
        signal = signal - 0.3 * np.maximum(signal.mean(axis=0) - 700.0, 0.0)
    elif kind == "readout":
        signal = signal - 300.0 * (signal / 1600.0) ** 2
    else:
        signal = signal * (1.0 + rng.normal(0.0, 0.02, s))[None, :]
    y, y_ho = (40.0 + signal + rng.normal(0.0, SD, signal.shape) for _ in range(2))
    valid = np.ones(y.shape, bool)
    return Data(y=y, y_ho=y_ho, t=t, r=r, valid=valid, valid_ho=valid,
                w=np.full(y.shape, SD ** -2), order=np.linspace(-1, 1, s),
                prev_index=np.arange(s) - 1, light=np.ones(s, bool), full_scale=4095.0,
                frame_gap=1.0)


def _with_effect(name, data):
    """A linear base with effect ``name``, fitted to convergence (as the search fits its
    choice), evaluated on the held-out samples."""
    from hsiffc.diagnose.bases import LinearBase
    from hsiffc.diagnose.fitting import State, fitpredict, refit_base
    from hsiffc.diagnose.select import evaluate

    base = LinearBase(False)
    base.full_scale = data.full_scale
    theta = base.start(data.y, data.t, data.r, data.valid, data.w)
    start = refit_base(data.y, data, State(base, theta))
    p, s = data.y.shape
    return evaluate(fitpredict([name], data, start), [name], data, p, s)


@pytest.mark.parametrize("kind, name", [("clamp", "readout_nonlinearity"),
                                        ("clamp", "illumination_error"),
                                        ("readout", "readout_nonlinearity"),
                                        ("light", "illumination_error")])
def test_effect_the_pixels_of_a_frame_do_not_show_stands_in(kind, name):
    """Fitted to a clamp, a readout nonlinearity or a light error explains the frames' mean
    levels, but the pixels of a frame do not follow it: its coefficient beside one offset per
    step is near 0 and far below 1, and it is a stand-in. Where it is the true effect the
    coefficient is near 1 and it stays a finding."""
    from hsiffc.diagnose.select import frame_constant_stand_in

    data = _sweep(kind, seed=3)
    fitted = _with_effect(name, data)
    found = frame_constant_stand_in(fitted, [name], data)
    if kind == "clamp":
        assert found is not None
        assert abs(found["beta"]) < 3 * found["standard_error"] < 1, found
        assert found["effects"] == [name]
        assert "black-level clamp" in found["reason"]
        # not decided on the per-pixel leakage base, whose fitted leakage shapes carry the
        # part that differs between the pixels there (their noise pulls the coefficient to 0)
        fitted.state.base.name = "leakage"
        assert frame_constant_stand_in(fitted, [name], data) is None
    else:
        assert found is None
    # effects it does not judge, and none at all
    assert frame_constant_stand_in(fitted, ["offset_drift"], data) is None
    assert frame_constant_stand_in(fitted, [], data) is None
