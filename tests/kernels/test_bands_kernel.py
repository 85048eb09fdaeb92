"""band_reduce's mean (the compiled per-band sums of hsiffc.kernels.bands) against numpy's
bincount over the usable pixels (the former implementation, re-derived here)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.spectral.bandstats import band_reduce
from hsiffc.kernels import launch


def bincount_mean(values, band_map, good, n):
    v = np.asarray(values, np.float64)
    use = np.isfinite(v) & (np.ones(v.shape, bool) if good is None else good)
    sums = np.bincount(band_map[use], weights=v[use], minlength=n)[:n]
    counts = np.bincount(band_map[use], minlength=n)[:n]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


@pytest.mark.parametrize("shape", [(7, 5), (300, 400), (1, launch.PARALLEL_MIN + 3)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_band_mean_equals_bincount(shape, dtype):
    rng = np.random.default_rng(0)
    values = (rng.uniform(0, 1000, shape)).astype(dtype)
    if dtype != np.uint16:
        values[0, 0] = np.nan
        values[-1, -1] = np.inf
    bm = rng.integers(0, 6, shape)
    good = rng.random(shape) > 0.2
    got = band_reduce(values, bm, good, n_bands=7)
    ref = bincount_mean(values, bm, good, 7)
    assert np.isnan(got[6]) and np.isnan(ref[6])
    assert np.allclose(got, ref, rtol=1e-12, equal_nan=True)
    assert np.allclose(band_reduce(values, bm), bincount_mean(values, bm, None, 6), rtol=1e-12)


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 90), w=st.integers(1, 90), n=st.integers(1, 5), seed=st.integers(0, 99))
def test_band_mean_any_layout(h, w, n, seed):
    rng = np.random.default_rng(seed)
    values = rng.normal(0, 10, (h, w))
    bm = rng.integers(0, n, (h, w))
    good = rng.random((h, w)) > 0.5
    assert np.allclose(band_reduce(values, bm, good, n_bands=n),
                       bincount_mean(values, bm, good, n), rtol=1e-12, equal_nan=True)
    assert np.allclose(band_reduce(values.ravel(), bm.ravel(), good.ravel(), n_bands=n),
                       bincount_mean(values, bm, good, n), rtol=1e-12, equal_nan=True)


@pytest.mark.parametrize("n", [1000, launch.PARALLEL_MIN + 7])
def test_two_point_apply_equals_the_numpy_product(n):
    from hsiffc.flatfield.two_point import two_point_apply

    rng = np.random.default_rng(1)
    signal = rng.normal(300, 50, n).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, n).astype(np.float32)
    scale = rng.uniform(0.9, 1.1, n).astype(np.float32)
    ref = np.multiply(signal, gain, dtype=np.float32) * scale  # the former two passes
    for s in (scale, np.float32(1.5), 1.0):
        out = two_point_apply(signal, gain, s)
        expect = np.multiply(signal, gain, dtype=np.float32) * np.float32(s)
        assert out.dtype == np.float32 and np.allclose(out, expect, rtol=3e-7, atol=0)
    assert np.allclose(two_point_apply(signal, gain, scale), ref, rtol=3e-7, atol=0)


@pytest.mark.parametrize("shape", [(30, 40), (272, 256)])
def test_per_band_scale_equals_the_per_pixel_map(shape):
    """The stage's path (a factor per band, looked up in the kernel; on the larger frame, a
    mosaic map, by row phase: each column's factor per phase row) gives the same array as
    the per-pixel map of paper_scale, bit for bit; bad band maps are refused."""
    from hsiffc.flatfield.two_point import paper_ratio, paper_scale, two_point_apply
    from hsiffc.data.mosaic import Mosaic

    rng = np.random.default_rng(2)
    bm = Mosaic.rectangular(2, 4).band_map(shape)
    raw = rng.normal(400, 60, shape).astype(np.float32)
    signal = (raw - 30).astype(np.float32)
    gain = rng.uniform(0.8, 1.2, shape).astype(np.float32)
    good = rng.random(shape) > 0.05
    flat_mean = rng.uniform(200, 300, 8)
    flat_mean[3] = np.nan  # an undefined band keeps the neutral factor 1
    ratio = paper_ratio(raw, flat_mean, band_map=bm, good=good)
    per_pixel = paper_scale(raw, flat_mean, band_map=bm, good=good)
    assert ratio.shape == (8,) and ratio[3] == 1.0
    assert np.array_equal(per_pixel, ratio[bm])
    out = two_point_apply(signal, gain, ratio, band_map=bm)
    assert np.array_equal(out, two_point_apply(signal, gain, per_pixel))
    with pytest.raises(ValueError, match="outside"):
        two_point_apply(signal, gain, ratio[:4], band_map=bm)
    with pytest.raises(ValueError, match="same shape"):
        two_point_apply(signal, gain, ratio, band_map=bm[:, :-1])


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 200), w=st.integers(1, 70), rows=st.integers(1, 6),
       cols=st.integers(1, 6), off=st.tuples(st.integers(0, 7), st.integers(0, 7)),
       masked=st.booleans(), seed=st.integers(0, 99))
def test_mosaic_band_mean_by_row_phase(h, w, rows, cols, off, masked, seed):
    """A mosaic's band map is summed by row phase (hsiffc.data.mosaic.row_period); the result is
    the same as bincount's over the usable pixels, for any tile, offset and frame height
    (blocks of 64 rows that do not start on a tile row included)."""
    from hsiffc.data.mosaic import Mosaic, row_period

    rng = np.random.default_rng(seed)
    pattern = rng.permutation(rows * cols).reshape(rows, cols)
    bm = Mosaic(pattern, offset=off).band_map((h, w))
    assert row_period(bm) == rows and row_period(np.array(bm)) == 0
    values = rng.normal(100, 10, (h, w)).astype(np.float32)
    values.flat[rng.integers(0, h * w, 3)] = [np.nan, np.inf, -np.inf]
    good = rng.random((h, w)) > 0.3 if masked else None
    n = rows * cols + 1  # one band more than the map holds: NaN
    got = band_reduce(values, bm, good, n_bands=n)
    assert np.allclose(got, bincount_mean(values, bm, good, n), rtol=1e-12, equal_nan=True)
    assert np.isnan(got[-1])
    m = int(np.array(bm).max()) + 1  # the default length: from the map's first rows
    assert np.allclose(band_reduce(values, bm, good), got[:m], rtol=0, equal_nan=True)
