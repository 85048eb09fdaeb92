"""Fixed-pattern non-uniformity (EMVA 1288 way): known patterns under temporal noise."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.flatfield.two_point import (
    fixed_pattern_nonuniformity,
    fixed_pattern_variance,
    uniformity,
    uniformity_before_after,
)
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create


def _stack(rng, gain_sigma, noise_dn, n_frames, shape=(128, 128), level=200.0):
    pattern = level * (1.0 + gain_sigma * rng.standard_normal(shape))
    return pattern, pattern + noise_dn * rng.standard_normal((n_frames,) + shape)


@pytest.mark.parametrize("n_frames", [2, 3, 10])
def test_fixed_pattern_is_recovered_under_larger_temporal_noise(n_frames):
    rng = np.random.default_rng(n_frames)
    pattern, stack = _stack(rng, 0.005, 4.0, n_frames)  # 1 DN fixed, 4 DN temporal
    fpn, tvar, mean = fixed_pattern_variance(stack)
    true_fpn = pattern.var(ddof=1)
    # standard error of the estimate ~ sqrt(2/P) * sigma_t^2 / L: a few percent of 1 DN^2 here
    assert fpn == pytest.approx(true_fpn, abs=0.12)
    assert np.sqrt(tvar) == pytest.approx(4.0, rel=0.02)
    assert mean == pytest.approx(200.0, rel=1e-3)
    r = fixed_pattern_nonuniformity(stack)
    assert r.fpn_percent[0] == pytest.approx(100 * pattern.std() / pattern.mean(), rel=0.1)
    # eq. (6) on single frames is dominated by the temporal noise: ~ sqrt(1 + 16) x larger
    assert r.eq6_percent[0] > 3.5 * r.fpn_percent[0]
    assert r.eq6_percent[0] == pytest.approx(uniformity(stack[0]), rel=0.05)


def test_two_frames_equal_the_spatial_covariance():
    rng = np.random.default_rng(3)
    _, stack = _stack(rng, 0.01, 2.0, 2, shape=(50, 60))
    fpn, _, _ = fixed_pattern_variance(stack)
    x1, x2 = stack.reshape(2, -1)
    assert fpn == pytest.approx(np.cov(x1, x2)[0, 1], rel=1e-9)


def test_per_band_with_dark_and_mask():
    rng = np.random.default_rng(4)
    shape = (64, 64)
    band_map = (np.arange(64)[:, None] % 2) * 2 + (np.arange(64)[None, :] % 2)
    levels = np.array([50.0, 100.0, 200.0, 400.0])
    sigmas = np.array([0.02, 0.01, 0.005, 0.0025])
    dark = 30.0 + rng.standard_normal(shape)
    pattern = levels[band_map] * (1 + sigmas[band_map] * rng.standard_normal(shape))
    stack = dark + pattern + 1.5 * rng.standard_normal((4,) + shape)
    mask = np.ones(shape, bool)
    stack[:, 5, 5] = 4000.0  # a hot pixel: masked out
    mask[5, 5] = False
    r = fixed_pattern_nonuniformity(stack, band_map, dark=dark, mask=mask)
    np.testing.assert_allclose(r.mean_dn, levels, rtol=0.01)
    np.testing.assert_allclose(r.fpn_percent, 100 * sigmas, rtol=0.2)
    assert r.n_pixels.sum() == 64 * 64 - 1
    assert r.n_frames == 4
    d = r.to_dict()
    assert d["pooled_fpn_percent"] == pytest.approx(np.sqrt(np.mean(r.fpn_percent ** 2)))
    # without the mask the hot pixel dominates band 1's pattern
    r_hot = fixed_pattern_nonuniformity(stack, band_map, dark=dark)
    assert r_hot.fpn_percent[band_map[5, 5]] > 5 * r.fpn_percent[band_map[5, 5]]


def test_one_frame_is_refused():
    with pytest.raises(ValueError, match="at least 2 frames"):
        fixed_pattern_variance(np.zeros((1, 4, 4)))


@pytest.mark.filterwarnings(  # band 1 of its flat is 8 % of the range: the fit's check says so
    "ignore::hsiffc.stages.refchecks.FlatTooDarkWarning")
def test_before_after_two_point_on_simulated_flat():
    sensor = MosaicSensor.default((64, 64), seed=5, dsnu_dn=0.5)
    light = PAPER_LIGHT_W_M2["fig5"]
    flat = sensor.capture(40.0, "lamp B", irradiance_w_m2=light, n_frames=100).to_frames()
    darks = sensor.capture(40.0, None, n_frames=100).to_frames()
    test = sensor.capture(40.0, "lamp B", irradiance_w_m2=light, n_frames=2).to_frames()
    pipe = Pipeline([("dark", create("dark")),
                     ("ffc", create("two_point_ffc", exposure_ms=40.0,
                                    normalisation="mean_gain"))]).fit(flat + darks)
    dark = np.mean(np.stack([f.data for f in darks]), axis=0)
    r = uniformity_before_after(test, pipe, dark=dark)
    # the sensor's PRNU is 1 %; the 100-frame flat leaves its temporal noise / 10 (~0.3 %)
    assert r["before"].pooled_fpn_percent == pytest.approx(1.0, abs=0.2)
    assert r["after"].pooled_fpn_percent < 0.6
    assert r["improvement_percent_points"] > 0.4


def test_standard_error_matches_the_spread_over_repeats():
    rng = np.random.default_rng(8)
    pattern = 100.0 * (1 + 0.004 * rng.standard_normal((64, 64)))
    results = [fixed_pattern_nonuniformity(pattern + 2.0 * rng.standard_normal((2, 64, 64)))
               for _ in range(60)]
    pct = np.array([r.fpn_percent[0] for r in results])
    se = np.median([r.fpn_se_percent[0] for r in results])
    assert pct.std() == pytest.approx(se, rel=0.3)


@pytest.mark.parametrize("shape", [(6, 8), (272, 256)])  # serial and parallel band sums
def test_uniformity_per_band_equals_the_per_band_numpy_definition(shape):
    """uniformity_per_band (two compiled band-sum passes) gives eq. (6) of each band as
    100 np.std / np.mean over its good, finite pixels: NaN and inf left out, flagged pixels
    left out, NaN for a band with fewer than two usable pixels; on a mosaic map (summed by
    row phase) and on a plain array."""
    from hsiffc.flatfield.two_point import uniformity_per_band
    from hsiffc.data.mosaic import Mosaic

    rng = np.random.default_rng(11)
    img = rng.normal(300.0, 25.0, shape).astype(np.float32)
    img[1, 2] = np.nan
    img[2, 3] = np.inf
    dq = (rng.random(shape) < 0.1).astype(np.uint32)
    mosaic_map = Mosaic.rectangular(2, 4).band_map(shape)
    plain_map = np.array(mosaic_map)  # same values, not registered as a mosaic map
    plain_map[plain_map == 5] = 9  # bands 5-8 empty, band 9 holds band 5's pixels
    for bm in (mosaic_map, plain_map):
        for flags in (None, dq):
            got = uniformity_per_band(img, bm, dq=flags)
            assert got.shape == (int(bm.max()) + 1,)
            for band in range(got.size):
                use = (bm == band) & np.isfinite(img)
                if flags is not None:
                    use &= flags == 0
                v = img[use].astype(np.float64)
                if v.size < 2:
                    assert np.isnan(got[band])
                else:
                    assert got[band] == pytest.approx(100.0 * v.std() / v.mean(), rel=1e-12)
    one = np.zeros(shape, np.int64)
    one[0, 0] = 1  # band 1 has a single pixel: no spread to speak of
    assert np.isnan(uniformity_per_band(img, one)[1])
