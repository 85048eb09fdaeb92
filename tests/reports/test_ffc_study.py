"""The held-out FFC study on the real EMVA 1288 CMOS sweep, and the ``uniformity`` and
``study-ffc`` commands."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hsiffc.calibrate import calibrate
from hsiffc.cli import main
from hsiffc.data.sweep import Sweep
from hsiffc.io import read_sweep
from hsiffc.reports.ffc_study import render_markdown, run_ffc_study


@pytest.fixture(scope="module")
def study(emva_dir):
    return run_ffc_study(emva_dir)


def test_model_ffc_beats_two_point_on_the_real_sweep(study):
    # ranges in fractions of saturation (242 DN above dark: the brightest step with at most
    # 1 % of its pixels at 255)
    assert 230 < study.saturation["signal_dn"] < 250
    rows = {row["range_fraction"][0]: row["methods"] for row in study.summary}
    assert set(rows) == {0.02, 0.12, 0.40, 0.80}
    for lo, m in rows.items():
        model = m["model_ffc"]["fpn_percent_median"]
        best = min(("two_point_2frame", "two_point_stack"),
                   key=lambda k: m[k]["fpn_percent_median"])
        best_two_point = m[best]["fpn_percent_median"]
        # at or below the best two-point, beyond twice the standard error of the difference
        # (at 2-12 % the model and the 100-frame stack measured 0.550 and 0.550 %)
        se = np.hypot(m["model_ffc"]["fpn_se_percent_median"], m[best]["fpn_se_percent_median"])
        assert model <= best_two_point + 2 * se, (lo, m)
        if lo >= 0.12:
            assert model <= 0.3, (lo, model)
        # a 2-frame flat prints its temporal noise into every frame: worse than raw
        assert m["two_point_2frame"]["fpn_percent_median"] > m["raw"]["fpn_percent_median"]
        # from the calibration alone (hsiffc correct's default; the calibration carries the
        # flat stack): better than raw and than a 2-frame flat everywhere, within 0.3 % from
        # 12 % of saturation (measured 0.55 / 0.18 / 0.17 / 0.29 %, two-point from the
        # 100-frame stack 0.55 / 0.19 / 0.16 / 0.43 %)
        alone = m["model_ffc_calibration"]["fpn_percent_median"]
        assert alone < m["raw"]["fpn_percent_median"], (lo, m)
        assert alone < m["two_point_2frame"]["fpn_percent_median"], (lo, m)
        if lo >= 0.12:
            assert alone <= 0.3, (lo, alone)
    # the model keeps the top of the range flat where the flat's gain no longer fits
    # (measured 0.29 against 0.43 %; 0.24 before the dark was taken from the dark frames and
    # each pixel's leakage had to be earned: the rule's 0.3 % still holds)
    for name in ("model_ffc", "model_ffc_calibration"):
        assert rows[0.80][name]["fpn_percent_median"] < 0.7 * rows[0.80][
            "two_point_stack"]["fpn_percent_median"]
    assert study.goals["failures"] == [] and study.goals["unresolved"] == []
    assert all(v for v in study.goals.values() if isinstance(v, bool))
    assert study.flat_stack["n_frames"] == 100
    # the 2-frame flat near half saturation
    assert 0.4 < study.flat_2frame["signal_dn"] / study.saturation["signal_dn"] < 0.6


def test_study_states_the_uncertainty_and_the_worst_step(study):
    u = study.uncertainty["bands"][0]
    assert 0 < u["sigma_combined_rms_percent"] < u["sigma_sweep_median_percent"]
    assert u["flat0_sigma_median_percent"] > 0
    assert study.worst["signal_dn"] >= 29 and study.worst["fpn_percent"] > 0
    page = render_markdown(study)
    assert "| 12-40 % (29-96 DN) |" in page and "Worst model_ffc step" in page
    assert "combined (inverse variance)" in page


def test_uniformity_command_on_sample_cubes(sample_cubes, tmp_path, capsys):
    sweep = sample_cubes / "sweep_2900K.tif"
    cal = tmp_path / "cal.npz"
    calibrate(read_sweep(sweep)).save(cal)
    out = tmp_path / "u.json"
    assert main(["uniformity", str(sweep), "--calibration", str(cal), "--json", str(out),
                 "--plot", str(tmp_path / "u.png")]) == 0
    doc = json.loads(out.read_text())
    assert set(doc) == {"steps", "summary"}
    step = doc["steps"][0]
    assert {"step", "exposure_ms", "signal_dn", "clipped_fraction", "flagged_fraction", "raw",
            "corrected"} <= set(step)
    assert set(step["raw"]) == {"eq6_percent", "fpn_percent", "fpn_se_percent",
                                "fpn_var_rel", "below_noise"}
    assert set(step["corrected"]) == {"model_ffc"}
    unclipped = [s for s in doc["steps"] if s["clipped_fraction"] < 0.01
                 and (s["signal_dn"] or 0) > 30]
    assert unclipped
    # the calibration's own sweep: the correction removes the simulated 1 % pattern
    def values(get):  # JSON null: no usable pixel in that step
        return np.array([np.nan if get(s) is None else get(s) for s in unclipped], float)

    raw = np.nanmedian(values(lambda s: s["raw"]["fpn_percent"]))
    corrected = np.nanmedian(values(lambda s: s["corrected"]["model_ffc"]["fpn_percent"]))
    assert raw > 0.7 and corrected < 0.5 * raw
    assert (tmp_path / "u.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "fixed-pattern non-uniformity" in printed
    # ranges in fractions of saturation: this leaky 10-bit sweep levels off near 870 DN above
    # dark, below 1023 DN; saturation is the brightest step before its response grows at less
    # than half its linear slope (about 740 DN), not the plateau
    top = doc["summary"][-1]
    assert top["range_fraction"] == [0.8, 1.0] and top["n_steps"] > 0
    assert 650 < top["signal_range_dn"][1] < 850 and "percent of saturation" in printed
    assert "(80-100 %)" in printed


def test_a_pattern_below_the_resolution_is_printed_as_a_bound(sample_cubes, tmp_path, capsys):
    # on the calibration's own sweep model_ffc leaves less fixed pattern than two frames of
    # 12 288 pixels can measure: the median is 0 %, which the table printed as "0.00%"
    sweep = sample_cubes / "sweep_2900K.tif"
    cal = tmp_path / "cal.npz"
    calibrate(read_sweep(sweep)).save(cal)
    assert main(["uniformity", str(sweep), "--calibration", str(cal), "--json",
                 str(tmp_path / "u.json")]) == 0
    printed = capsys.readouterr().out
    doc = json.loads((tmp_path / "u.json").read_text())
    bounded = [r["methods"]["model_ffc"] for r in doc["summary"] if "model_ffc" in r["methods"]
               and r["methods"]["model_ffc"]["fpn_percent_median"] == 0.0]
    assert bounded and all(m["fpn_se_percent_median"] > 0 for m in bounded)
    assert f"< {2 * bounded[0]['fpn_se_percent_median']:.2f}%" in printed
    assert "0.00%" not in printed and "below what the frames can resolve" in printed
    raw = doc["steps"][0]["raw"]
    assert 0 < raw["fpn_se_percent"] < raw["fpn_percent"]  # the raw 1 % pattern is resolved


def test_summarise_range_without_any_figure():
    from hsiffc.reports.sweep_uniformity import StepUniformity, summarise
    from hsiffc.flatfield.uniformity import FixedPattern

    fields = FixedPattern.__dataclass_fields__
    nan_pattern = FixedPattern(**{k: np.array([np.nan]) for k in fields})
    step = StepUniformity(step=3, exposure_ms=1.0, signal_dn=50.0, clipped_fraction=0.0,
                          flagged_fraction=1.0, raw=nan_pattern)
    row = summarise([step], (), ranges=((5.0, 100.0),))[0]
    assert row["n_steps"] == 1
    assert np.isnan(row["methods"]["raw"]["fpn_percent_median"])
    assert row["methods"]["raw"]["worst_step"] is None


def test_uniformity_command_without_multi_frame_steps(tmp_path, capsys):
    from hsiffc.io.tiff import write_sweep
    from hsiffc.data.sweep import Sweep

    path = tmp_path / "one.tif"
    write_sweep(path, Sweep(np.full((2, 8, 8), 100, np.uint16), [1.0, 2.0],
                                 ["light", "light"], 10))
    assert main(["uniformity", str(path), "--json", str(tmp_path / "u.json")]) == 2
    assert "two or more frames" in capsys.readouterr().err


def test_study_command_names_a_missing_folder(tmp_path, capsys):
    assert main(["study-ffc", str(tmp_path / "out"), "--emva", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err


def test_uniformity_with_darks_at_one_exposure(sample_cubes, tmp_path, capsys):
    # the dark stage fitted with match="scale" needs darks at two exposures: with one it
    # raised a plain ValueError ("internal error", exit 3)
    from hsiffc.io.tiff import write_sweep

    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    darks = np.flatnonzero(sweep.is_dark)
    one = sweep.exposure_ms[darks[0]]
    keep = sweep.is_light | (sweep.is_dark & (sweep.exposure_ms == one))
    assert (sweep.is_dark & ~keep).any()  # the sample has darks at several exposures
    path = tmp_path / "one_dark.tif"
    write_sweep(path, sweep.select(keep))
    out = tmp_path / "u.json"
    assert main(["uniformity", str(path), "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"dark frames at one exposure only ({one:g} ms)" in err
    assert json.loads(out.read_text())["steps"]
    cal = tmp_path / "cal.npz"
    calibrate(sweep).save(cal)  # with a calibration: its dark at every exposure, no warning
    assert main(["uniformity", str(path), "--calibration", str(cal), "--json",
                 str(tmp_path / "u2.json")]) == 0
    assert "one exposure only" not in capsys.readouterr().err


def _levelling(u):
    """A response of slope 1 up to 120 DN that levels off at 200 DN (slope e^{-(u - 120) / 80}
    beyond)."""
    u = np.asarray(u, float)
    return np.where(u < 120.0, u, 200.0 - 80.0 * np.exp(-(u - 120.0) / 80.0))


def _levelling_sweep(*, leaky: bool):
    """An 8-bit exposure sweep of 16 x 16 px at one light, 24 light steps of 2 frames with a
    dark step each: linear (0.35 DN per unit of dose u), or linear up to 120 DN above the dark
    and levelling off at 200 DN beyond (:func:`_levelling`)."""
    rng = np.random.default_rng(7)
    u = np.linspace(10.0, 600.0, 24)  # DN of light a linear pixel would collect
    gain = 1.0 + 0.01 * rng.standard_normal((16, 16))
    frames, exposure, kind, step = [], [], [], []
    for i, ui in enumerate(u):
        signal = _levelling(ui * gain) if leaky else 0.35 * ui * gain
        for k, level in (("light", signal), ("dark", 0.0)):
            for _ in range(2):
                frames.append(np.clip(np.round(10.0 + level + rng.normal(0, 0.5, (16, 16))),
                                      0, 255))
                exposure.append(float(ui))
                kind.append(k)
                step.append(2 * i + (k == "dark"))
    return Sweep(np.asarray(frames, np.uint16), np.asarray(exposure), np.asarray(kind), 8,
                 step=np.asarray(step)), u


def test_saturation_is_where_a_levelling_response_stops_measuring_the_light():
    # the summary's ranges end where the mean response grows at less than half its linear
    # slope (model alpha 50 %, where model_ffc flags a pixel LEAKAGE): beyond that dose the
    # steps' signal is the spread of the pixels' saturation levels, not a measure of the light
    from hsiffc.reports.ffc_study import SATURATION_ALPHA_PERCENT, saturation_level

    sweep, u = _levelling_sweep(leaky=True)
    light = [int(s) for s in sweep.steps() if s % 2 == 0]
    sat = saturation_level(sweep, light, lambda t: np.full(sweep.frame_shape, 10.0))
    assert sat["reached"]
    # the brightest step before the first whose rise from the previous one is below half the
    # linear slope
    rise = np.diff(_levelling(u)) / np.diff(u)
    first = 1 + int(np.argmax(rise < 1.0 - SATURATION_ALPHA_PERCENT / 100.0))
    assert sat["signal_dn"] == pytest.approx(float(_levelling(u[first - 1])), abs=1.0)
    assert sat["signal_dn"] < 0.9 * 200.0  # not the plateau
    # a linear response keeps its brightest step below clipping
    sweep, u = _levelling_sweep(leaky=False)
    sat = saturation_level(sweep, light, lambda t: np.full(sweep.frame_shape, 10.0))
    assert not sat["reached"]
    assert sat["signal_dn"] == pytest.approx(0.35 * u[-1], rel=0.01)
