"""Model-based flat-field correction (model_ffc) on simulated truth: the calibration's
fixed-pattern floor, the flat stack, spectral fidelity into leakage; the stage in pipelines,
TOML and files; flags and finiteness."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.leakage import model
from hsiffc.spectral.bandstats import band_reduce
from hsiffc.calibrate import calibrate
from hsiffc.data.dq import DQ
from hsiffc.flatfield.floor import parameter_covariance, sweep_floor
from hsiffc.data.frame import Frame
from hsiffc.flatfield.model_based import correction_uncertainty, model_ffc_apply
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create

LIGHT = PAPER_LIGHT_W_M2["training"]
FLAT_MS = 8.0
SWEEP_MS = np.tile(np.geomspace(0.5, 150, 20), 3)
SWEEP_LEVELS = np.repeat([0.5, 1.0, 1.6], 20)
SWEEP_FRAMES = 4


@pytest.fixture(scope="module")
def sim():
    """A leaking 10-bit sensor calibrated from a 3-light-level sweep, a 50-frame flat stack at
    8 ms (about 24 % of full scale, no leakage) with darks, and both corrections fitted."""
    sensor = MosaicSensor.default((32, 64), seed=3)
    sweep = sensor.sweep_varying_light(SWEEP_MS, SWEEP_LEVELS, "lamp A", irradiance_w_m2=LIGHT,
                                       n_frames=SWEEP_FRAMES, seed=1)
    cal = calibrate(sweep)
    flat = sensor.capture(FLAT_MS, "lamp A", irradiance_w_m2=LIGHT, n_frames=50,
                          seed=2).to_frames()
    darks = sensor.capture(FLAT_MS, None, n_frames=50, seed=3).to_frames()
    mffc = Pipeline([("ffc", create("model_ffc", calibration=cal))]).fit(
        Frame.list_from_sweep(sweep) + flat + darks)
    two_point = Pipeline([("dark", create("dark", calibration=cal)),
                          ("ffc", create("two_point_ffc", exposure_ms=FLAT_MS,
                                         normalisation="mean_gain", average="mean"))]
                         ).fit(flat + darks)
    return sensor, cal, mffc, two_point


def _noise_free(sensor, truth, t):
    """The noise-free response as a frame: what is left after correcting it is fixed pattern."""
    return Frame.from_raw(np.minimum(truth.expected_dn(t), 2 ** 10 - 1), exposure_ms=t,
                          bit_depth=10, mosaic=sensor.mosaic)


def _spread_percent(x, band_map, good):
    mean = band_reduce(x, band_map, good)
    return 100 * np.sqrt(band_reduce((x / mean[band_map] - 1) ** 2, band_map, good))


def _sweep_covariance(sensor, cal):
    """Cramer-Rao covariance of the calibration's parameters from the fixture's sweep design
    (every light step followed by a dark step) and the simulated sensor's noise."""
    p = sensor.params
    return parameter_covariance(
        np.repeat(SWEEP_MS, 2), np.stack([SWEEP_LEVELS, 0 * SWEEP_LEVELS], axis=1).ravel(),
        cal["responsivity"], cal.a, cal.b, cal.dark, cal["dark_current_dn_per_ms"],
        n_frames=SWEEP_FRAMES, read_noise_dn=p.read_noise_dn,
        conversion_gain_dn_per_e=p.conversion_gain_dn_per_e, full_scale_dn=p.full_scale_dn,
        full_well_dn=p.full_well_e * p.conversion_gain_dn_per_e)


def test_reaches_the_calibration_floor_where_two_point_does_not(sim):
    """The floor: where the response is (nearly) linear (model alpha up to the stage's
    ``flat_alpha_percent``, 5 %), the error of the factor combined from the sweep and the flat
    stack plus the dark's (:func:`correction_uncertainty`); above it the sweep fit's
    Cramer-Rao bound with the full covariance of g, a, b and the dark
    (:mod:`hsiffc.flatfield.floor`), which the calibration's per-parameter sigmas cannot give (ln a
    and ln b errors are correlated at about -0.998). Measured: model_ffc at 0.81-1.03 times
    the first (0.12-0.20 %) and 0.95-1.11 times the second (0.15-0.34 % at alpha 5.5-50 %;
    two-point 0.31-0.82 % there), from 5 % of full scale up."""
    sensor, cal, mffc, two_point = sim
    stage = mffc.named_steps["ffc"]
    truth = sensor.truth(sensor.light_rate(sensor.illumination("lamp A", LIGHT)))
    bm = sensor.band_map
    cov = _sweep_covariance(sensor, cal)
    checked_high = 0
    # from 5 % of full scale to beyond alpha 50 % in the brightest bands
    for t in (1.7, 4.0, 8.0, 16.0, 20.0, 24.0, 28.0, 30.0, 32.0):
        frame = _noise_free(sensor, truth, t)
        m, tp = mffc.transform(frame), two_point.transform(frame)
        at_sweep = sweep_floor(frame.data, t, cov, cal.a, cal.b, cal.dark,
                               cal["dark_current_dn_per_ms"])
        good = (m.dq == 0) & (tp.dq == 0) & np.isfinite(at_sweep)
        alpha = band_reduce(model.leakage_percentage(
            truth.expected_dn(t), truth.k_total_dn_per_ms, truth.a_dn_per_ms, truth.b_per_dn),
            bm, statistic="median")
        linear_floor = 100 * np.sqrt(band_reduce(correction_uncertainty(
            frame.data, t, cal.a, cal.b, cal.dark, stage.sigma_ln_gain_,
            sigma_dark_dn=cal["sigma_dark_dn"]) ** 2, bm, good))
        bent_floor = 100 * np.sqrt(band_reduce(at_sweep ** 2, bm, good))
        floor = np.where(alpha <= stage.flat_alpha_percent, linear_floor, bent_floor)
        fpn_m, fpn_tp = _spread_percent(m.data, bm, good), _spread_percent(tp.data, bm, good)
        signal = band_reduce(frame.data - sensor.dark_dn, bm)
        use = (signal >= 0.05 * 1023) & (alpha <= 50.0)
        assert use.any()
        # model_ffc reaches the floor the calibration's noise sets, at every level
        assert np.all(fpn_m[use] <= 1.2 * floor[use]), (t, alpha, fpn_m, floor)
        # and the floor is not loose: above the flats' share it is met, not beaten
        bent = use & (alpha >= 10.0)
        assert np.all(fpn_m[bent] >= 0.85 * bent_floor[bent]), (t, fpn_m, bent_floor)
        # two-point carries its flat's noise everywhere and the leakage bend above it
        assert np.all(fpn_tp[use] >= 1.4 * fpn_m[use]), (t, fpn_tp, fpn_m)
        assert np.all(fpn_tp[bent] >= 1.6 * fpn_m[bent]), (t, fpn_tp, fpn_m)
        checked_high += int(bent.sum())
    assert checked_high >= 8  # bands between alpha 10 % and 50 % were tested
    # the stated floor: factor error from the sweep and the flat stack, combined
    u = stage.uncertainty_["bands"]
    sweep_median = np.median([b["sigma_sweep_median_percent"] for b in u])
    assert 100 * np.median(stage.sigma_ln_gain_) < 0.9 * sweep_median
    assert all(0.05 < b["sigma_combined_rms_percent"] < 0.25 for b in u)
    assert 0.2 < float(np.median(stage.flat_weight_)) < 0.9


def test_spectral_fidelity_into_leakage(sim):
    sensor, _, mffc, two_point = sim
    wl = sensor.bands.wavelengths_nm
    reflectance = 0.35 + 0.5 * np.exp(-((wl - 650.0) / 120.0) ** 2)
    k = sensor.light_rate(sensor.illumination("lamp A", LIGHT), reflectance=reflectance)
    truth = sensor.truth(k)
    bm = sensor.band_map
    true_spectrum = band_reduce(k / sensor.gain, bm)  # band light rates without the pattern

    def angle_deg(u):
        cos = np.dot(u, true_spectrum) / np.linalg.norm(u) / np.linalg.norm(true_spectrum)
        return float(np.degrees(np.arccos(min(cos, 1.0))))

    worst_alpha, angles_m, angles_tp = 0.0, [], []
    for t in (4.0, 8.0, 16.0, 24.0, 30.0, 36.0, 40.0):
        alpha = band_reduce(model.leakage_percentage(
            truth.expected_dn(t), truth.k_total_dn_per_ms, truth.a_dn_per_ms, truth.b_per_dn),
            bm, statistic="median")
        if alpha.max() > 55.0:
            break
        worst_alpha = alpha.max()
        frame = _noise_free(sensor, truth, t)
        angles_m.append(angle_deg(band_reduce(mffc.transform(frame).data, bm) / t))
        angles_tp.append(angle_deg(band_reduce(two_point.transform(frame).data, bm) / t))
    assert worst_alpha > 40.0  # the brightest band reached alpha ~50 %
    # model_ffc keeps the band ratios (< 0.05 degrees) from unsaturated to alpha ~50 %;
    # two-point bends the brightest bands (over 1 degree at alpha ~50 %)
    assert max(angles_m) < 0.05, angles_m
    assert angles_tp[-1] > 1.0 and angles_tp[-1] > 20 * angles_m[-1], (angles_tp, angles_m)


def test_flags_and_never_nan(sim):
    sensor, cal, mffc, _ = sim
    shape = sensor.shape
    clipped = Frame.from_raw(np.full(shape, 1023), exposure_ms=20.0, bit_depth=10,
                             mosaic=sensor.mosaic)
    out = mffc.transform(clipped)
    assert np.isfinite(out.data).all()
    assert ((out.dq & int(DQ.SATURATED)) != 0).all()
    below = Frame.from_raw(np.zeros(shape), exposure_ms=20.0, bit_depth=10,
                           mosaic=sensor.mosaic)
    out = mffc.transform(below)
    assert np.isfinite(out.data).all() and (out.data < 0).all()
    assert ((out.dq & int(DQ.BELOW_DARK)) != 0).mean() > 0.99
    zero_t = Frame.from_raw(np.asarray(cal.dark), exposure_ms=0.0, bit_depth=10,
                            mosaic=sensor.mosaic)
    out = mffc.transform(zero_t)
    assert np.isfinite(out.data).all() and np.abs(out.data).max() < 1e-3
    # deep in saturation: flagged LEAKAGE, value kept finite
    y = np.asarray(cal["saturation_ref_dn"], float) - 1.0
    data, dq, alpha = model_ffc_apply(y, 200.0, cal.a, cal.b, cal.dark, np.ones(shape))
    assert np.isfinite(data).all() and ((dq & int(DQ.LEAKAGE)) != 0).mean() > 0.5
    assert np.all(alpha[(dq & int(DQ.LEAKAGE)) != 0] > 50.0)


def test_after_a_dark_stage_and_through_files(sim, tmp_path):
    sensor, cal, mffc, _ = sim
    cal_path = tmp_path / "cal.npz"
    cal.save(cal_path)
    flat = sensor.capture(FLAT_MS, "lamp A", irradiance_w_m2=LIGHT, n_frames=12,
                          seed=5).to_frames()
    darks = [f for t in (FLAT_MS, 16.0)
             for f in sensor.capture(t, None, n_frames=12, seed=6).to_frames()]
    toml = tmp_path / "p.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n\n[[step]]\nname = "ffc"\n'
                    'stage = "model_ffc"\ncalibration = "cal.npz"\nmin_flat_frames = 10\n')
    pipe = Pipeline.from_toml(toml).fit(flat + darks)
    test = sensor.capture(16.0, "lamp A", irradiance_w_m2=LIGHT, n_frames=1,
                          seed=7).to_frames()[0]
    out = pipe.transform(test)
    assert out.dark_removed is not None and out.corrected_by == "model_ffc"
    # the dark stage's master dark is the start level: same result as giving that dark
    stage = pipe.named_steps["ffc"]
    master = pipe.named_steps["dark"].dark_for(16.0, test.data.shape)[0]
    ref, _, _ = model_ffc_apply(test.data, 16.0, cal.a, cal.b, master, stage.gain_,
                                gain_sweep=stage.gain_sweep_, full_scale_dn=1023)
    np.testing.assert_allclose(out.data, ref, rtol=1e-6, atol=1e-4)
    assert stage.uncertainty_["n_flat_stacks"] == 1
    saved = pipe.save(tmp_path / "p.npz")
    again = Pipeline.load(saved).transform(test)
    np.testing.assert_array_equal(again.data, out.data)
    np.testing.assert_array_equal(again.dq, out.dq)


def test_bad_parameters_fail_at_fit(sim):
    from hsiffc.errors import ParameterError

    _, cal, _, _ = sim
    with pytest.raises(ParameterError, match="alpha_limit_percent"):
        create("model_ffc", calibration=cal, alpha_limit_percent=-1).fit([])
    with pytest.raises(ParameterError, match="calibration"):
        create("model_ffc").fit([])
