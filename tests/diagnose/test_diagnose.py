"""Diagnosis on data with an undeclared effect: the right effect is found at 2x, 10x and 100x
its detection limit and the systematic error falls to the noise; clean data of every sweep
design raise no alarm; what a design cannot identify is skipped with a reason; an effect
outside the library is reported as unexplained; a readout compression is told from leakage.
And the run on the real EMVA 1288 sweep."""

from __future__ import annotations

import json
import math

import pytest

from hsiffc.cli import main
from hsiffc.diagnose import EFFECTS, diagnose
from hsiffc.diagnose.simulated import simulated_sweep, write_emva1288
from hsiffc.diagnose.effects import add_effect
from hsiffc.errors import DataFormatError
from hsiffc.simulate import PAPER_LIGHT_W_M2


@pytest.fixture(scope="module")
def sweeps():
    """EMVA 1288-like sweeps (40 light steps, shuffled exposures 2-200 ms and changing light,
    each followed by a dark step, 2 frames per step, no dark current) and the other designs."""
    return {1: simulated_sweep("mixed", seed=1), 2: simulated_sweep("mixed", seed=2)}


def _no_nan(out):
    for key in ("noise_floor_dn",):
        assert math.isfinite(out[key])
    for part in ("before", "after"):
        assert all(math.isfinite(v) for v in out[part].values())


@pytest.mark.parametrize("seed", [1, 2])
def test_clean_data_select_nothing(sweeps, seed):
    out = diagnose(sweeps[seed])
    assert out["selected_effects"] == [] and not out["unexplained"]
    assert out["before"]["systematic_rms_dn"] < 0.1 * out["noise_floor_dn"]
    assert out["leakage"]["verdict"] == "needed"
    _no_nan(out)


DESIGNS = {
    "exposure sweep": dict(design="exposure"),
    "light sweep at one exposure": dict(design="light"),
    "one frame per step": dict(design="mixed", n_frames=1, n_steps=60),
    "no darks": dict(design="mixed", darks=False),
    "few steps": dict(design="mixed", n_steps=10),
}


@pytest.mark.parametrize("label", list(DESIGNS))
def test_clean_data_on_every_design_select_nothing(label, tmp_path):
    from hsiffc.diagnose.report import write_report

    out = diagnose(simulated_sweep(seed=4, **DESIGNS[label]))
    assert out["selected_effects"] == [], out["candidates"]
    _no_nan(out)
    assert out["before"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    write_report(out, tmp_path)  # every report and plot works on every design
    assert (tmp_path / "residuals.png").stat().st_size > 10_000
    skipped = {s["name"]: s["reason"] for s in out["skipped"]}
    if label == "light sweep at one exposure":
        assert "one exposure" in skipped["exposure_offset"]
        assert "same exposure" in skipped["dark_current"]
    if label == "one frame per step":
        assert "alternate steps" in out["held_out"]
        assert "two frames per step" in skipped["illumination_error"]
        assert "frame_light_change" in skipped


# about the detection limits measured on seeds 1 and 2 (docs/diagnose.md, written by
# python3 docs/gen/diagnose_figures.py); for exposure_offset and image_lag the measured limit
# is twice the value here, so their "2x" case sits at the limit (frame_light_change: measured
# at the value here since round three's fifth pass)
LIMITS = {"exposure_offset": 0.05, "readout_nonlinearity": 20.0, "pixel_nonlinearity": 40.0,
          "offset_drift": 1.0, "illumination_error": 0.004, "image_lag": 0.002,
          "frame_light_change": 0.002}
# multiples that keep the data inside the ADC range (the dark level is 32 DN, full scale 1023)
FACTORS = {"readout_nonlinearity": (2, 10), "pixel_nonlinearity": (2, 5),
           "offset_drift": (2, 10, 25), "frame_light_change": (2, 10, 50)}
CASES = [(n, f) for n in LIMITS for f in FACTORS.get(n, (2, 10, 100))]
#: the default run keeps each effect at its detection limit (2x) and at its largest size; the
#: sizes between (10x, a diagnosis of 6-12 s each) run with ``-m slow``, and the detection
#: curves over every size are measured by ``python3 docs/gen/diagnose_figures.py`` (the page's
#: limits) and the evaluation half (library effects at 5x and more)
BETWEEN = 10


@pytest.mark.parametrize("name,factor", [
    pytest.param(n, f, marks=[pytest.mark.slow] if f == BETWEEN and f < max(
        FACTORS.get(n, (2, 10, 100))) else [], id=f"{n}-{f}x") for n, f in CASES])
def test_each_library_effect_is_found_at_any_size(sweeps, name, factor):
    out = diagnose(add_effect(sweeps[1], name, LIMITS[name] * factor, seed=7))
    assert out["selected_effects"][:1] == [name], out["candidates"]
    assert len(out["selected_effects"]) == 1 or factor > 10
    before, after = out["before"]["systematic_rms_dn"], out["after"]["systematic_rms_dn"]
    noise = out["noise_floor_dn"]
    if name == "pixel_nonlinearity":  # per-pixel parameters leave their own fit noise
        assert after < 0.5 * before
    else:
        assert after < max(0.15 * noise, 0.1 * before)
    chosen = out["effects"][0]
    assert chosen["interpretation"] and chosen["params"]
    _no_nan(out)


@pytest.mark.parametrize("size", [0.04, 0.2, 2.0])  # 2x, 10x, 100x the limit without darks
def test_dark_current_seen_in_the_darks_is_part_of_the_base(sweeps, size):
    # thermally generated charge fills the well like the light's: 2.0 DN/ms is 400 DN at 200 ms
    out = diagnose(add_effect(sweeps[1], "dark_current", size, seed=7, in_well=True))
    assert "dark current" in out["dark_model"]["model"]
    assert out["dark_model"]["median_dark_current_dn_per_ms"] == pytest.approx(size, rel=0.1)
    assert out["selected_effects"] == []
    assert out["before"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    assert any(s["name"] == "dark_current" and "base" in s["reason"] for s in out["skipped"])


def test_warm_sensor_base_fit_does_not_diverge(recwarn):
    sw = simulated_sweep("mixed", seed=3, dark_current_dn_per_ms=2.0)  # dark 400 DN at 200 ms
    out = diagnose(sw)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
    assert out["before"]["systematic_rms_dn"] < 0.2 * out["noise_floor_dn"]
    assert out["selected_effects"] == [] and not out["unexplained"]


@pytest.mark.parametrize("pair", [("image_lag", "offset_drift"),
                                  ("exposure_offset", "offset_drift")])
def test_two_effects_together_are_both_found(sweeps, pair):
    sw = sweeps[2]
    for i, name in enumerate(pair):
        sw = add_effect(sw, name, 5 * LIMITS[name], seed=11 + i)
    out = diagnose(sw)
    assert sorted(out["selected_effects"]) == sorted(pair), out["candidates"]
    assert out["after"]["systematic_rms_dn"] < 0.15 * out["noise_floor_dn"]


def test_injected_parameters_are_recovered(sweeps):
    out = diagnose(add_effect(sweeps[2], "exposure_offset", 0.3, seed=1))
    assert out["effects"][0]["params"]["t0_ms"] == pytest.approx(0.3, rel=0.1)
    out = diagnose(add_effect(sweeps[2], "image_lag", 0.005, seed=1))
    assert out["effects"][0]["params"]["lag"] == pytest.approx(0.005, rel=0.2)


def test_compression_on_a_fixed_exposure_light_sweep_is_not_blamed_on_leakage(tmp_path):
    """EMVA 1288 format written by the simulator: light sweep at 20 ms up to full scale, a
    sensor without leakage and a 3 % compressive readout nonlinearity at full scale."""
    from hsiffc.io import read_sweep

    sw = simulated_sweep("light", seed=3, irradiance=1.5 * PAPER_LIGHT_W_M2["training"],
                         leak_rate_dn_per_ms=1e-6)
    fs = sw.full_scale_dn
    write_emva1288(add_effect(sw, "readout_nonlinearity", -0.03 * fs, seed=1), tmp_path)
    emva = read_sweep(tmp_path)
    assert emva.meta["format"] == "emva1288" and len(set(emva.exposure_ms)) == 1
    out = diagnose(emva)
    assert out["selected_effects"] == ["readout_nonlinearity"], out["candidates"]
    dev = out["effects"][0]["params"]["deviation_at_full_scale_dn"]
    assert dev == pytest.approx(-0.03 * fs, rel=0.15)
    assert out["leakage"]["verdict"] in ("not needed", "cannot tell")
    assert out["base_model"].startswith("linear")
    assert "one light rate" in out["leakage"]["reason"]
    assert out["after"]["systematic_rms_dn"] < 0.15 * out["noise_floor_dn"]


def test_an_effect_outside_the_library_is_reported_unexplained(sweeps):
    out = diagnose(add_effect(sweeps[1], "adc_ripple", 2.0, seed=3))
    assert out["unexplained"]
    assert out["selected_effects"] == []
    assert any(f["significant"] and "signal" in f["grouping"]
               for f in out["residual_structure_after"])


def test_a_design_with_nothing_to_learn_is_refused():
    sw = simulated_sweep("mixed", seed=0, n_steps=3)
    with pytest.raises(DataFormatError, match="at least 4"):
        diagnose(sw)


def test_a_sweep_whose_light_steps_are_all_clipped_is_refused():
    # the darks alone passed the "enough valid samples" check, and diagnose fitted and
    # reported a response on a sweep without one usable light sample
    from dataclasses import replace

    sw = simulated_sweep("mixed", seed=0)
    data = sw.data.copy()
    data[sw.is_light] = sw.full_scale_dn
    with pytest.raises(DataFormatError, match="light samples below full scale"):
        diagnose(replace(sw, data=data))


def test_effect_library():
    assert len(EFFECTS) >= 8
    assert {"readout_nonlinearity", "frame_light_change"} <= set(EFFECTS)
    assert all(e.summary and e.scope in ("global", "pixel", "step", "pair", "frame")
               for e in EFFECTS.values())


def test_cli_json_and_report(sweeps, tmp_path, capsys):
    from dataclasses import replace

    from hsiffc.io import write_sweep

    path = tmp_path / "sweep.tif"
    sw = add_effect(sweeps[1], "offset_drift", 1.5, seed=2)
    write_sweep(path, replace(sw, meta={}))
    assert main(["diagnose", str(path), "--json", str(tmp_path / "d.json"), "--report",
                 str(tmp_path / "rep")]) == 0
    printed = capsys.readouterr().out
    assert "nan" not in printed.lower()
    doc = json.loads((tmp_path / "d.json").read_text())
    for key in ("dataset", "base_model", "n_pixels", "n_samples", "n_invalid_samples",
                "noise_floor_dn", "before", "after", "selected_effects", "candidates",
                "unexplained", "skipped", "dark_model", "leakage", "design"):
        assert key in doc
    assert doc["selected_effects"] == ["offset_drift"]
    assert {"name", "heldout_rms_dn", "criterion", "params"} <= set(doc["candidates"][0])
    assert (tmp_path / "rep" / "report.md").read_text().count("offset_drift") >= 2
    assert (tmp_path / "rep" / "residuals.png").stat().st_size > 10_000
    assert main(["diagnose", "--list-effects"]) == 0
    assert "readout_nonlinearity" in capsys.readouterr().out


@pytest.mark.realdata
def test_real_emva_sweep(emva_dir, tmp_path):
    from hsiffc.diagnose.report import write_report
    from hsiffc.io import read_sweep

    out = diagnose(read_sweep(emva_dir), max_pixels=1024)
    # the base model is close to the noise floor; the second frame of bright steps is darker
    # than the first (0.15 %): the within-step light change is the effect that explains most
    assert out["before"]["systematic_rms_dn"] < 0.3 * out["noise_floor_dn"]
    assert "frame_light_change" in out["selected_effects"], out["candidates"]
    eps = [e for e in out["effects"] if e["name"] == "frame_light_change"][0]["params"]["eps"]
    assert -0.003 < eps < -0.0005
    _no_nan(out)
    write_report(out, tmp_path)
