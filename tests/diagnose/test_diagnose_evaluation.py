"""Diagnose measured, not tuned: the three sweeps of issue 38 built with hsiffc's simulator
(a readout compression on a leaky sensor with four light rates; a strong log-normal dark
current; a 12-bit light sweep with a 2 % cubic nonlinearity and no leakage), the honest
verdicts (``unexplained`` agrees with the figures; ``ambiguous`` ties), the step-factor trend
test, and the evaluation generator: a small fixed sample of it in the default run, the whole
evaluation half behind ``-m slow``."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from hsiffc.diagnose import diagnose
from hsiffc.diagnose import evaluation as ev
from hsiffc.diagnose.simulated import simulated_sweep
from hsiffc.diagnose.effects import add_effect, add_term, effect_term, truth_terms
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor, SensorParams


def _honest(out):
    """The verdict agrees with the figures printed beside it."""
    after = out["after"]
    if after["systematic_rms_dn"] > 0.5 * after["noise_floor_dn"]:
        assert out["unexplained"], out["unexplained_reason"]
    if not out["unexplained"]:
        assert "within" in out["unexplained_reason"]
    assert isinstance(out["ambiguous"], list)


def test_readout_compression_on_a_leaky_sensor_with_four_light_rates():
    # 2 % low at half of full scale; the design reaches equal signal at four light rates, so
    # the compression (signal only) is told from the leakage (light rate dependent)
    sensor = MosaicSensor((24, 32), params=SensorParams(dark_current_dn_per_ms=0.0), seed=11)
    t = np.tile(np.geomspace(2, 200, 10), 4)
    levels = np.repeat([1.0, 0.6, 0.35, 0.2], 10)
    sw = sensor.sweep_varying_light(t, levels, "lamp A",
                                    irradiance_w_m2=0.5 * PAPER_LIGHT_W_M2["training"], seed=12)
    sw = add_effect(sw, "readout_nonlinearity", -0.04 * sw.full_scale_dn)
    out = diagnose(sw)
    assert out["selected_effects"][:1] == ["readout_nonlinearity"], out["candidates"]
    assert "illumination_error" not in out["selected_effects"]
    assert out["leakage"]["verdict"] == "needed"
    assert out["base_model"].startswith("leakage")
    assert not any(s["name"] == "readout_nonlinearity" for s in out["skipped"])
    assert out["after"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    assert not out["unexplained"]
    _honest(out)


def test_strong_lognormal_dark_current_is_the_base_and_nothing_else():
    # median 0.5 DN/ms, log-normal sigma 1: up to ~10 DN/ms, hundreds of DN at 200 ms; the
    # strongest pixels' darks bend (their charge leaks like the light's)
    sw = simulated_sweep("mixed", seed=5, dark_current_dn_per_ms=0.5, dark_current_spread=1.0)
    out = diagnose(sw)
    assert "dark current" in out["dark_model"]["model"]
    assert out["selected_effects"] == [], out["candidates"]
    assert out["before"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    assert not out["unexplained"]
    _honest(out)


def test_cubic_nonlinearity_on_a_linear_12_bit_light_sweep_is_not_leakage():
    # like the EMVA 1288 reference simulation: one exposure, light steps, no leakage, and a
    # 2 % cubic compression at full scale shared by every pixel
    fs = 4095
    sw = simulated_sweep("light", seed=6, n_steps=30, bit_depth=12,
                         conversion_gain_dn_per_e=0.28, full_well_e=16000.0, read_noise_dn=3.0,
                         dark_level_dn=60.0, leak_rate_dn_per_ms=1e-9,
                         leak_b_per_dn=12.8 / fs, leak_ref_dn=0.8 * fs,
                         irradiance=1.6 * PAPER_LIGHT_W_M2["training"])
    c = truth_terms(sw)
    sw = add_term(sw, -0.02 * c["signal"] * (c["signal"] / fs) ** 2)
    out = diagnose(sw)
    assert out["base_model"].startswith("linear"), out["leakage"]
    assert out["selected_effects"] == ["readout_nonlinearity"], out["candidates"]
    # parsimony is stated: a shared compression against per-pixel leakage
    assert out["leakage"]["verdict"] in ("not needed", "cannot tell")
    assert "fewer parameters" in out["leakage"]["reason"]
    if out["leakage"]["verdict"] == "cannot tell":
        assert out["ambiguous"]
    dev = out["effects"][0]["params"]["deviation_at_full_scale_dn"]
    assert dev == pytest.approx(-0.02 * fs, rel=0.3)
    assert out["after"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    _honest(out)


def test_a_smooth_misfit_is_not_taken_for_per_step_light_errors():
    """A per-step light error whose factors follow the signal is refused with the reason; a
    random one is accepted."""
    from hsiffc.diagnose.select import step_trend

    sw = simulated_sweep("exposure", seed=9, n_steps=24, shape=(16, 32))
    out = diagnose(add_effect(sw, "illumination_error", 0.02, seed=3))
    assert out["selected_effects"] == ["illumination_error"], out["candidates"]
    assert callable(step_trend)
    # a smooth function of the signal seen through per-step factors (shuffled exposures and
    # light: the factors are not in the order of the signal)
    sw = simulated_sweep("mixed", seed=9, n_steps=24, shape=(16, 32))
    c = truth_terms(sw)
    smooth = 0.03 * c["dydlnk"] * (c["signal"] / sw.full_scale_dn - 0.3) * c["light"][None, :]
    out = diagnose(add_term(sw, smooth))
    assert "illumination_error" not in out["selected_effects"]
    rejected = [e for e in out["candidates"] if e["name"] == "illumination_error"
                and "rejected" in e]
    assert rejected and "step factors follow" in rejected[0]["rejected"]
    _honest(out)


def test_unexplained_follows_the_systematic_error_left():
    # an effect outside the library, large: the systematic error left is above half the
    # noise, and the verdict says so in numbers
    sw = simulated_sweep("mixed", seed=2, shape=(16, 32), n_steps=24)
    c = truth_terms(sw)
    out = diagnose(add_term(sw, ev.outside_term(sw, "slow_lag", 0.02, c)))
    assert out["unexplained"]
    _honest(out)


def test_leakage_start_values_follow_the_signal_span_and_no_pixel_falls_below_dark():
    from hsiffc.diagnose.bases import B_SPAN_GRID, LeakageBase, b_grid

    y = np.array([[100.0, 1100.0, 8100.0], [100.0, 1100.0, 8100.0]])
    valid = np.ones_like(y, bool)
    # b x span over the grid, for the span of the data and up to full scale (14-bit)
    grid = b_grid(y, valid, full_scale=16383.0)
    assert min(grid) == pytest.approx(B_SPAN_GRID[0] / (16383.0 - 100.0))
    assert max(grid) == pytest.approx(B_SPAN_GRID[-1] / 8000.0)
    # a leaky pixel in the dark stays at its dark level (the leakage model alone would drain it)
    base = LeakageBase(False)
    theta = np.array([[np.log(2.0), np.log(0.05), np.log(0.02), 50.0, 0.0]])
    t, r = np.array([10.0, 100.0, 10.0]), np.array([0.0, 0.0, 1.0])
    m, jac, _, dydt, _ = base.evaluate(theta, t, r)
    assert m[0, :2].tolist() == [50.0, 50.0] and m[0, 2] > 50.0
    assert jac[0, 0].tolist() == [0.0, 0.0, 0.0, 1.0] and dydt[0, 0] == 0.0
    np.testing.assert_array_equal(base.predict(theta, t, r), m)


def test_quantisation_bias_of_quiet_integer_samples():
    from hsiffc.diagnose.design import quantisation_bias

    v = np.array([0.0, 0.005, 0.02, 0.05, 0.1, 0.3, 5.0])
    bias = quantisation_bias(v)
    assert bias[0] == pytest.approx(1 / 12, rel=0.01)  # all rounding, no noise
    assert np.all(np.diff(bias) < 0) and bias[-1] < 1e-12  # noisy samples: none
    assert quantisation_bias(4 * v, quantum=2.0) == pytest.approx(4 * bias)
    assert not quantisation_bias(v, quantum=0.0).any()


def test_generator_is_seeded_and_split_in_halves():
    assert ev.case_spec(5) == ev.case_spec(5)
    assert ev.case_spec(5) != ev.case_spec(7)
    assert ev.seeds("dev", 10) == [0, 2, 4, 6, 8] and ev.seeds("eval", 10) == [1, 3, 5, 7, 9]
    assert not set(ev.seeds("dev", 240)) & set(ev.seeds("eval", 240))
    with pytest.raises(ValueError, match="half"):
        ev.seeds("test", 10)
    kinds = {ev.case_spec(s)["kind"] for s in range(40)}
    assert kinds == {"clean", "single", "pair", "outside"}
    designs = {ev.case_spec(s)["design"] for s in range(40)}
    assert designs == {"exposure", "light", "mixed"}
    assert {ev.case_spec(s)["bit_depth"] for s in range(40)} == {8, 10, 12, 14, 16}


def test_effect_sizes_are_in_units_of_the_detection_limit():
    spec = ev.case_spec(3)
    sw = ev.clean_sweep(spec)
    terms = truth_terms(sw)
    unit = effect_term(sw, "image_lag", 1.0, terms=terms)
    dl = ev.detection_limit(sw, unit, terms)
    sd, mask, project = ev._noise_and_projector(sw, terms)
    sep = project(dl * unit)
    rms = np.sqrt(np.mean(sep[mask] ** 2))
    assert rms == pytest.approx(ev.DL_OF_NOISE * np.sqrt(np.mean(sd[mask] ** 2)), rel=1e-6)
    # the sweep carries the size put in: twice the effect, twice the change in the frames
    a = add_term(sw, 2 * dl * unit).data.astype(float) - sw.data
    assert np.abs(a).max() > 0


#: a fixed sample of the development half (the fastest cases of its first 15 seeds): a light
#: sweep with per-step light errors at 2x, a clean 8-bit light sweep, a within-step light
#: change at 10x on an exposure sweep at several light rates, a clean mixed 10-bit sweep; and
#: two that failed before: random per-step light errors at 10x on a mixed sweep without darks
#: (their factors trended only along what the base absorbs), a clean leaky 14-bit sensor driven
#: near its dynamic saturation (the base fit stayed linear and a readout nonlinearity was
#: selected)
SAMPLE = (2, 8, 26, 28, 36, 42)


def test_fixed_sample_of_the_generator():
    results = ev.run(SAMPLE)
    summary = ev.summarise(results)
    kinds = [r["truth"]["kind"] for r in results]
    assert kinds == ["single", "clean", "single", "clean", "single", "clean"]
    assert [r["right"] for r in results] == [True] * len(SAMPLE), [
        (r["case"]["seed"], r["truth"], r["found"]["selected"]) for r in results]
    assert summary["scores"]["false_alarm_clean"] == {"fraction": 0.0, "right": 0, "n": 3}
    assert summary["n_cases"] == len(SAMPLE)
    text = ev.markdown(summary, [], "how")
    assert "Confusion matrix" in text and "| clean |" in text
    json.dumps(summary)


def test_write_page_between_markers(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("head\n<!-- BEGIN evaluation -->\nold\n<!-- END evaluation -->\ntail\n")
    ev.write_page(page, "new table\n")
    assert page.read_text() == ("head\n<!-- BEGIN evaluation -->\n\nnew table\n\n"
                                "<!-- END evaluation -->\ntail\n")
    bad = tmp_path / "q.md"
    bad.write_text("no markers")
    with pytest.raises(ValueError, match="markers"):
        ev.write_page(bad, "x")


def test_the_rounds_table_has_a_column_per_code():
    """One column per code before and one for now; a code before is scored on the seeds it
    holds (an evaluation half grown since it ran)."""
    def case(seed, kind, right, name="frame_lag"):
        effects = [] if kind == "clean" else [{"name": name}]
        return {"case": {"seed": seed}, "truth": {"kind": kind, "effects": effects},
                "right": right, "false_alarm": False}
    now = [case(1, "clean", True), case(3, "single", True), case(5, "single", True)]
    first = [case(1, "clean", True), case(3, "single", False)]
    second = [case(1, "clean", False), case(3, "single", True), case(5, "single", False)]
    text = ev.by_round([("first", first), ("second", second)], now)
    assert "| `first` (2) | `second` (3) | now |" in text
    assert "| frame_lag | 2 | 0/1 | 1/2 | 2/2 |" in text
    assert "| all | 3 | 1/2 | 1/3 | 3/3 |" in text
    # a class no code before holds a seed of
    text = ev.by_round([("first", first)], now + [case(7, "single", True, "lamp_drift")])
    assert "| lamp_drift | 1 | - | 1/1 |" in text


@pytest.mark.slow
def test_full_evaluation_half(tmp_path):
    """The published evaluation (the failure classes of issue 53): every seed of the evaluation
    half gives the scores the diagnose page shows (they are deterministic)."""
    from pathlib import Path

    out = tmp_path / "eval.json"
    assert ev.main(["--half", "eval", "--cases", "1", "--classes", "336", "--classes2", "80",
                    "--classes3", "40", "--jobs", "2", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    sc = summary["scores"]
    # issue 53: every case reported unexplained labels its selected effects stand-ins
    assert sc["stand_ins_labelled"]["fraction"] in (None, 1.0)
    page = (Path(__file__).resolve().parents[2] / "docs" / "diagnose.md").read_text()
    published = page.split("<!-- BEGIN evaluation -->")[1].split("<!-- END evaluation -->")[0]
    table = ev.markdown(summary, [], "how").split("Shared data sets")[0]
    for line in table.splitlines():
        if line.startswith("| ") and "%" in line:
            assert line in published, line


def test_report_states_ties_and_the_unexplained_reason(tmp_path):
    from hsiffc.diagnose.report import write_report

    out = diagnose(simulated_sweep("mixed", seed=3, shape=(16, 16), n_steps=12))
    out["ambiguous"] = [{"effects": ["readout_nonlinearity", "illumination_error"],
                         "reason": "both fit the held-out data equally well"}]
    text = write_report(out, tmp_path).read_text()
    assert "## Equally good explanations" in text
    assert "readout_nonlinearity / illumination_error: both fit" in text
    assert out["unexplained_reason"] in text
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["ambiguous"][0]["effects"] == ["readout_nonlinearity", "illumination_error"]


def test_shared_leakage_base_fits_one_leakage_shape_for_the_sensor():
    """Gain and dark per pixel, a and b for the sensor: the fit finds the shape, costs no
    more than the per-pixel leakage fit allows, and absorbs per pixel only what a pixel owns."""
    from hsiffc.diagnose.bases import LeakageBase, SharedLeakageBase
    from hsiffc.diagnose.fitting import Data
    from hsiffc.diagnose.select import evaluate
    from hsiffc.leakage import model

    rng = np.random.default_rng(0)
    n_pix, a, b = 150, 1e-2, 5e-3
    t = np.tile(np.geomspace(2.0, 200.0, 12), 2)
    r = np.repeat([1.0, 0.4], 12)
    g = rng.uniform(8.0, 12.0, n_pix)[:, None]
    d = rng.uniform(50.0, 60.0, n_pix)[:, None]
    y = model.response(t, g * r, a, b, d) + rng.normal(0.0, 1.0, (n_pix, t.size))
    valid, w = np.ones(y.shape, bool), np.ones(y.shape)
    shared = SharedLeakageBase(False)
    shared.full_scale = 4095.0
    theta = shared.start(y, t, r, valid, w)
    assert np.ptp(theta[:, 1]) == 0 and np.ptp(theta[:, 2]) == 0  # one shape
    assert np.exp(theta[0, 1]) == pytest.approx(a, rel=0.2)
    assert np.exp(theta[0, 2]) == pytest.approx(b, rel=0.05)
    per_pixel = LeakageBase(False)
    per_pixel.full_scale = 4095.0
    th_pp = per_pixel.start(y, t, r, valid, w)
    c_sh = float((w * (y - shared.predict(theta, t, r)) ** 2).sum())
    c_pp = float((w * (y - per_pixel.predict(th_pp, t, r)) ** 2).sum())
    # the noise alone: chi-square ~ n_samples; the two extra per-pixel parameters take ~2 each
    assert c_pp <= c_sh < c_pp + 4 * n_pix
    assert c_sh < 1.1 * y.size
    # the Jacobian holds the per-pixel parameters only, and the parameter count is honest
    m, jac, *_ = shared.evaluate(theta, t, r)
    assert jac.shape == (n_pix, t.size, 2)
    np.testing.assert_allclose(m, shared.predict(theta, t, r))
    from hsiffc.diagnose.fitting import State
    st = State(shared, theta)
    st.prediction = m
    data = Data(y=y, y_ho=y, t=t, r=r, valid=valid, valid_ho=valid, w=w,
                order=np.linspace(-1, 1, t.size), prev_index=np.arange(t.size) - 1,
                light=np.ones(t.size, bool), full_scale=4095.0, frame_gap=1.0)
    assert evaluate(st, [], data, n_pix, t.size).n_params == 2 * n_pix + 2


def test_a_clean_leaky_sensor_is_not_a_linear_one_with_a_readout_compression():
    """The false alarms of the evaluation: a leaky sensor whose pixels share most of their
    leakage shape, on a mixed design. Per-pixel leakage pays two parameters a pixel more than
    a linear response with a shared compression; the shared-shape leakage model does not, and
    nothing is selected (dev seeds 102 and 170 of the generator)."""
    for seed in (102, 170):
        r = ev.run_case(seed)
        assert r["truth"]["kind"] == "clean" and r["case"]["leaky"]
        assert r["found"]["selected"] == [] and not r["found"]["unexplained"], r["found"]
        assert r["found"]["base"].startswith("leakage")


def test_a_full_well_that_clips_below_the_adc_full_scale_is_left_out():
    from hsiffc.diagnose.design import clip_level, subset

    sw = simulated_sweep("exposure", seed=4, shape=(16, 16), n_steps=20, leak_rate_dn_per_ms=1e-9)
    assert clip_level(sw) is None  # a smooth top: no clip
    top = float(np.floor(np.percentile(sw.data[np.asarray(sw.kind) == "light"], 85)))
    clipped = replace(sw, data=np.minimum(sw.data, top).astype(sw.data.dtype))
    assert clip_level(subset(clipped, 256, 0)[0]) == top - 1
    out = diagnose(clipped)
    assert any("clip at" in n for n in out["design"]["notes"]), out["design"]
    assert out["selected_effects"] == [], out["candidates"]
    assert not out["unexplained"]
    # dynamic saturation of a leaky pixel is no clip
    leaky = simulated_sweep("exposure", seed=4, shape=(16, 16), n_steps=20)
    assert clip_level(leaky) is None


@pytest.mark.parametrize("name", ["emva1288-refsim-linear12-exposure",
                                  "emva1288-refsim-linear10-light"])
def test_linear_reference_simulations_stay_linear(name, shared_set):
    """The EMVA 1288 reference implementation's linear sets: a linear base, nothing selected
    (the 12-bit set's full well clips at about 4001 DN, below the ADC's 4095)."""
    from hsiffc.io import read_sweep

    out = diagnose(read_sweep(shared_set(name)))
    assert out["base_model"].startswith("linear"), out["leakage"]
    assert out["selected_effects"] == [] and not out["unexplained"], out["candidates"]
    _honest(out)


def test_pixels_x_steps_pattern_against_what_the_fit_itself_leaves():
    """The leading singular value of the residual finds a gain step on every other group of
    four columns from the middle of the acquisition (column bins of eight columns and step
    means both average it out); per-pixel parameter errors leave such a pattern too, and
    against the reference of another draw of them nothing is found."""
    from hsiffc.diagnose.structure import LOW_RANK, groupings, low_rank, structure

    rng = np.random.default_rng(5)
    p, s = 1024, 40
    valid = np.ones((p, s), bool)
    sd = np.full(s, 2.0)
    cols = np.arange(p) % 64
    jump = np.where((cols // 4) % 2 == 1, 1.0, -1.0)[:, None] * (np.arange(s) >= s // 2)
    res = sd * rng.standard_normal((p, s)) + 1.0 * jump  # RMS 0.35 of the noise
    groups = groupings(valid, np.tile(np.linspace(10, 900, s), (p, 1)), np.ones(s, bool),
                       np.arange(p) // 64, cols, np.zeros(p, int))
    findings, flag = structure(res, valid, groups, 2.0, sd=sd)
    by = {f["grouping"]: f for f in findings}
    assert flag and by[LOW_RANK]["significant"]
    assert not any(f["significant"] for g, f in by.items() if g != LOW_RANK)
    assert by[LOW_RANK]["structured_rms_dn"] == pytest.approx(np.sqrt(0.5), rel=0.25)

    def fit_errors():  # per-pixel gain errors times the signal over the steps
        return (sd * rng.standard_normal((p, s))
                + 2.0 * rng.standard_normal((p, 1)) * np.linspace(0.1, 1.0, s)[None, :])
    alone = low_rank(fit_errors(), valid, sd)
    assert alone["p_value"] < 1e-6  # a pattern, but the fit's own
    ref = low_rank(fit_errors(), valid, sd)["chi2"]
    against = low_rank(fit_errors(), valid, sd, null_chi2=ref)
    assert against["p_value"] > 1e-6 and against["structured_rms_dn"] < 0.2 * 2.0


def test_a_lag_absorbed_by_a_nuisance_is_still_unexplained():
    """Dev seed 202: image lag over several steps on a linear sensor's light sweep. A per-step
    offset drift absorbs most of it, the binned tests see nothing, the pixels x steps pattern
    of the residual does."""
    r = ev.run_case(202)
    assert r["truth"]["kind"] == "outside" and r["truth"]["effects"][0]["name"] == "slow_lag"
    assert r["found"]["unexplained"] and r["right"], r["found"]


def test_the_rounding_of_a_quiet_integer_sensor_is_in_the_null():
    """Dev seed 56: a clean 8-bit leaky sensor with 0.03 DN of read noise. Its frames round
    to codes the pixels of a step share; the null simulates the ADC's rounding, so that is not
    reported as structure."""
    from hsiffc.diagnose.design import noise_before_rounding

    v = np.array([0.0, 0.05, 1 / 12, 0.3, 50.0])
    s2 = noise_before_rounding(v)
    assert np.all(np.diff(s2) > 0) and s2[0] == 0 and s2[-1] == pytest.approx(50 - 1 / 12)
    assert np.array_equal(noise_before_rounding(v, quantum=0.0), v)
    r = ev.run_case(56)
    assert r["truth"]["kind"] == "clean" and r["case"]["bit_depth"] == 8
    assert not r["found"]["unexplained"] and r["found"]["selected"] == [], r["found"]


def test_frames_at_the_adc_lowest_code_are_clipped_samples():
    """A frame at 0 DN has its noise cut off below: the step mean is biased upward. Diagnose
    leaves such samples out as it does those at full scale (integer data); the calibration's
    sampling keeps them unless asked (``floor_dn``)."""
    from hsiffc.calibrate.samples import collect_samples

    sw = simulated_sweep("exposure", seed=4, shape=(8, 8), n_steps=6, leak_rate_dn_per_ms=1e-9)
    data = sw.data.copy()
    data[0, 2, 3] = 0
    low = replace(sw, data=data)
    step0 = list(low.steps()).index(low.step[0])
    plain = collect_samples(low).clipped
    assert not plain[step0, 2 * 8 + 3]
    got = collect_samples(low, floor_dn=0.0)
    assert got.clipped[step0, 2 * 8 + 3] and got.clipped.sum() == plain.sum() + 1
    # dev seed 270: a 16-bit sensor with an offset drift 100x its detection limit, whose
    # darks drift below 0 DN; before, the clipped darks brought two effects beside it
    r = ev.run_case(270)
    assert r["truth"]["effects"][0]["name"] == "offset_drift" and r["right"], r["found"]


def test_the_search_starts_from_the_base_that_predicts_the_held_out_data():
    """Dev seed 300: a linear sensor whose per-pixel leakage model follows the fit half's noise
    (held-out RMS 4.75 DN against 4.52 with one leakage shape); started from it, a
    frame_light_change made up part of the difference. Dev seed 296: an exposure offset on a
    leaky sensor, found only with per-pixel leakage, so the search from that model is kept."""
    for seed, name in ((300, "dark_current"), (296, "exposure_offset")):
        r = ev.run_case(seed)
        assert r["truth"]["effects"][0]["name"] == name and r["right"], (seed, r["found"])


def test_a_within_step_effect_must_be_shown_by_the_frame_differences():
    """Dev seed 160: a clean 16-bit leaky sensor. frame_light_change lowered the held-out error
    by 9.5 paired standard errors, from a coefficient that is noise times a misfit of the base;
    the frame differences show it at less than 5 standard errors, so it is not taken."""
    r = ev.run_case(160)
    assert r["truth"]["kind"] == "clean"
    assert r["found"]["selected"] == [] and not r["found"]["unexplained"], r["found"]


def test_the_noise_floor_leaves_out_a_selected_within_step_effect():
    """Dev seed 864: an 8-bit light sweep with a light that changes between the frames of a
    step and a readout compression. The noise is measured on the frame differences, which hold
    the light change too: once ``frame_light_change`` is selected, the floor is measured on
    the differences less what it predicts. With the inflated floor the compression was taken
    for noise and the verdict was 'unexplained' beside 0 DN of systematic error.

    The same sweep has the backward step drop a per-step effect standing in for a smooth one:
    the forward search adds ``illumination_error`` after the compression (its small factors
    pass the trend test while the compression is there); next to it the compression looks
    unneeded, but without the compression its factors follow the signal, so it is the one
    dropped."""
    sw, truth = ev.build_case(ev.case_spec(864))
    assert {e["name"] for e in truth["effects"]} == {"frame_light_change",
                                                     "readout_nonlinearity"}
    out = diagnose(sw, max_pixels=ev.MAX_PIXELS, seed=864)
    assert set(out["selected_effects"]) == {"frame_light_change", "readout_nonlinearity"}
    # round three: with the floor measured on the cleared frame differences (lower than the
    # raw ones), a grouping of the residual now shows structure above 0.2 x that floor, so the
    # verdict is 'unexplained' and both effects are labelled stand-ins (a change of verdict on
    # this development seed, not yet understood; round two said 'nothing unexplained')
    if out["unexplained"]:
        assert set(out["stand_ins"]) == set(out["selected_effects"]), out["effects"]
    # the frame differences fail the test against the noise model (issue 53): the floor is
    # measured on them cleared of what follows the signal across the pixels, below the raw
    # differences by more than the fit noise can explain, and selecting the light change no
    # longer moves it (it was 0.9 x or less of the raw floor before the test)
    test = out["noise_test"]
    assert test["within_step"] and test["clean_dn"] < 0.9 * test["raw_dn"], test
    assert out["after"]["noise_floor_dn"] == pytest.approx(out["noise_floor_dn"], rel=0.1)
    _honest(out)
    # round two's forward search added illumination_error here, which the backward step then
    # dropped as a stand-in for the compression; with the floor of the cleared differences
    # the forward search no longer adds it, so no backward step is needed
    assert "illumination_error" not in out["selected_effects"], out["candidates"]


def test_a_sensor_wide_effect_beats_a_per_step_stand_in():
    """Dev seed 570: an exposure offset (5x its detection limit) on an 8-bit leaky sensor, mixed
    design, no darks. With one leakage shape for the sensor, the quick trial fit found half the
    offset and a held-out error worse than without it; ``illumination_error`` (a factor
    ``1 + t0 / t`` a step) won the round. Fitted to convergence, the offset predicts the
    held-out data as well with one parameter: it is chosen, and the tie is reported."""
    sw, truth = ev.build_case(ev.case_spec(570))
    assert [e["name"] for e in truth["effects"]] == ["exposure_offset"]
    out = diagnose(sw, max_pixels=ev.MAX_PIXELS, seed=570)
    assert out["selected_effects"] == ["exposure_offset"], out["selected_effects"]
    t0 = out["effects"][0]["params"]["t0_ms"]
    assert t0 == pytest.approx(truth["effects"][0]["size"], rel=0.15)
    rivals = [c for c in out["candidates"] if "rival" in c.get("fit", "")]
    assert any(c["name"] == "exposure_offset" and c["selected_in_round"] for c in rivals)
    assert any(set(a["effects"]) == {"exposure_offset", "illumination_error"}
               for a in out["ambiguous"]), out["ambiguous"]
    _honest(out)


def test_a_linear_model_that_predicts_better_is_kept_whatever_the_bic():
    """Dev seed 846: a per-pixel quadratic nonlinearity (5x) on a linear 14-bit sensor. A
    linear response with ``pixel_nonlinearity`` predicts the held-out data 8 standard errors
    better than the leakage model with one shape for the sensor, which has the lower BIC (two
    parameters a pixel against three); the leakage model was kept as 'cannot tell'."""
    r = ev.run_case(846)
    assert r["truth"]["effects"][0]["name"] == "pixel_nonlinearity"
    assert r["found"]["selected"] == ["pixel_nonlinearity"] and r["right"], r["found"]


def test_step_factors_of_a_drift_or_a_lag_over_several_steps_are_a_trend():
    """The trend test looks at the factors times the signal in acquisition order (dev seed
    1066: an offset drift at 5x on a mixed design, whose factors look random) and at the signal
    of the steps before (dev seed 982: an image lag decaying over several steps, outside the
    library, which ``illumination_error`` absorbed)."""
    r = ev.run_case(1066)
    assert r["truth"]["effects"][0]["name"] == "offset_drift" and r["right"], r["found"]
    r = ev.run_case(982)
    assert r["truth"]["effects"][0]["name"] == "slow_lag"
    assert "illumination_error" not in r["found"]["selected"] and r["right"], r["found"]
