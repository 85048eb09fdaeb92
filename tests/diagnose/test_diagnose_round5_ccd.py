"""Diagnose, round five (issue 53): a linear sensor with an exposure offset (light collected for
longer than the nominal exposure) and a soft compression of the well as it fills, the physics
of the shared set ``indep-ccd12-offset``. Its own seed stream (from ``CLASS2_SEED0``), written
from its own physics; a per-pixel leakage shape took most of the offset and the compression,
so the offset was not found and leakage was called needed on a sensor without any."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hsiffc.diagnose import evaluation as ev


def test_the_stream_is_seeded_split_and_leaves_the_other_streams_alone():
    seeds = ev.seeds("all", 0, 0, 16)
    assert seeds == list(range(ev.CLASS2_SEED0, ev.CLASS2_SEED0 + 16))
    assert ev.seeds("dev", 4, 0, 4) == [0, 2, ev.CLASS2_SEED0, ev.CLASS2_SEED0 + 2]
    specs = [ev.case_spec(s) for s in seeds]
    assert all(s["round"] == 5 and not s["leaky"] for s in specs)
    for half in ("dev", "eval"):
        assert {s["class"] for s in specs if s["half"] == half} == set(ev.CCD_KINDS)
    # both halves hold each kind in turn
    assert [s["class"] for s in specs[:8:2]] == list(ev.CCD_KINDS)
    assert ev.case_spec(ev.CLASS2_SEED0 + 3) == ev.case_spec(ev.CLASS2_SEED0 + 3)
    # an offset at one light level is drawn with darks (without them it is a dark level)
    for s in specs:
        if "offset" in s["class"] and s["n_rates"] == 1:
            assert s["darks"]
    # the other streams draw what they drew
    assert "round" not in ev.case_spec(5)
    assert ev.case_spec(ev.CLASS_SEED0 + 1)["round"] == 3


def test_a_case_is_built_the_same_twice_with_the_effects_at_5x_or_more():
    spec = ev.case_spec(ev.CLASS2_SEED0 + 6)  # an offset and a compression
    a, truth = ev.build_case(spec)
    b, _ = ev.build_case(spec)
    assert np.array_equal(a.data, b.data) and a.data.shape[1:] == ev.SHAPE
    assert [e["name"] for e in truth["effects"]] == ["exposure_offset", "readout_nonlinearity"]
    assert all(e["multiple"] >= 5 for e in truth["effects"])
    assert truth["t0_ms"] > 0 and truth["compression"] > 0
    # the same sweep without the effects: more light in the short exposures (the offset), the
    # darks hold the dark level alone either way
    clean = ev.ccd_sweep({**spec, "t0_of_max": 0.0, "compression": 0.0})[0]
    light = a.kind == "light"
    short = light & (a.exposure_ms == a.exposure_ms[light].min())
    lift = a.data[short].mean() - clean.data[short].mean()
    assert lift > 0.5 * truth["t0_ms"] / a.exposure_ms[short][0] * (
        clean.data[short].mean() - clean.data[~light].mean())
    assert abs(a.data[~light].mean() - clean.data[~light].mean()) < 0.1
    assert a.data.max() <= a.full_scale_dn


def test_the_stream_is_scored_on_its_own():
    def case(seed, what, selected, leakage):
        truth = {"class": what, "stream": 5, "kind": "single", "effects": []}
        found = {"selected": selected, "unexplained": False, "leakage": leakage,
                 "ambiguous": [], "runtime_s": 1.0}
        return {"case": {"seed": seed, "n_rates": 1, "darks": True, "n_frames": 2},
                "truth": truth, "found": found, **ev.ccd_verdict(truth, found)}

    results = [case(1, "exposure_offset", ["exposure_offset"], "cannot tell"),
               case(3, "well_compression", ["readout_nonlinearity"], "needed"),
               case(5, "clean_linear", [], "not needed")]
    assert [r["right"] for r in results] == [True, False, True]
    summary = ev.summarise(results)
    assert summary["scores"]["named_right_5x"]["n"] == 0  # not mixed into the first streams
    assert summary["ccd"]["well_compression"]["leakage_claimed"] == 1
    text = ev.markdown(summary, [], "how")
    assert "| well compression | 0 % (0/1) | 1/1 |" in text
    json.dumps(summary)


def _one_rate(n_pix=300, t0=0.3, compression=0.03, seed=5):
    """Step means (fit and held-out halves) of a linear sensor at one light rate with darks at
    every exposure: light collected for ``t0`` ms longer than the nominal exposure, a well that
    fills as ``S (1 - exp(-x / S))`` (``compression`` low at 3000 DN), 2 DN of noise."""
    from hsiffc.diagnose.fitting import Data

    rng = np.random.default_rng(seed)
    t = np.concatenate([np.geomspace(1.0, 40.0, 20)] * 2)
    light = np.repeat([True, False], 20)
    g = rng.uniform(60.0, 100.0, (n_pix, 1))
    scale = ev._well_capacity(compression, 3000.0)
    x = np.where(light, g * (t + t0), 0.0)
    clean = 50.0 + (-scale * np.expm1(-x / scale))
    y, y_ho = (clean + rng.normal(0.0, 2.0, clean.shape) for _ in range(2))
    valid = np.ones(y.shape, bool)
    return Data(y=y, y_ho=y_ho, t=t, r=light.astype(float), valid=valid, valid_ho=valid,
                w=np.full(y.shape, 0.25), order=np.linspace(-1, 1, t.size),
                prev_index=np.arange(t.size) - 1, light=light, full_scale=4095.0,
                frame_gap=1.0)


def test_the_linear_alternative_gets_the_exposure_offset():
    """A line per pixel with a readout nonlinearity misses the offset's lift of the short
    exposures (the leakage shape takes it); with the offset added it reaches what was put in."""
    from hsiffc.diagnose.bases import LinearBase
    from hsiffc.diagnose.fitting import State, fitpredict, refit_base
    from hsiffc.diagnose.select import evaluate, linear_with_offset, paired

    data = _one_rate()
    base = LinearBase(False)
    start = evaluate(refit_base(data.y, data, State(base, base.start(
        data.y, data.t, data.r, data.valid, data.w))), [], data, 300, 20)
    rn = ["readout_nonlinearity"]
    alt = evaluate(fitpredict(rn, data, start.state), rn, data, 300, 20)
    got = linear_with_offset(alt, start, rn + ["exposure_offset"], data, 300, 20)
    assert got.names == rn + ["exposure_offset"]
    gain, se = paired(alt, got, data.valid_ho)
    assert gain > 5 * se
    assert got.state.effects["exposure_offset"][0][0] == pytest.approx(0.3, rel=0.1)
    # not a candidate (one exposure, or skipped): the alternative as it was
    assert linear_with_offset(alt, start, rn, data, 300, 20) is alt


def test_leakage_is_not_claimed_where_every_signal_has_one_light_rate():
    from hsiffc.diagnose.select import Fitted, one_rate_shape

    def fitted(names, mse):
        return Fitted(state=None, names=names, res=np.zeros((1, 1)), mse=mse, bic=0.0,
                      n_params=1)

    out = one_rate_shape(fitted(["lamp_drift"], 100.0), fitted(["readout_nonlinearity"], 196.0),
                         96.0, 1.5, {"design_separates_by_light_rate": False})
    assert out["verdict"] == "cannot tell"
    assert out["models"] == ["leakage base + lamp_drift", "linear base + readout_nonlinearity"]
    assert "one light rate" in out["reason"] and "64 standard errors" in out["reason"]
