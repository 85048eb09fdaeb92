"""Issue 50: the correction's predicted fixed-pattern error travels with the output.

The calibration holds each pixel's terms (``sigma_dark_dn``; the model flat's
``sigma_ln_gain_``), the corrected frame flags UNCERTAIN where they predict more than the
stage's limit at the pixel's own corrected signal, and the prediction is checked against the
fixed-pattern non-uniformity measured on steps the calibration did not see.
"""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.calibrate import calibrate
from hsiffc.data.dq import DQ
from hsiffc.data.frame import Frame
from hsiffc.io import read_sweep
from hsiffc.reports import indep_sensors
from hsiffc.stages import create
from hsiffc.stages.defaults import default_pipeline


@pytest.fixture(scope="module")
def leaky(sample_cubes):
    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    return sweep, calibrate(sweep)


def _frame(sweep, i, scale=1.0):
    dark = float(np.median(sweep.data[sweep.is_dark]))
    raw = np.round(dark + (sweep.data[i].astype(np.float64) - dark) * scale)
    return Frame.from_raw(raw.astype(sweep.data.dtype), exposure_ms=float(sweep.exposure_ms[i]),
                          bit_depth=sweep.bit_depth, mosaic=sweep.mosaic)


def test_uncertain_where_the_calibration_predicts_more_than_the_limit(leaky):
    sweep, cal = leaky
    pipe = default_pipeline(cal)
    ffc = pipe.named_steps["ffc"]
    i = int(np.flatnonzero(sweep.is_light)[0])  # the shortest light step: a few DN of signal
    frame = _frame(sweep, i, scale=0.5)
    ffc.uncertain_above_percent = None
    first = pipe.transform(frame)
    sd = np.asarray(cal["sigma_dark_dn"], np.float64)
    pred = np.sqrt(ffc.sigma_ln_gain_.astype(np.float64) ** 2
                   + (sd * ffc.gain_ / first.data.astype(np.float64)) ** 2)
    limit = float(np.nanmedian(pred))  # half the pixels above it
    ffc.uncertain_above_percent = 100 * limit
    out = pipe.transform(frame)
    np.testing.assert_array_equal(out.data, first.data)
    flagged = (out.dq & DQ.UNCERTAIN) != 0
    ok = np.isfinite(pred) & (np.abs(pred / limit - 1) > 1e-4)  # off the float32 rounding edge
    assert 0.3 < flagged[ok].mean() < 0.7
    np.testing.assert_array_equal(flagged[ok], pred[ok] > limit)
    # the value is kept: a flag, not a deletion
    assert np.isfinite(out.data[flagged]).all()


def test_uncertain_off_and_on_a_bright_frame(leaky):
    sweep, cal = leaky
    pipe = default_pipeline(cal)
    i = int(np.flatnonzero(sweep.is_light)[len(np.flatnonzero(sweep.is_light)) // 2])
    bright = pipe.transform(_frame(sweep, i))
    assert not ((bright.dq & DQ.UNCERTAIN) != 0).any()  # 5 % default: nothing at mid-range
    pipe.named_steps["ffc"].uncertain_above_percent = None
    dim = pipe.transform(_frame(sweep, 0 if sweep.is_light[0] else 1, scale=0.01))
    assert not ((dim.dq & DQ.UNCERTAIN) != 0).any()


def test_the_limit_is_a_checked_parameter():
    with pytest.raises(Exception, match="uncertain_above_percent"):
        create("model_ffc", uncertain_above_percent=-1.0).validate_params()


def test_predicted_fixed_pattern_error_agrees_with_held_out_steps():
    """The calibration's own errors predict the fixed pattern the kept model leaves on light
    steps it did not see, on a linear CCD where the kept model is right: the median over the
    held-out steps of their ratio is within a factor 1.5 of 1 (a single step's figure carries
    the sampling error of two frames), and the summary prints it."""
    case = indep_sensors.DESIGN_CASES["ccd12-exposure-offset"]
    sweep = indep_sensors.indep_sweep(case)
    light = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    stacks = sweep.select(np.isin(sweep.step, sweep.meta["spatial_steps"]))
    cal = calibrate(light, flats=stacks)
    choice = cal.fitted_on["model_choice"]
    for band in choice["bands"]:
        assert 1 / 1.5 < band["held_out_over_predicted"] < 1.5, band
    ratio = choice["bands"][0]["held_out_over_predicted"]
    assert f"held-out / predicted {ratio:.2f}" in cal.summary()
