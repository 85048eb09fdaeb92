"""Two-point FFC (eq. 5) and the uniformity metric (eq. 6)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.data.dq import DQ
from hsiffc.flatfield.two_point import (
    two_point_correct,
    two_point_gain,
    uniformity,
    uniformity_per_band,
)


def test_uniformity_is_std_over_mean_in_percent():
    img = np.array([9.0, 11.0, 9.0, 11.0])
    assert uniformity(img) == pytest.approx(10.0)
    assert np.isnan(uniformity(np.array([5.0])))
    assert uniformity(np.array([1.0, np.nan, 3.0])) == pytest.approx(50.0)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(1e-3, 1e3), seed=st.integers(0, 1000))
def test_uniformity_is_scale_invariant(scale, seed):
    img = np.random.default_rng(seed).uniform(50, 150, size=(16, 16))
    assert uniformity(img * scale) == pytest.approx(uniformity(img), rel=1e-9)


def test_two_point_removes_gain_and_offset_exactly():
    rng = np.random.default_rng(0)
    gain = rng.uniform(0.8, 1.2, (32, 32))
    offset = rng.uniform(20, 40, (32, 32))
    scene = 100.0
    dark, flat = offset, offset + gain * 500
    test = offset + gain * scene
    out, dq = two_point_correct(test, dark, flat)
    assert np.all(dq == 0)
    assert uniformity(out) < 1e-4
    # eq. (5): Avg(L3) * (R3 - R1) / (R2 - R1), here Avg(L3) * 100 / 500 everywhere
    assert np.allclose(out, test.mean() * scene / 500, rtol=1e-6)
    mg, _ = two_point_correct(test, dark, flat, normalisation="mean_gain")
    assert np.allclose(mg, scene * gain.mean(), rtol=1e-6)  # DN at the mean gain


def test_per_band_normalisation_keeps_each_band_level():
    band_map = np.indices((8, 8)).sum(axis=0) % 2
    flat = np.where(band_map == 0, 300.0, 600.0)
    test = np.where(band_map == 0, 100.0, 400.0)
    out, _ = two_point_correct(test, np.zeros((8, 8)), flat, band_map=band_map,
                               normalisation="mean_gain")
    assert np.allclose(out[band_map == 0], 100.0) and np.allclose(out[band_map == 1], 400.0)
    paper, _ = two_point_correct(test, np.zeros((8, 8)), flat, band_map=band_map)
    assert np.allclose(paper[band_map == 0], 100 * 100 / 300)  # Avg(L3) of band 0 times ratio
    u = uniformity_per_band(out, band_map)
    assert u.shape == (2,) and np.all(u < 1e-9)


def test_bad_flat_pixels_are_flagged_not_deleted():
    dark = np.full((4, 4), 30.0)
    flat = np.full((4, 4), 530.0)
    flat[0, 0] = 30.0  # no signal
    flat[1, 1] = np.nan
    gain, dq = two_point_gain(dark, flat)
    assert gain[0, 0] == 1.0 and gain[1, 1] == 1.0
    assert dq[0, 0] & DQ.NO_FLAT and dq[1, 1] & DQ.NO_FLAT
    out, dq2 = two_point_correct(np.full((4, 4), 130.0), dark, flat)
    assert np.all(np.isfinite(out)) and (dq2 != 0).sum() == 2


def test_shape_and_option_errors():
    with pytest.raises(ValueError, match="same shape"):
        two_point_correct(np.zeros((2, 2)), np.zeros((2, 3)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="normalisation"):
        two_point_correct(np.ones((2, 2)), np.zeros((2, 2)), np.ones((2, 2)), normalisation="x")


def test_uniformity_improvement_between_two_stages():
    from hsiffc.flatfield.two_point import uniformity_improvement

    rng = np.random.default_rng(1)
    band_map = np.indices((16, 16)).sum(axis=0) % 2
    gain = rng.uniform(0.9, 1.1, (16, 16))
    before = 100 * gain
    after, _ = two_point_correct(before, np.zeros((16, 16)), 500 * gain, band_map=band_map)
    r = uniformity_improvement(before, after, band_map)
    assert len(r["improvement"]) == 2
    assert all(i > 4 for i in r["improvement"]) and all(a < 1e-4 for a in r["after"])
