"""The independent sensors of the FFC zoo (hsiffc.reports.indep_sensors): generated without
hsiffc's simulator, one sensor per seed, and every effect they claim is in their frames
(measured here with numpy). The FFC rule on them is not asserted here."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hsiffc.reports import indep_sensors as ind

REPO = Path(__file__).resolve().parents[2]
SMALL = (48, 64)


def _case(**fields) -> ind.IndepCase:
    """A small linear 12-bit exposure sweep of 4 frames per step, no stack; ``fields`` on top."""
    base = dict(seed=7, primary=ind.PRIMARY_EFFECTS[0], bit_depth=12, light_sweep=False,
                frames_per_step=4, stack_frames=0, n_steps=24, exposure_ms=12.0,
                dark_level_dn=60.0, dsnu_dn=1.0, read_noise_e=5.0, full_well_e=20000.0,
                prnu=0.008, shape=SMALL)
    return ind.IndepCase(**{**base, **fields})


def _step_means(sweep, kind):
    """(exposure, photons, mean frame) of every step of ``kind`` in the sweep part."""
    out = []
    for s in sweep.meta["sweep_steps"]:
        idx = np.flatnonzero(sweep.step == s)
        if sweep.kind[idx[0]] == kind:
            out.append((sweep.exposure_ms[idx[0]], sweep.photons[idx[0]],
                        sweep.data[idx].astype(float).mean(axis=0)))
    return out


def _signal(sweep, top=0.8):
    """(exposure, photons, light - dark mean frame) of the light steps whose mean signal is
    below ``top`` of the clip code."""
    lights, darks = _step_means(sweep, "light"), _step_means(sweep, "dark")
    limit = top * sweep.data.max()
    return [(t, ph, lf - df) for (t, ph, lf), (_, _, df) in zip(lights, darks)
            if lf.mean() < limit]


def test_the_generator_does_not_import_hsiffc_s_simulator():
    code = ("import sys, hsiffc.reports.indep_sensors as m; m.indep_sweep(m.indep_case(2000, "
            "shape=(20, 20))); print(sorted(k for k in sys.modules if k.startswith('hsiffc')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, check=True)
    loaded = eval(out.stdout)  # noqa: S307 -- our own print of a list of strings
    assert "hsiffc.reports.indep_sensors" in loaded
    assert not [m for m in loaded if m.startswith(("hsiffc.simulate", "hsiffc.model",
                                                   "hsiffc.calibrate"))], loaded


def test_one_seed_one_sensor_and_the_halves_are_disjoint():
    a = ind.indep_sweep(ind.indep_case(2003, shape=SMALL))
    b = ind.indep_sweep(ind.indep_case(2003, shape=SMALL))
    assert np.array_equal(a.data, b.data) and a.source == b.source
    assert not np.array_equal(a.data, ind.indep_sweep(ind.indep_case(2008, shape=SMALL)).data)
    assert not set(ind.INDEP_DEV_SEEDS) & set(ind.INDEP_EVAL_SEEDS)
    assert a.source.startswith("independent, seed 2003: common readout nonlinearity")


@pytest.mark.parametrize("seeds", [ind.INDEP_DEV_SEEDS, ind.INDEP_EVAL_SEEDS])
def test_each_half_covers_the_effects_and_designs(seeds):
    cases = [ind.indep_case(s) for s in seeds]
    assert {c.primary for c in cases} == set(ind.PRIMARY_EFFECTS)
    assert {c.frames_per_step for c in cases} == {2, 4}
    assert {bool(c.stack_frames) for c in cases} == {True, False}
    assert all(20 <= c.stack_frames <= 50 for c in cases if c.stack_frames)
    offsets = [c.exposure_offset_ms for c in cases if c.exposure_offset_ms]
    assert min(offsets) < 0 < max(offsets)
    assert not any(c.exposure_offset_ms for c in cases if c.light_sweep)
    assert {c.light_sweep for c in cases if c.nonlinearity} == {True, False}
    assert {c.mosaic_tile for c in cases} == {0, 4, 5}
    assert all(c.dark_level_dn >= 100 for c in cases if c.primary == ind.PRIMARY_EFFECTS[4])
    assert all(30 <= c.n_steps <= 40 and 8 <= c.bit_depth <= 14 for c in cases)


def test_sweep_design_steps_stacks_and_clip():
    case = _case(stack_frames=20, clip_fraction=0.9, n_steps=30)
    sweep = ind.indep_sweep(case)
    assert sweep.data.dtype == np.uint16 and sweep.data.max() == case.clip_code_dn
    assert len(sweep.meta["sweep_steps"]) == 60
    flat, dark = sweep.meta["spatial_steps"]
    assert (sweep.step == flat).sum() == 20 and set(sweep.kind[sweep.step == dark]) == {"dark"}
    assert sweep.exposure_ms[sweep.step == flat][0] == sweep.exposure_ms[sweep.step == dark][0]
    sig = _signal(sweep, top=1.01)
    ratio = sig[0][2].mean() / sig[-1][2].mean()
    assert 0.01 < ratio < 0.04  # from about 2 % of saturation ...
    assert (sweep.data[sweep.step == 2 * 29] == case.clip_code_dn).mean() > 0.5  # ... past it
    assert sweep.mosaic is None
    assert ind.indep_sweep(_case(mosaic_tile=5, n_steps=6)).mosaic.tile_shape == (5, 5)
    light = sweep.kind == "light"
    assert np.allclose(sweep.photons[light], sweep.exposure_ms[light])  # one light level
    assert np.isnan(sweep.photons[~light]).all()
    assert ind.indep_sweep(_case(stack_frames=0)).meta["spatial_steps"] == []


@pytest.mark.parametrize("t0", [0.1, -0.1])
def test_an_exposure_offset_shifts_the_light_response(t0):
    sig = _signal(ind.indep_sweep(_case(exposure_offset_ms=t0)))
    t = np.array([s[0] for s in sig])
    y = np.array([s[2].mean() for s in sig])
    slope, intercept = np.polyfit(t, y, 1)
    assert intercept / slope == pytest.approx(t0, abs=0.02)
    # without the offset the response starts at the dark level
    sig = _signal(ind.indep_sweep(_case()))
    slope, intercept = np.polyfit([s[0] for s in sig], [s[2].mean() for s in sig], 1)
    assert abs(intercept / slope) < 0.02


def test_the_dark_frames_do_not_depend_on_the_light():
    # a light sweep at one exposure, with a dark signal outside the photodiode: every dark
    # step has the same mean frame within its noise, whatever the light of its step
    case = _case(light_sweep=True, outside_dark_dn=40.0, outside_dark_spread=0.6,
                 nonlinearity=0.03)
    darks = np.array([d for _, _, d in _step_means(ind.indep_sweep(case), "dark")])
    first, last = darks[: len(darks) // 2].mean(axis=0), darks[len(darks) // 2:].mean(axis=0)
    noise = darks.std(axis=0, ddof=1).mean() / np.sqrt(len(darks) // 2)  # of a half's mean
    assert abs(first.mean() - last.mean()) < 5 * noise / np.sqrt(first.size)
    assert np.std(first - last) < 1.5 * np.sqrt(2) * noise
    # the dark signal is a per-pixel log-normal pattern above the offset: skewed, and it
    # grows with the exposure on an exposure sweep
    assert np.mean((first - first.mean()) ** 3) > 0
    dark_t = _step_means(ind.indep_sweep(replace(case, light_sweep=False)), "dark")
    slope = np.polyfit([t for t, _, _ in dark_t], [d.mean() for _, _, d in dark_t], 1)[0]
    t_max = case.exposure_ms * 1.15
    assert slope * t_max == pytest.approx(40.0, rel=0.05)


@pytest.mark.parametrize("light_sweep", [True, False])
def test_a_common_nonlinearity_compresses_the_mean_response(light_sweep):
    c = 0.04
    for nonlinearity in (0.0, c):
        case = _case(light_sweep=light_sweep, nonlinearity=nonlinearity, nonlinearity_power=2)
        sig = _signal(ind.indep_sweep(case), top=0.9)
        light = np.array([ph for _, ph, _ in sig])
        y = np.array([s.mean() for _, _, s in sig])
        low, high = y < 0.25 * y.max(), y > 0.7 * y.max()
        drop = 1 - (y[high] / light[high]).mean() / (y[low] / light[low]).mean()
        x = y[high].mean() / case.full_scale_dn  # the compression at the high steps' level
        expected = c * x ** 2 if nonlinearity else 0.0
        assert drop == pytest.approx(expected, abs=0.004), (nonlinearity, drop, expected)


def test_smear_adds_a_column_pattern_proportional_to_the_column_s_light():
    smear = 0.3
    case = _case(smear_ms=smear, mosaic_tile=4)
    sig = _signal(ind.indep_sweep(case))
    t = np.array([s[0] for s in sig])
    frames = np.array([s[2] for s in sig])
    # per pixel, a line over the exposures: slope (the pixel's light) and intercept
    coef = np.polyfit(t, frames.reshape(len(t), -1), 1)
    slope, intercept = (c.reshape(case.shape) for c in coef)
    expected = smear * slope.mean(axis=0)  # the column's mean light for the transfer time
    col = intercept.mean(axis=0)
    assert np.corrcoef(col, expected)[0, 1] > 0.95
    assert np.median(col / expected) == pytest.approx(1.0, abs=0.1)
    # constant down the column: what is left is the fits' noise, not the pixels' light
    within = intercept - col
    assert abs(np.corrcoef(within.ravel(), (slope - slope.mean(axis=0)).ravel())[0, 1]) < 0.2


def test_ccd_like_sensor_has_a_large_flat_dark():
    case = ind.indep_case(2004, shape=SMALL)
    assert case.primary == ind.PRIMARY_EFFECTS[4] and not case.nonlinearity
    darks = _step_means(ind.indep_sweep(case), "dark")
    means = [d.mean() for _, _, d in darks]
    assert np.ptp(means) < 1.0 and abs(np.mean(means) - case.dark_level_dn) < 2.0
    stack = np.array([d for _, _, d in darks])
    temporal = stack.var(axis=0, ddof=1).mean() / len(stack)  # of the mean over the steps
    assert np.sqrt(stack.mean(axis=0).var() - temporal) == pytest.approx(case.dsnu_dn, rel=0.2)


@pytest.mark.parametrize("seed", [2004, 2006])
def test_the_ffc_study_runs_on_a_case_with_and_without_a_flat_stack(seed):
    from hsiffc.reports.ffc_study import run_ffc_study

    case = ind.indep_case(seed, shape=SMALL)
    res = run_ffc_study(ind.indep_sweep(case))
    expected = {"raw", "two_point_2frame", "model_ffc", "model_ffc_calibration"}
    if case.stack_frames:
        expected.add("two_point_stack")
    assert (res.flat_stack is not None) == bool(case.stack_frames)
    for row in res.summary:
        assert set(row["methods"]) <= expected
    assert set().union(*(row["methods"] for row in res.summary)) == expected
    assert {"model_at_most_raw", "failures"} <= set(res.goals)


def test_the_zoo_gives_the_independent_sensors_rows_and_a_summary_row_of_their_own():
    from hsiffc.reports import ffc_zoo

    results = ffc_zoo.run_zoo(seeds=(), indep_seeds=(2006,), designs=())
    (name, res), = results
    assert name == ind.indep_case(2006).label and ffc_zoo.sensor_group(name) == "independent"
    # a simulated sensor beside it (the same study under another name: rendering only)
    zoo = [("simulated, seed 5: stand-in", res)] + results
    page = ffc_zoo.render_zoo(zoo, half="dev")
    summary = page.split("| sensor | rule |")[0]
    assert "| simulated, 1 sensors (development half; median) |" in summary
    assert "| independent, 1 sensors (development half; median) |" in summary
    assert f"## {name}" in page and re.search(r"\d of 1 independent sensors", page)
    doc = ffc_zoo.zoo_json(zoo, half="dev")
    assert doc["half"] == "dev"
    assert [s["group"] for s in doc["sensors"]] == ["simulated", "independent"]


@pytest.mark.parametrize("half, seeds, indep", [
    ("dev", "DEV_SEEDS", ind.INDEP_DEV_SEEDS[:2]),
    ("eval", "EVAL_SEEDS", ind.INDEP_EVAL_SEEDS[:2])])
def test_half_picks_both_grids_seeds(tmp_path, monkeypatch, half, seeds, indep):
    from hsiffc.reports import ffc_zoo

    called = {}
    monkeypatch.setattr(ffc_zoo, "run_zoo", lambda **kw: called.update(kw) or [])
    assert ffc_zoo.main([str(tmp_path), "--half", half, "--seeds", "2"]) == 0
    assert tuple(called["seeds"]) == getattr(ffc_zoo, seeds)[:2]
    assert tuple(called["indep_seeds"]) == indep


def test_the_fixed_designs_have_the_designs_of_issue_50_s_sensors():
    ccd, ref = (ind.DESIGN_CASES[n] for n in ("ccd12-exposure-offset",
                                              "refsim12-light-nonlinear"))
    assert ccd.label.startswith("independent, design ccd12-exposure-offset: CCD-like")
    assert (ccd.bit_depth, ccd.light_sweep, ccd.stack_frames) == (12, False, 50)
    assert ccd.exposure_offset_ms > 0 and not ccd.nonlinearity
    assert (ref.bit_depth, ref.light_sweep, ref.nonlinearity) == (12, True, 0.02)
    assert not ref.exposure_offset_ms and not ref.smear_ms and not ref.outside_dark_dn
    sweep = ind.indep_sweep(replace(ccd, shape=SMALL, n_steps=8, stack_frames=4))
    assert sweep.source.startswith("independent, design ccd12-exposure-offset: ")
