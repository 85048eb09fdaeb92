"""Issue 50: every per-pixel parameter earned from the data, each band's model chosen by
held-out prediction, on sensors whose physics the leakage model leaves out.

The sensors come from :mod:`hsiffc.reports.indep_sensors` (numpy only, not hsiffc's simulator):
the two designs of the sensors the issue measured (a 12-bit CCD with an exposure offset; a
12-bit light sweep with a common readout nonlinearity), each before the fix (the per-pixel
leakage model with the dark as each pixel's intercept, what ``hsiffc calibrate`` did) and after
it (the default). The evaluation half of the independent sensors runs behind ``-m slow``; the
shared sets are in tests/reports/test_ffc_zoo.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.calibrate import calibrate
from hsiffc.calibrate.choice import CANDIDATES, CODES
from hsiffc.cli import main
from hsiffc.diagnose.simulated import write_emva1288
from hsiffc.reports import indep_sensors
from hsiffc.reports.ffc_study import run_ffc_study

#: what hsiffc calibrate did before issue 50: dark = each pixel's intercept, no offset, per-pixel
#: leakage wherever the fit converged
BEFORE = {"dark_from": "fit", "exposure_offset_ms": 0.0, "choose": False}


def _design(name):
    return indep_sensors.indep_sweep(indep_sensors.DESIGN_CASES[name])


@pytest.fixture(scope="module")
def ccd():
    return _design("ccd12-exposure-offset")


def _split(sweep):
    light = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    stacks = sweep.select(np.isin(sweep.step, sweep.meta["spatial_steps"]))
    return light, stacks


def _figures(res):
    return [(r["range_fraction"], {m: v["fpn_percent_median"] for m, v in r["methods"].items()})
            for r in res.summary]


def test_ccd_with_an_exposure_offset_broken_before_and_met_after(ccd):
    before = run_ffc_study(ccd, calibrate_kwargs=BEFORE)
    assert before.goals["failures"], _figures(before)  # the failure, reproduced
    after = run_ffc_study(ccd)
    assert after.goals["failures"] == [], _figures(after)
    low = after.summary[0]["methods"]
    assert low["model_ffc"]["fpn_percent_median"] < low["raw"]["fpn_percent_median"]


def test_common_nonlinearity_light_sweep_met_after():
    res = run_ffc_study(_design("refsim12-light-nonlinear"))
    assert res.goals["failures"] == [], _figures(res)


def test_dark_from_the_dark_frames_and_the_offset_measured(ccd):
    light, stacks = _split(ccd)
    case = indep_sensors.DESIGN_CASES["ccd12-exposure-offset"]
    cal = calibrate(light, flats=stacks)
    darks = light.data[light.kind == "dark"].astype(float).mean(axis=0)
    # the dark is each pixel's dark frames' (their mean), not its light response's intercept
    assert np.median(np.abs(cal.dark - darks)) < 0.05
    old = calibrate(light, **BEFORE)
    assert np.std(old.dark - darks) > 5 * np.std(cal.dark - darks)
    t0 = cal.fitted_on["exposure_offset_ms"]
    assert t0 == pytest.approx(case.exposure_offset_ms, rel=0.1)
    # the dark's stated error is the dark frames' (2 x 40 frames of 3 DN read noise)
    assert np.median(cal["sigma_dark_dn"]) == pytest.approx(3.0 / np.sqrt(80), rel=0.25)


def test_the_choice_is_recorded_and_printed(ccd):
    light, stacks = _split(ccd)
    cal = calibrate(light, flats=stacks)
    choice = cal.fitted_on["model_choice"]
    assert choice["candidates"] == list(CANDIDATES)
    (band,) = choice["bands"]
    assert band["kept"] in ("two_point_stack", "linear")  # nothing here bends per pixel
    assert set(band["held_out_fpn_percent"]) == set(CANDIDATES)
    assert not set(choice["fit_steps"]) & set(choice["held_out_steps"])
    assert (cal["model_kept"] == CODES[band["kept"]]).all()
    assert (cal.a == 0).all()  # no pixel inverted through a leakage it did not earn
    text = cal.summary()
    assert f"band 1: {band['kept']}" in text and "exposure offset" in text
    assert "dark level from dark frames" in text


def test_a_leaky_sensor_keeps_the_per_pixel_leakage(sample_cubes):
    from hsiffc.io import read_sweep

    cal = calibrate(read_sweep(sample_cubes / "sweep_2900K.tif"))
    bands = cal.fitted_on["model_choice"]["bands"]
    assert {b["kept"] for b in bands} == {"pixel_leakage"}
    for b in bands:  # by far, on held-out steps
        err = b["held_out_fpn_percent"]
        assert err["pixel_leakage"] < 0.7 * err["linear"]


def test_cli_calibrate_summary_says_per_band_which_model_was_kept(ccd, tmp_path, capsys):
    path = write_emva1288(ccd, tmp_path / "ccd")  # an EMVA 1288 folder: sweep + stacks
    rc = main(["calibrate", str(path), "-o", str(tmp_path / "cal.npz"), "--json",
               str(tmp_path / "cal.json")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "model kept per band, by held-out fixed-pattern non-uniformity" in out
    assert "band 1: " in out and "two_point_stack" in out


@pytest.mark.parametrize("seed", indep_sensors.INDEP_DEV_SEEDS[:2])
def test_rule_on_independent_sensors_of_the_development_half(seed):
    case = indep_sensors.indep_case(seed, shape=(48, 64))
    res = run_ffc_study(indep_sensors.indep_sweep(case))
    assert res.goals["failures"] == [], (case.label, _figures(res))


@pytest.mark.slow
@pytest.mark.parametrize("seed", indep_sensors.INDEP_EVAL_SEEDS)
def test_rule_on_independent_sensors_of_the_evaluation_half(seed):
    case = indep_sensors.indep_case(seed)
    res = run_ffc_study(indep_sensors.indep_sweep(case))
    assert res.goals["failures"] == [], (case.label, _figures(res))
