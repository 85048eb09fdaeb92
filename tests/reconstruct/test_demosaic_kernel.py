"""The compiled interpolation kernel (hsiffc.kernels.demosaic, behind hsiffc.reconstruct)
against the former evaluation with OpenCV filters, re-derived here as the reference: normalised
convolution of zero-filled band planes with cv2.sepFilter2D, the wide-tent fallback, the band
median, the DQ rule by dilation of each flag bit, and the alpha cube by dilation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.data.dq import DQ, DQ_DTYPE
from hsiffc.kernels import launch
from hsiffc.kernels import ppi as ppi_kernels
from hsiffc.kernels.demosaic import interpolate_bands
from hsiffc.kernels.lattice import split_lattices
from hsiffc.data.mosaic import Mosaic
from hsiffc.reconstruct import demosaic, ppi_kernel, reconstruct_alpha
from hsiffc.reconstruct.refined import few_level_samples
from hsiffc.reconstruct.prepare import (Prepared, band_levels, periodic_index, prepare,
                                        pseudo_panchromatic)


# -- the reference (OpenCV filters on zero-filled planes) --------------------------------------

def _tent(period, dtype=np.float32):
    d = np.arange(-(period - 1), period, dtype=np.float64)
    return (1.0 - np.abs(d) / period).astype(dtype)


def _filt(img, kx, ky):
    """The separable filter in the image's own precision (float32 or float64)."""
    depth = cv2.CV_64F if img.dtype == np.float64 else cv2.CV_32F
    return cv2.sepFilter2D(img, depth, kx.astype(img.dtype), ky.astype(img.dtype),
                           borderType=cv2.BORDER_CONSTANT)


def _interp(values, w, ph, pw):
    num, den = _filt(values * w, _tent(pw), _tent(ph)), _filt(w, _tent(pw), _tent(ph))
    have1 = den > 1e-6
    est = np.divide(num, den, out=np.zeros_like(num), where=have1)
    num2, den2 = _filt(values * w, _tent(2 * pw), _tent(2 * ph)), _filt(w, _tent(2 * pw),
                                                                         _tent(2 * ph))
    fill = ~have1 & (den2 > 1e-6)
    est[fill] = num2[fill] / den2[fill]
    return est, have1, have1 | fill


def reference(raw, mosaic, dq, method, alpha=None, dtype=np.float32):
    """The cube, its DQ and (with ``alpha``) its alpha; values in ``dtype`` arithmetic."""
    raw = raw.astype(np.float32)
    dq = np.zeros(raw.shape, DQ_DTYPE) if dq is None else dq
    good = dq == 0
    bm = mosaic.band_map(raw.shape)
    ph, pw = mosaic.tile_shape
    if method == "ppid":
        p = Prepared(raw, dq.copy(), mosaic)  # the general (flag-aware) PPI path
        levels = np.ones(mosaic.n_bands) if few_level_samples(p) else band_levels(p)
        ppi, ppi_ok = pseudo_panchromatic(p, levels)
        ppi = ppi.astype(dtype)
    cube = np.empty(raw.shape + (mosaic.n_bands,), dtype)
    cube_dq = np.zeros(cube.shape, DQ_DTYPE)
    values = raw.astype(dtype)
    for b in range(mosaic.n_bands):
        w = ((bm == b) & good).astype(dtype)
        if method == "ppid":
            level = dtype(levels[b])
            diff, have1, have2 = _interp(values - level * ppi, w, ph, pw)
            est = diff + level * ppi
            bil, _, bil2 = _interp(values, w, ph, pw)
            hole = ~ppi_ok & bil2
            est[hole] = bil[hole]
        else:
            est, have1, have2 = _interp(values, w, ph, pw)
        vals = raw[(bm == b) & good]
        est[~have2] = np.median(vals) if vals.size else 0.0
        cube[:, :, b] = est
        own = np.where(bm == b, dq, 0).astype(DQ_DTYPE)
        out = own.copy()
        box = np.ones((2 * ph - 1, 2 * pw - 1), np.uint8)
        for bit in range(32):
            plane = ((own >> bit) & 1).astype(np.uint8)
            if plane.any():
                reach = cv2.dilate(plane, box, borderType=cv2.BORDER_CONSTANT, borderValue=0)
                out[~have1 & (reach > 0)] |= DQ_DTYPE(1 << bit)
        out[~have2] |= DQ_DTYPE(DQ.DO_NOT_USE)
        cube_dq[:, :, b] = out
    if alpha is None:
        return cube, cube_dq
    a = np.where(np.isfinite(alpha), alpha, np.finfo(np.float32).max).astype(np.float32)
    cube_a = np.empty(cube.shape, np.float32)
    if method == "ppid":
        kh, kw = ppi_kernel(ph).size, ppi_kernel(pw).size
        big = np.ones((2 * ph - 1 + kh - 1, 2 * pw - 1 + kw - 1), np.uint8)
        common = cv2.dilate(a, big, borderType=cv2.BORDER_REPLICATE)
    for b in range(mosaic.n_bands):
        plane = np.where(bm == b, a, np.float32(-np.inf))
        m = cv2.dilate(plane, np.ones((2 * ph - 1, 2 * pw - 1), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=float(-np.inf))
        m[~np.isfinite(m)] = 0.0
        cube_a[:, :, b] = np.maximum(m, common) if method == "ppid" else m
    return cube, cube_dq, cube_a


# -- comparisons --------------------------------------------------------------------------------

MOSAICS = [Mosaic.rectangular(2, 4), Mosaic.square(5), Mosaic.square(4),
           Mosaic(np.arange(25).reshape(5, 5), offset=(3, 1)), Mosaic(np.array([[0, 1], [1, 2]]))]


def _scene(shape, mosaic, seed, flag_fraction):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    level = 100.0 + 40.0 * np.arange(mosaic.n_bands)
    raw = (level[mosaic.band_map(shape)] * (1 + 0.3 * np.sin(xx / 7.0) * np.cos(yy / 5.0))
           + rng.normal(0, 2.0, shape)).astype(np.float32)
    dq = np.zeros(shape, DQ_DTYPE)
    flagged = rng.random(shape) < flag_fraction
    dq[flagged] = rng.choice([int(DQ.LEAKAGE), int(DQ.SATURATED), int(DQ.HOT)], flagged.sum())
    return raw, (dq if flag_fraction else None), rng.uniform(0, 30, shape).astype(np.float32)


@pytest.mark.parametrize("method", ["bilinear", "ppid"])
@pytest.mark.parametrize("mosaic", MOSAICS, ids=lambda m: f"{m.tile_shape}{m.offset}")
@pytest.mark.parametrize("flag_fraction", [0.0, 0.05, 0.6])
def test_kernel_equals_the_opencv_filter_evaluation(method, mosaic, flag_fraction):
    raw, dq, alpha = _scene((61, 83), mosaic, 1, flag_fraction)
    alpha[3, 4] = np.inf
    cube, cube_dq, cube_a = demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    ref, ref_dq, ref_a = reference(raw, mosaic, dq, method, alpha)
    assert np.allclose(cube, ref, rtol=2e-6, atol=2e-5 * np.abs(ref).max())
    assert np.array_equal(cube_dq, ref_dq)
    assert np.array_equal(cube_a, ref_a)
    assert np.array_equal(reconstruct_alpha(alpha, mosaic, method=method), ref_a)


@pytest.mark.parametrize("method", ["bilinear", "ppid"])
@pytest.mark.parametrize("mosaic", MOSAICS, ids=lambda m: f"{m.tile_shape}{m.offset}")
def test_float32_interpolation_stays_within_its_error_budget(method, mosaic):
    """The kernel interpolates in float32: every value within 4 float32 ulps of the frame's
    largest value (2**-22 of it) of the same interpolation in float64, and, for bilinear,
    within 4 ulps of the value itself (PPID subtracts and adds back the PPI, so its error
    scales with the frame, not with a value near zero)."""
    raw, dq, _ = _scene((61, 83), mosaic, 3, 0.2)
    raw *= np.float32(20.0)  # thousands of DN, where an ulp is about 1e-4 DN
    cube, _, _ = demosaic(raw, mosaic, method=method, dq=dq)
    ref, _ = reference(raw, mosaic, dq, method, dtype=np.float64)
    err = np.abs(cube - ref)
    assert err.max() <= 2.0 ** -22 * np.abs(ref).max()
    if method == "bilinear":
        assert np.all(err <= 4 * np.spacing(np.abs(ref).astype(np.float32)))


def test_a_band_without_any_usable_sample_takes_the_median_and_do_not_use():
    mosaic = Mosaic.rectangular(2, 4)
    raw, _, _ = _scene((20, 24), mosaic, 2, 0.0)
    dq = np.zeros(raw.shape, DQ_DTYPE)
    dq[mosaic.band_map(raw.shape) == 3] = DQ.HOT
    dq[:, :12][mosaic.band_map(raw.shape)[:, :12] == 5] = DQ.LEAKAGE
    for method in ("bilinear", "ppid"):
        cube, cube_dq, _ = demosaic(raw, mosaic, method=method, dq=dq)
        ref, ref_dq = reference(raw, mosaic, dq, method)
        assert np.allclose(cube, ref, rtol=2e-6, atol=1e-3)
        assert np.array_equal(cube_dq, ref_dq)
        assert np.all(cube_dq[:, :, 3] & DQ.DO_NOT_USE) and np.all(cube[:, :, 3] == 0)


@pytest.mark.parametrize("ph,pw", [(1, 1), (2, 4), (3, 3), (5, 5), (4, 2), (6, 7), (2, 8)])
@pytest.mark.parametrize("shape", [(37, 53), (3, 5), (6, 1), (5, 3), (1, 6)])
def test_ppi_equals_separable_sums_in_numpy_bit_for_bit(ph, pw, shape):
    # the kernel writes the 3- and 5-tap window sums out and loops over the taps for other
    # sizes (1, 7, 9 taps here); each must give the sums of a frame-wide float64 horizontal
    # pass then a vertical one, taps in order, on the frame extended by whole tiles; frames
    # narrower than half the window (1 and 3 columns) are all border columns, and a single
    # row reaches every window row through the index map
    mosaic = Mosaic(np.arange(ph * pw).reshape(ph, pw), offset=(1 % ph, 2 % pw))
    raw = np.random.default_rng(ph * 10 + pw).uniform(-20.0, 900.0, shape).astype(np.float32)
    p = prepare(raw, mosaic, None)
    levels = band_levels(p)
    ppi, ok = pseudo_panchromatic(p, levels)
    inv = (1.0 / np.asarray(levels, np.float64)).astype(np.float32)
    vals = (raw * inv[mosaic.band_map(shape)]).astype(np.float64)  # float32 product, as kernel
    kx, ky = ppi_kernel(pw).astype(np.float64), ppi_kernel(ph).astype(np.float64)
    rows = periodic_index(shape[0], ph, ky.size // 2)
    cols = periodic_index(shape[1], pw, kx.size // 2)
    hn = np.zeros((rows.size, shape[1]))
    hd = np.zeros((rows.size, shape[1]))
    for t in range(kx.size):
        hn = hn + kx[t] * vals[rows][:, cols[t:t + shape[1]]]
        hd = hd + kx[t] * 1.0
    n = np.zeros(shape)
    d = np.zeros(shape)
    for t in range(ky.size):
        n = n + ky[t] * hn[t:t + shape[0]]
        d = d + ky[t] * hd[t:t + shape[0]]
    assert ok is None
    assert np.array_equal(ppi.view(np.uint32), (n / d).astype(np.float32).view(np.uint32))


@pytest.mark.parametrize("ph,pw,shape", [(2, 4, (9, 21)), (5, 5, (12, 13)), (3, 2, (4, 3))])
def test_ppi_neighbour_sums_pixel_by_pixel_equal_the_row_form(ph, pw, shape):
    # rows with few flagged pixels take their neighbour sums pixel by pixel, others the whole
    # row: both must give the same bits at every pixel, frame edges included
    rng = np.random.default_rng(ph + pw)
    raw = rng.uniform(-5.0, 900.0, shape).astype(np.float32)
    dq = (rng.random(shape) < 0.4).astype(DQ_DTYPE) * DQ_DTYPE(DQ.LEAKAGE)
    offs = ppi_kernels.neighbour_offsets(ph, pw)
    for y in range(shape[0]):
        acc, wsum = np.empty(shape[1]), np.empty(shape[1])
        ppi_kernels.row_neighbour_sums(raw, dq, y, offs, acc, wsum)
        one = np.array([ppi_kernels.pixel_neighbour_sums(raw, dq, y, x, offs)
                        for x in range(shape[1])])
        assert np.array_equal(one[:, 0], acc) and np.array_equal(one[:, 1], wsum)


def test_unflagged_ppi_shortcut_equals_the_weighted_path():
    mosaic = Mosaic.square(5)
    raw, _, _ = _scene((50, 65), mosaic, 3, 0.0)
    p = prepare(raw, mosaic, None)
    levels = band_levels(p)
    fast, ok_fast = pseudo_panchromatic(p, levels)
    slow, ok_slow = pseudo_panchromatic(Prepared(p.raw, np.zeros(raw.shape, DQ_DTYPE), mosaic),
                                        levels)
    assert ok_fast is None and ok_slow.all()
    assert np.allclose(fast, slow, rtol=1e-6)


@pytest.mark.parametrize("method", ["bilinear", "ppid"])
@settings(max_examples=25, deadline=None)
@given(ph=st.integers(1, 5), pw=st.integers(2, 5), oy=st.integers(0, 4), ox=st.integers(0, 4),
       h=st.integers(2, 40), w=st.integers(2, 40),
       frac=st.sampled_from([0.0, 0.1, 0.3, 0.9]), seed=st.integers(0, 1000))
def test_random_layouts_match_the_reference(method, ph, pw, oy, ox, h, w, frac, seed):
    """Random layouts, offsets and flags, frames down to narrower and lower than the tile
    (where a flagged sample's neighbours one tile away fall outside the frame and some bands
    have no sample at all)."""
    mosaic = Mosaic(np.arange(ph * pw).reshape(ph, pw), offset=(oy, ox))
    raw, dq, alpha = _scene((h, w), mosaic, seed, frac)
    cube, cube_dq, cube_a = demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    ref, ref_dq, ref_a = reference(raw, mosaic, dq, method, alpha)
    assert np.all(np.isfinite(cube))
    assert np.allclose(cube, ref, rtol=2e-6, atol=2e-5 * np.abs(ref).max())
    assert np.array_equal(cube_dq, ref_dq) and np.array_equal(cube_a, ref_a)


@pytest.mark.parametrize("method", ["nearest", "bilinear", "ppid"])
def test_a_band_with_no_sample_in_the_frame_is_zero_and_do_not_use(method):
    """A frame narrower than the tile holds no sample of some bands: those values follow the
    rule for no usable sample (the band median, 0 when there is none, and DO_NOT_USE), never
    NaN with DQ 0 (as they were), and the other bands are untouched."""
    raw = np.array([[10.0, 20.0], [30.0, 40.0]], np.float32)
    cube, cube_dq, alpha = demosaic(raw, Mosaic(np.arange(3).reshape(1, 3)), method=method,
                                    alpha=np.ones((2, 2), np.float32))
    assert np.all(np.isfinite(cube)) and np.all(cube[:, :, 2] == 0.0)
    assert np.all(cube_dq[:, :, 2] == DQ.DO_NOT_USE) and not cube_dq[:, :, :2].any()
    assert np.array_equal(cube[:, :, 0], [[10, 10], [30, 30]])
    assert np.array_equal(cube[:, :, 1], [[20, 20], [40, 40]])
    assert np.all(np.isfinite(alpha))


@pytest.mark.parametrize("method", ["bilinear", "ppid"])
@pytest.mark.parametrize("mosaic", [MOSAICS[0], MOSAICS[3]], ids=["2x4", "5x5 offset"])
def test_flagged_blocks_take_the_wide_tent_the_bilinear_value_and_the_median(method, mosaic):
    """A flagged block wider than the PPI window and than S2: inside it the PPI is undefined
    (the bilinear value is used), near its edge S1 is empty (S2), in its middle S2 is empty
    too (band median, DO_NOT_USE); plus flagged rows and columns."""
    raw, dq, alpha = _scene((70, 90), mosaic, 4, 0.25)
    dq[20:45, 30:62] = DQ.HOT
    dq[5, :] |= DQ_DTYPE(DQ.SATURATED)
    dq[:, 11] |= DQ_DTYPE(DQ.LEAKAGE)
    cube, cube_dq, cube_a = demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    ref, ref_dq, ref_a = reference(raw, mosaic, dq, method, alpha)
    assert np.all(cube_dq[32, 46] & DQ.DO_NOT_USE)
    assert np.allclose(cube, ref, rtol=2e-6, atol=2e-5 * np.abs(ref).max())
    assert np.array_equal(cube_dq, ref_dq)
    assert np.array_equal(cube_a, ref_a)


@pytest.mark.slow  # compiles the parallel builds of the interpolation and PPI kernels
@pytest.mark.parametrize("method", ["bilinear", "ppid"])
def test_parallel_build_on_a_frame_equals_the_reference(method):
    """Frames of PARALLEL_MIN pixels or more run the parallel builds (the rest of this module
    runs the serial ones): the same values, DQ and alpha as the reference, with many flags."""
    mosaic = Mosaic.rectangular(2, 4)
    raw, dq, alpha = _scene((256, 384), mosaic, 5, 0.22)
    dq[100:130, 200:260] = DQ.HOT
    alpha[7, 9] = np.nan
    assert raw.size >= launch.PARALLEL_MIN
    cube, cube_dq, cube_a = demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    ref, ref_dq, ref_a = reference(raw, mosaic, dq, method, alpha)
    assert np.allclose(cube, ref, rtol=2e-6, atol=2e-5 * np.abs(ref).max())
    assert np.array_equal(cube_dq, ref_dq)
    assert np.array_equal(cube_a, ref_a)


def test_where_the_ppi_is_undefined_ppid_takes_the_bilinear_value():
    """The kernel's path for PPID values whose PPI window held no usable pixel but whose S1
    holds a usable sample (rare in frames; driven here through a made-up definition mask)."""
    mosaic = Mosaic.rectangular(2, 4)
    raw, dq, _ = _scene((40, 56), mosaic, 6, 0.3)
    p = prepare(raw, mosaic, dq)
    levels = band_levels(p)
    ppi, _ = pseudo_panchromatic(p, levels)
    undefined = np.random.default_rng(7).random(raw.shape) < 0.1
    shape = raw.shape + (mosaic.n_bands,)
    cubes = []
    for ok in (None, ~undefined):
        cube = np.empty(shape, np.float32)  # the DQ cube holds garbage: all of it is written
        cube_dq = np.full(shape, 0xDEADBEEF, DQ_DTYPE)
        missing = interpolate_bands(p.raw, p.dq, None, ppi, ok, levels, p.lattices(),
                                    mosaic.tile_shape, cube, cube_dq, None)
        assert not missing.any()
        cubes.append((cube, cube_dq))
    bil, bil_dq = reference(raw, mosaic, dq, "bilinear")
    bm = mosaic.band_map(raw.shape)
    for b in range(mosaic.n_bands):
        w = ((bm == b) & (dq == 0)).astype(np.float32)
        have1 = _interp(raw, w, *mosaic.tile_shape)[1]
        use_bil = undefined & have1
        assert use_bil.sum() > 20
        got, full = cubes[1][0][:, :, b], cubes[0][0][:, :, b]
        assert np.allclose(got[use_bil], bil[:, :, b][use_bil], rtol=2e-6, atol=1e-3)
        assert np.array_equal(got[~undefined], full[~undefined])
    assert np.array_equal(cubes[0][1], cubes[1][1]) and np.array_equal(cubes[1][1], bil_dq)


@pytest.mark.parametrize("pattern, offset", [([[0, 1, 2, 3], [4, 5, 6, 7]], (0, 0)),
                                             ([[0, 1], [1, 2]], (1, 0))])
def test_band_medians_are_numpy_medians_of_the_usable_samples(pattern, offset):
    """band_medians (two threads, shared by PPID's levels and the no-source fill) equals
    np.median over each band's unflagged samples, 0 for a band with none, in the order asked;
    the strided gather (np.compress) takes every occurrence of a band in the tile."""
    from hsiffc.reconstruct.prepare import band_medians

    mosaic = Mosaic(np.array(pattern), offset=offset)
    rng = np.random.default_rng(7)
    raw = rng.normal(100, 20, (37, 50)).astype(np.float32)
    bm = mosaic.band_map(raw.shape)
    raw += 10.0 * bm  # distinct levels per band
    dq = np.where(rng.random(raw.shape) < 0.3, DQ.LEAKAGE, 0).astype(DQ_DTYPE)
    dq[bm == 2] = DQ.DO_NOT_USE  # band 2 has no usable sample
    p = prepare(raw, mosaic, dq)
    bands = list(range(mosaic.n_bands))[::-1]
    got = band_medians(p, bands)
    want = [np.median(raw[(bm == b) & (dq == 0)]) if b != 2 else 0.0 for b in bands]
    np.testing.assert_array_equal(got, np.array(want, np.float64))
    assert band_medians(p, [1]).tolist() == [want[bands.index(1)]]  # one band: no threads


def test_band_median_is_numpy_median_for_odd_and_even_counts():
    """The band median (one partition, the lower middle value as the max below it for an even
    count) equals np.median for odd and even counts, ties and constant values."""
    from hsiffc.reconstruct.prepare import band_medians

    rng = np.random.default_rng(3)
    one_band = Mosaic(np.array([[0]]))
    for shape in ((1, 1), (1, 2), (3, 1), (2, 2), (11, 1), (25, 40), (25, 41), (100, 200)):
        for values in (rng.normal(size=shape), rng.integers(0, 5, shape), np.full(shape, 7.0)):
            raw = values.astype(np.float32)
            got = band_medians(prepare(raw, one_band, None), [0])
            assert got.tolist() == [float(np.median(raw))], shape


@pytest.mark.parametrize("shape", [(7, 11), (2, 3), (300, 260)])
def test_lattice_planes_hold_each_lattice_contiguously_and_zeros_beyond_the_frame(shape):
    """split_lattices (the frame as one plane per lattice, which the kernel reads with flags):
    every sample of the frame at its lattice place, zeros where a lattice runs past the frame
    (serial build for the small frames, parallel for the large one)."""
    rng = np.random.default_rng(5)
    raw = rng.normal(50, 9, shape).astype(np.float32)
    dq = rng.integers(0, 3, shape).astype(DQ_DTYPE)
    ppi = rng.normal(40, 5, shape).astype(np.float32)
    ph, pw = 3, 4
    lat_r = np.array([r for r in range(ph) for _ in range(pw)], np.int64)
    lat_c = np.array([c for _ in range(ph) for c in range(pw)], np.int64)
    size = (ph * pw, -(-shape[0] // ph), -(-shape[1] // pw))
    planes = [np.zeros(size, np.float32), np.zeros(size, DQ_DTYPE), np.zeros(size, np.float32)]
    split_lattices(raw, dq, ppi, True, lat_r, lat_c, ph, pw, *planes)
    for j, (r, c) in enumerate(zip(lat_r, lat_c)):
        for plane, src in zip(planes, (raw, dq, ppi)):
            inside = src[r::ph, c::pw]
            assert np.array_equal(plane[j][:inside.shape[0], :inside.shape[1]], inside)
            rest = plane[j].copy()
            rest[:inside.shape[0], :inside.shape[1]] = 0
            assert not rest.any()


def test_samples_of_several_bands_equal_the_strided_lattice_samples():
    """Prepared.samples_of (one compiled pass, parallel over bands) returns, per band, the
    unflagged samples of its lattices: those of numpy's strided views, in the same order."""
    rng = np.random.default_rng(11)
    mosaic = Mosaic(np.array([[0, 1, 2], [2, 3, 0]]), offset=(1, 2))
    raw = rng.normal(20, 4, (300, 301)).astype(np.float32)
    dq = (rng.random(raw.shape) < 0.3).astype(DQ_DTYPE) * DQ.HOT
    for flags in (dq, None):
        p = prepare(raw, mosaic, flags)
        got = p.samples_of([3, 0, 2])
        for b, v in zip([3, 0, 2], got):
            ph, pw = mosaic.tile_shape
            want = [raw[r::ph, c::pw][(flags[r::ph, c::pw] == 0) if flags is not None
                                      else np.ones_like(raw[r::ph, c::pw], bool)]
                    for r, c in p.lattices()[b]]
            assert np.array_equal(v, np.concatenate(want))


@pytest.mark.slow  # compiles the parallel builds; bench_kernels checks the same on a clean cache
def test_each_block_function_compiles_once_for_the_serial_and_parallel_builds():
    """The interpolation and PPI kernels hand their block functions int64 indices in both
    builds. numba types a parallel loop's index uint64 (and a literal ``1`` as a literal), and
    it compiled each callee once per type it saw: on a clean numba cache the first full-frame
    PPID cube took 63 s of compiling instead of 34 (measured in this repository, the default
    pipeline's first call). Checkable where the kernels compile in this process (a clean
    checkout, as in CI); kernels loaded from numba's disk cache compile no callee at all."""
    rng = np.random.default_rng(5)
    mosaic = Mosaic(np.arange(8).reshape(2, 4))
    for shape, flagged in (((16, 32), 0.05), ((256, 288), 0.05), ((256, 288), 0.4)):
        assert (np.prod(shape) >= launch.PARALLEL_MIN) == (shape[0] == 256)  # both builds run
        raw = rng.uniform(10.0, 100.0, shape).astype(np.float32)
        dq = np.where(rng.random(shape) < flagged, DQ.LEAKAGE, 0).astype(DQ_DTYPE)
        alpha = rng.uniform(0.0, 5.0, shape).astype(np.float32)
        for method in ("bilinear", "ppid"):
            demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    from hsiffc.kernels import demosaic as demosaic_kernels
    callees = (demosaic_kernels._interpolate_block, ppi_kernels._window_block,
               ppi_kernels.row_neighbour_sums, ppi_kernels.pixel_neighbour_sums)
    compiled = {f.py_func.__name__: [str(s) for s in f.signatures] for f in callees}
    if not any(compiled.values()):
        pytest.skip("the kernels came from numba's disk cache: no callee compiled here")
    # at most once each: a kernel whose source did not change loads from the disk cache and
    # compiles no callee, while an edited one compiles its own
    assert all(len(s) <= 1 for s in compiled.values()), compiled
