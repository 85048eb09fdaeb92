"""The mosaic-sensor simulator: physics, noise, fixed pattern, reproducibility, paper defaults."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.leakage import model
from hsiffc.data.mosaic import Mosaic
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor, SensorParams
from hsiffc.spectral import imec_4x4_visible, imec_5x5_nir, read_imec_xml

TRAIN = PAPER_LIGHT_W_M2["training"]
FIG5 = PAPER_LIGHT_W_M2["fig5"]


def test_reproducible_from_seed_and_different_across_seeds():
    a = MosaicSensor((16, 24), seed=5).capture(10.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=2)
    b = MosaicSensor((16, 24), seed=5).capture(10.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=2)
    c = MosaicSensor((16, 24), seed=6).capture(10.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=2)
    assert np.array_equal(a.frames, b.frames)
    assert not np.array_equal(a.frames, c.frames)
    # an explicit capture seed fixes the temporal noise, the sensor seed the fixed pattern
    s = MosaicSensor((16, 24), seed=5)
    x = s.capture(10.0, "lamp A", irradiance_w_m2=TRAIN, seed=9).frames
    y = s.capture(10.0, "lamp A", irradiance_w_m2=TRAIN, seed=9).frames
    assert np.array_equal(x, y)


def test_capture_returns_raw_integers_and_truth():
    s = MosaicSensor((32, 40), seed=1)
    cap = s.capture(20.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=3)
    assert cap.frames.shape == (3, 32, 40) and cap.frames.dtype == np.uint16
    assert cap.frames.max() <= 1023
    t = cap.truth
    for arr in (t.k_dn_per_ms, t.a_dn_per_ms, t.b_per_dn, t.dark_dn):
        assert arr.shape == (32, 40) and np.all(np.isfinite(arr))
    assert np.array_equal(t.band, s.mosaic.band_map((32, 40)))
    assert cap.illumination.startswith("lamp A") or "2900" in cap.illumination


def test_mean_response_follows_the_leakage_model_not_a_clipped_line():
    # a low light and long exposures: the mean of many frames sits on the model curve, which
    # levels off far below full scale
    s = MosaicSensor((24, 24), seed=2)
    for t in (50.0, 400.0, 1500.0):
        cap = s.capture(t, "lamp B", irradiance_w_m2=FIG5, n_frames=40, seed=int(t))
        mean = cap.frames.mean(axis=0)
        expected = cap.truth.expected_dn(t)
        # unbiased, and scattered by exactly the shot + read noise of a 40-frame mean
        g = s.params.conversion_gain_dn_per_e
        sigma = np.sqrt((g * (expected - cap.truth.dark_dn) + s.params.read_noise_dn ** 2
                         + 1 / 12) / 40)
        z = (mean - expected) / sigma
        assert abs(z.mean()) < 0.2 and z.std() == pytest.approx(1.0, abs=0.12)
        if t == 1500.0:
            sat = model.dynamic_saturation_level(cap.truth.k_total_dn_per_ms,
                                                 cap.truth.a_dn_per_ms, cap.truth.b_per_dn)
            assert np.all(mean < 1000) and np.allclose(mean, sat, atol=6)


def test_temporal_noise_is_shot_plus_read_noise():
    p = SensorParams(prnu=0.0, dsnu_dn=0.0, leak_rate_dn_per_ms=1e-12)  # no leakage
    s = MosaicSensor((64, 64), params=p, seed=3)
    cap = s.capture(10.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=60, seed=4)
    sig = cap.frames.astype(float)
    band0 = cap.truth.band == 0
    mean = sig.mean(axis=0)[band0].mean() - p.dark_level_dn
    var = sig.var(axis=0, ddof=1)[band0].mean()
    expected = p.conversion_gain_dn_per_e * mean + p.read_noise_dn ** 2 + 1 / 12
    assert var == pytest.approx(expected, rel=0.05)


def test_dark_frames_have_dsnu_and_no_light():
    s = MosaicSensor((64, 64), seed=4)
    dark = s.capture(10.0, None, n_frames=20)
    m = dark.frames.mean(axis=0)
    assert m.mean() == pytest.approx(s.params.dark_level_dn, abs=0.5)
    assert m.std() == pytest.approx(s.params.dsnu_dn, rel=0.15)
    assert np.all(dark.truth.k_dn_per_ms == 0)


def test_full_well_and_full_scale_clip():
    p = SensorParams(leak_rate_dn_per_ms=1e-12, full_well_e=5000.0)
    s = MosaicSensor((16, 16), params=p, seed=5)
    cap = s.capture(1000.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=2)
    fw_dn = s.dark_dn + p.full_well_e * p.conversion_gain_dn_per_e
    assert np.all(cap.expected_dn <= fw_dn + 1e-9)
    assert np.all(cap.frames.mean(axis=0) <= fw_dn + 6 * p.read_noise_dn)
    p2 = SensorParams(leak_rate_dn_per_ms=1e-12)
    cap2 = MosaicSensor((16, 16), params=p2, seed=5).capture(1000.0, "lamp A",
                                                              irradiance_w_m2=TRAIN)
    assert cap2.frames.max() == 1023


def test_hot_and_dead_pixels():
    p = SensorParams(hot_fraction=0.02, dead_fraction=0.02)
    s = MosaicSensor((64, 64), params=p, seed=6)
    assert 0.01 < s.hot.mean() < 0.03 and 0.01 < s.dead.mean() < 0.03
    dark = s.capture(200.0, None, n_frames=4).frames.mean(axis=0)
    assert dark[s.hot].mean() > dark[~s.hot].mean() + 100
    light = s.capture(20.0, "lamp A", irradiance_w_m2=TRAIN, n_frames=4).frames.mean(axis=0)
    assert np.all(light[s.dead] < s.dark_dn[s.dead] + 10)


def test_vignetting_and_reflectance():
    s = MosaicSensor.default((64, 64), seed=7, prnu=0.0)
    flat = s.light_rate("lamp A", irradiance_w_m2=TRAIN)
    vig = s.light_rate("lamp A", irradiance_w_m2=TRAIN, vignetting=0.3)
    ratio = vig / flat
    assert ratio[32, 32] == pytest.approx(1.0, abs=0.01)
    assert ratio[0, 0] == pytest.approx(0.7, abs=0.03)
    half = s.light_rate("lamp A", irradiance_w_m2=TRAIN, reflectance=np.full(601, 0.5))
    assert np.allclose(half, 0.5 * flat)
    labels = np.zeros((64, 64), int)
    labels[:, 32:] = 1
    spectra = np.stack([np.full(601, 0.2), np.full(601, 0.8)])
    k = s.light_rate("lamp A", irradiance_w_m2=TRAIN, reflectance=(labels, spectra))
    assert np.allclose(k[:, :32], 0.2 * flat[:, :32]) and np.allclose(k[:, 32:], 0.8 * flat[:, 32:])


def test_warmer_lamp_shifts_light_to_the_red_bands():
    s = MosaicSensor.default((16, 16), seed=8, prnu=0.0)
    ka = s.light_rate("2900K", irradiance_w_m2=1.0)
    kb = s.light_rate("2200K", irradiance_w_m2=1.0)
    bm = s.band_map
    ratio = [np.mean(kb[bm == i] / ka[bm == i]) for i in range(8)]
    assert np.all(np.diff(ratio) > 0)  # 470 nm ... 890 nm: 2200 K is relatively redder


@pytest.mark.parametrize("n,bands", [(4, imec_4x4_visible), (5, imec_5x5_nir)])
def test_square_mosaics(n, bands):
    b = bands()
    s = MosaicSensor((20, 30), mosaic=Mosaic.square(n, b.centres_nm), bands=b, seed=1)
    cap = s.capture(5.0, "D65", irradiance_w_m2=TRAIN)
    assert cap.frames.shape == (1, 20, 30)
    assert set(np.unique(cap.truth.band)) == set(range(n * n))


def test_sensor_from_the_real_imec_calibration(imec_xml):
    cal = read_imec_xml(imec_xml)
    s = MosaicSensor((40, 50), mosaic=cal.mosaic(), bands=cal.bands, seed=2)
    k = s.light_rate("lamp A", irradiance_w_m2=TRAIN)
    assert k.shape == (40, 50) and np.all(k > 0)
    assert s.band_map[3, 0] == 0  # filter area starts at row 3


def test_mismatched_mosaic_and_bands_is_a_clear_error():
    with pytest.raises(ValueError, match="one band response per mosaic band"):
        MosaicSensor((8, 8), mosaic=Mosaic.square(4), seed=0)


def test_named_lamp_needs_an_irradiance():
    with pytest.raises(ValueError, match="irradiance_w_m2"):
        MosaicSensor((8, 8)).capture(1.0, "lamp A")


def test_default_sensor_is_consistent_with_the_paper():
    s = MosaicSensor((64, 64), seed=0)
    assert s.params.bit_depth == 10
    bm = s.band_map
    # Fig. 5: k ~ 2 DN/ms under lamp B, dynamic saturation ~ 800 DN, leakage ~ 2 DN/ms there
    k = s.light_rate("lamp B", irradiance_w_m2=FIG5)
    assert np.median(k[bm == 0]) == pytest.approx(2.0, rel=0.02)
    sat = model.dynamic_saturation_level(k, s.a_dn_per_ms, s.b_per_dn)
    assert np.median(sat[bm == 0]) == pytest.approx(800, abs=25)
    # Table I: alpha grows over 6.45-32.25 ms under the training light from ~0.01 % to tens of %
    k = s.light_rate("lamp A", irradiance_w_m2=TRAIN)
    ts = np.array([6.45, 12.9, 19.35, 25.8, 32.25])
    for band in range(3):
        m = bm == band
        alpha = [np.median(model.leakage_percentage_paper(
            model.response(t, k[m], s.a_dn_per_ms[m], s.b_per_dn[m], s.dark_dn[m]), t,
            s.a_dn_per_ms[m], s.b_per_dn[m], s.dark_dn[m])) for t in ts]
        assert np.all(np.diff(alpha) > 0)
        assert alpha[0] < 0.1 and 0.2 < alpha[2] < 3 and 20 < alpha[4] < 90


def test_sweep_has_light_and_dark_steps_in_order():
    s = MosaicSensor((8, 8), seed=0)
    sw = s.sweep([1.0, 2.0], "lamp A", irradiance_w_m2=TRAIN, n_frames=2)
    assert sw.kind.tolist() == ["light"] * 2 + ["dark"] * 2 + ["light"] * 2 + ["dark"] * 2
    assert sw.exposure_ms.tolist() == [1.0] * 4 + [2.0] * 4
    assert len(sw.steps()) == 4 and sw.bit_depth == 10 and sw.mosaic == s.mosaic
