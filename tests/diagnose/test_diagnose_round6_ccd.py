"""Diagnose, round six (issue 53): a full well that stops the response below the ADC's full
scale with the read noise after it (the shared set ``indep-ccd12-offset`` stops at about
3915 DN of 4095), which the clip test (values piling up at one code) does not see. Its own seed
stream (from ``CLASS3_SEED0``); diagnose leaves the plateau out as it leaves a clip out, and
does not take the dynamic saturation of a leaky pixel (which keeps its shot noise) or a clip
moved by a black-level clamp for a full well."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.data.sweep import Sweep
from hsiffc.diagnose import design as ds
from hsiffc.diagnose import evaluation as ev

GAIN = 0.1  # DN/e-
READ = 3.0  # DN
DARK = 15.0  # DN


def _sweep(signal_e, clamp=None, seed=0, bits=12):
    """Two frames a light step and a dark after it of 2048 pixels at the exposures 1..S ms:
    ``signal_e(t, q)`` the charge (e-) a pixel holds after it collected ``q`` (Poisson, its
    response 0.5 % apart) for ``t`` ms; dark level, read noise, rounding and the ADC's clip;
    ``clamp`` (DN per DN of the frame's mean signal) moves each frame after the ADC."""
    rng = np.random.default_rng(seed)
    n_pix, n_steps = 2048, 24
    resp = 1500.0 * (1 + 0.005 * rng.standard_normal(n_pix))  # e-/ms
    dark = DARK + 0.3 * rng.standard_normal(n_pix)
    fs = 2 ** bits - 1
    frames, t_all, kind = [], [], []
    for t in np.linspace(1.0, float(n_steps), n_steps):
        for what in ("light", "dark"):
            for _ in range(2):
                q = rng.poisson(resp * t).astype(float) if what == "light" else np.zeros(n_pix)
                x = dark + GAIN * (signal_e(t, q) if what == "light" else q)
                x = np.clip(np.rint(x + READ * rng.standard_normal(n_pix)), 0, fs)
                if clamp is not None:
                    x = np.rint(x - clamp * max(x.mean() - 0.3 * fs, 0.0))
                frames.append(x.reshape(32, 64))
                t_all.append(t)
                kind.append(what)
    return Sweep(np.array(frames).astype(np.uint16), exposure_ms=t_all, kind=kind,
                 bit_depth=bits, illumination=["lamp" if k == "light" else "" for k in kind])


def _plateau(sweep):
    return ds.well_plateau(sweep, ds.step_dose(sweep))


def test_a_full_well_below_full_scale_is_found_and_acts_as_the_clip():
    """A hard well at 3000 DN above dark (30 000 e-, reached at 20 ms): the top steps hold the
    read noise alone, not the 17 DN of shot noise, and no code holds a pile-up, so the clip
    test sees nothing."""
    sweep = _sweep(lambda t, q: np.minimum(q, 30000.0))
    assert ds.clip_level(sweep) is None
    got = _plateau(sweep)
    assert got is not None
    assert DARK + 3000 - 8 * READ < got["level_dn"] <= DARK + 3000
    assert got["read_dn2"] == pytest.approx(READ ** 2 + 1 / 12, rel=0.15)
    assert got["plateau_dn2"] < 2 * got["read_dn2"] < got["shot_dn2"]
    smp = ds.samples(ds.subset(sweep, 512, 0)[0])
    assert smp["plateau"] is not None  # of the 512 pixels: their lowest level
    assert got["level_dn"] <= smp["clip_dn"] == smp["plateau"]["level_dn"] < DARK + 3000
    light = smp["kind"] == "light"
    # the steps on the plateau are left out, those well below it kept
    assert not smp["valid"][:, light & (smp["t"] > 20.5)].any()
    assert smp["valid"][:, light & (smp["t"] < 19)].all()
    # a soft well (rounding into the same capacity over 1 % of it) is found as well
    soft = _sweep(lambda t, q: 30000.0 - 300.0 * np.logaddexp(0.0, (30000.0 - q) / 300.0))
    assert _plateau(soft) is not None


def test_a_response_that_keeps_its_shot_noise_is_no_plateau():
    """The dynamic saturation of a leaky pixel (dY/dt = k - a exp(bY): the response flattens
    towards the level where the leak equals the light, here 2400 DN, and its charge keeps its
    shot noise) and a linear sensor clipped by the ADC are no full well; nor a clip that a
    black-level clamp moves by a different offset in every step (a pile-up in each frame, at a
    code of its own)."""
    b = 1.0 / 4000.0  # per e-
    k = 1500.0  # e-/ms

    def leaky(t, q):  # the mean follows the leakage model; q keeps its Poisson spread
        z = np.exp(-b * 24000.0) + (1.0 - np.exp(-b * 24000.0)) * np.exp(-b * k * t)
        mean = -np.log(z) / b
        return q * mean / (k * t)

    sweep = _sweep(leaky)
    light = sweep.kind == "light"
    top = sweep.data[light][-2:].mean() - sweep.data[light][-6:-4].mean()
    assert top < 10 * READ  # the response is flat within the noise at the top
    assert _plateau(sweep) is None
    clipped = _sweep(lambda t, q: 2.0 * q)
    assert clipped.data.max() == 4095 and _plateau(clipped) is None
    clamped = _sweep(lambda t, q: 2.0 * q, clamp=0.05)
    assert clamped.data.max() < 4095
    assert _plateau(clamped) is None


def test_the_stream_is_seeded_and_leaves_the_linear_stream_alone():
    seeds = ev.seeds("all", 0, 0, 0, 8)
    assert seeds == list(range(ev.CLASS3_SEED0, ev.CLASS3_SEED0 + 8))
    assert ev.seeds("dev", 2, 0, 2, 2) == [0, ev.CLASS2_SEED0, ev.CLASS3_SEED0]
    specs = [ev.case_spec(s) for s in seeds]
    assert all(s["round"] == 6 and 0.55 <= s["well"]["of_range"] <= 0.95 for s in specs)
    assert [s["class"] for s in specs[::2]] == list(ev.CCD_KINDS)
    # the linear stream draws what it drew (round five): no well, its own fill
    old = ev.case_spec(ev.CLASS2_SEED0 + 3)
    assert "well" not in old and old == ev.ccd_case_spec(ev.CLASS2_SEED0 + 3)


def test_a_well_case_stops_below_full_scale_with_the_read_noise_after_it():
    spec = ev.case_spec(ev.CLASS3_SEED0 + 16)  # a clean linear sensor, a hard well, 14 bit
    sweep, truth = ev.build_case(spec)
    again, _ = ev.build_case(spec)
    assert np.array_equal(sweep.data, again.data)
    assert truth["stream"] == 6 and truth["effects"] == [] and truth["well_soft"] == 0
    top = spec["params"]["dark_level_dn"] + truth["well_dn"]
    assert sweep.data.max() < sweep.full_scale_dn
    assert ds.clip_level(sweep) is None
    got = _plateau(sweep)
    assert got is not None and abs(got["level_dn"] - top) < 0.01 * truth["well_dn"]
    summary = ev.summarise([{"case": {"seed": spec["seed"], "n_rates": 1, "darks": True,
                                      "n_frames": 2}, "truth": truth,
                             "found": {"selected": [], "unexplained": False,
                                       "leakage": "not needed", "ambiguous": [],
                                       "runtime_s": 1.0}, "right": True,
                             "false_alarm": False, "leakage_claimed": False}])
    assert summary["well"]["clean_linear"]["right"] == 1 and "ccd" not in summary
    assert "well fills below the ADC's range" in ev.markdown(summary, [], "how")


def test_diagnose_fits_the_offset_on_the_samples_that_carry_signal():
    """The exposure offset of a sensor whose well fills below full scale: the plateau is left
    out (a design note says so) and the offset is found alone."""
    from hsiffc.diagnose import diagnose

    spec = ev.case_spec(ev.CLASS3_SEED0 + 18)  # an offset, a hard well at 12 bit, 3 rates
    sweep, truth = ev.build_case(spec)
    out = diagnose(sweep, max_pixels=256, seed=0)
    assert any("the response stops at" in n for n in out["design"]["notes"])
    assert out["selected_effects"] == ["exposure_offset"], out["candidates"]
    t0 = out["effects"][0]["params"]["t0_ms"]
    assert t0 == pytest.approx(truth["t0_ms"], rel=0.3)
