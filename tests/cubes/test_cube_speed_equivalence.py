"""The interpolation kernel (hsiffc.kernels.demosaic) against the DQ rule of
hsiffc.reconstruct written out plainly: for every band and pixel, the same-band samples at
every offset of the one-tile support S1 (then the twice-wide S2) summed with their tent
weights in float64 numpy, one shifted plane per offset (no lattice planes, no column phases,
no lists of values: none of the kernel's shortcuts). Frames with many flagged pixels, flagged
blocks, rows, columns and borders, bands once and twice per tile, offsets, bilinear and PPID
(the PPI taken from the package, its use checked here), both builds of the kernel (serial for
the small frames, parallel for the one of PARALLEL_MIN pixels).

Tolerance: the kernel sums in float64 in its own order and rounds once to float32; the
reference sums in float64 in another order. The two agree to float32 rounding (here within
1e-6 relative, 1e-6 of the frame's largest value absolute); a wrong sample, weight or support
would be off by far more."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.data.dq import DQ, DQ_DTYPE
from hsiffc.kernels import launch
from hsiffc.data.mosaic import Mosaic
from hsiffc.reconstruct import demosaic
from hsiffc.reconstruct import ppi_kernel
from hsiffc.reconstruct.prepare import band_levels, prepare, pseudo_panchromatic


def _shifted(plane, dy, dx, fill):
    """``out[y, x] = plane[y + dy, x + dx]`` inside the frame, ``fill`` outside."""
    H, W = plane.shape
    out = np.full(plane.shape, fill, plane.dtype)
    ys, xs = slice(max(0, -dy), min(H, H - dy)), slice(max(0, -dx), min(W, W - dx))
    ys2, xs2 = slice(max(0, dy), min(H, H + dy)), slice(max(0, dx), min(W, W + dx))
    out[ys, xs] = plane[ys2, xs2]
    return out


def _support(values, usable, ph, pw, m):
    """Tent-weighted sums over the same-band samples within ``m`` tiles: (sum w v, sum w)."""
    num = np.zeros(values.shape)
    den = np.zeros(values.shape)
    for dy in range(-(m * ph - 1), m * ph):
        for dx in range(-(m * pw - 1), m * pw):
            w = (1 - abs(dy) / (m * ph)) * (1 - abs(dx) / (m * pw))
            num += w * _shifted(np.where(usable, values, 0.0), dy, dx, 0.0)
            den += w * _shifted(usable.astype(np.float64), dy, dx, 0.0)
    return num, den


def plain_reference(raw, mosaic, dq, alpha, method):
    """The cube, its DQ and its alpha by the package's DQ rule, written out."""
    H, W = raw.shape
    ph, pw = mosaic.tile_shape
    bm = mosaic.band_map(raw.shape)
    good = dq == 0
    v64 = raw.astype(np.float64)
    if method == "ppid":
        p = prepare(raw, mosaic, dq)
        levels = band_levels(p)
        ppi, ppi_ok = pseudo_panchromatic(p, levels)
        ppi_ok = np.ones(raw.shape, bool) if ppi_ok is None else ppi_ok
    B = mosaic.n_bands
    cube = np.empty((H, W, B))
    cube_dq = np.zeros((H, W, B), DQ_DTYPE)
    cube_a = np.zeros((H, W, B), np.float32)
    for b in range(B):
        site = bm == b
        usable = site & good
        n1, d1 = _support(v64, usable, ph, pw, 1)
        n2, d2 = _support(v64, usable, ph, pw, 2)
        est = np.where(d1 > 0, n1 / np.where(d1 > 0, d1, 1), n2 / np.where(d2 > 0, d2, 1))
        if method == "ppid":
            diff = v64 - levels[b] * ppi.astype(np.float64)
            m1, _ = _support(diff, usable, ph, pw, 1)
            m2, _ = _support(diff, usable, ph, pw, 2)
            pp = np.where(d1 > 0, m1 / np.where(d1 > 0, d1, 1), m2 / np.where(d2 > 0, d2, 1))
            pp += levels[b] * ppi
            est = np.where(ppi_ok, pp, est)  # PPI undefined: the bilinear value
        med = np.median(raw[usable]) if usable.any() else 0.0
        est[(d1 == 0) & (d2 == 0)] = med
        cube[:, :, b] = est
        own = np.where(site, dq, 0).astype(DQ_DTYPE)
        s1_flags = np.zeros(raw.shape, DQ_DTYPE)
        s1_alpha = np.full(raw.shape, -np.inf, np.float32)
        for dy in range(-(ph - 1), ph):
            for dx in range(-(pw - 1), pw):
                s1_flags |= _shifted(own, dy, dx, 0)
                s1_alpha = np.maximum(s1_alpha, _shifted(np.where(site, alpha, -np.inf)
                                                         .astype(np.float32), dy, dx, -np.inf))
        q = own | np.where(d1 == 0, s1_flags, 0).astype(DQ_DTYPE)
        q[(d1 == 0) & (d2 == 0)] |= DQ_DTYPE(DQ.DO_NOT_USE)
        cube_dq[:, :, b] = q
        if method == "ppid":  # and every raw pixel entering the PPI at those samples
            s1_alpha = np.maximum(s1_alpha, _ppi_window_max(alpha, ph, pw))
        cube_a[:, :, b] = np.where(np.isfinite(s1_alpha), s1_alpha, 0.0)
    return cube, cube_dq, cube_a


def _ppi_window_max(alpha, ph, pw):
    """The max alpha over the centred window of ``2 p - 1 + len(ppi_kernel(p)) - 1`` rows
    and columns, the frame extended by its edge values."""
    ry = (2 * ph - 2 + ppi_kernel(ph).size - 1) // 2
    rx = (2 * pw - 2 + ppi_kernel(pw).size - 1) // 2
    padded = np.pad(alpha, ((ry, ry), (rx, rx)), mode="edge")
    H, W = alpha.shape
    return np.max([padded[dy:dy + H, dx:dx + W] for dy in range(2 * ry + 1)
                   for dx in range(2 * rx + 1)], axis=0)


def _frame(shape, mosaic, seed, fraction):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    level = 80.0 + 35.0 * np.arange(mosaic.n_bands)
    raw = (level[mosaic.band_map(shape)] * (1 + 0.4 * np.sin(xx / 5.0) * np.cos(yy / 3.0))
           + rng.normal(0, 3.0, shape)).astype(np.float32)
    dq = np.where(rng.random(shape) < fraction,
                  rng.choice([int(DQ.LEAKAGE), int(DQ.HOT), int(DQ.SATURATED)], shape),
                  0).astype(DQ_DTYPE)
    H, W = shape
    dq[H // 3:H // 3 + 7, W // 2:W // 2 + 11] |= DQ_DTYPE(DQ.HOT)  # wider than S2 in places
    dq[0, :] |= DQ_DTYPE(DQ.SATURATED)  # a flagged border row and column, and one inside
    dq[:, -1] |= DQ_DTYPE(DQ.LEAKAGE)
    dq[:, 5] |= DQ_DTYPE(DQ.LEAKAGE)
    alpha = rng.uniform(0, 25, shape).astype(np.float32)
    return raw, dq, alpha


MOSAICS = {"2x4": Mosaic.rectangular(2, 4),
           "band twice per tile": Mosaic(np.array([[0, 1], [1, 2]]), offset=(1, 0)),
           "3x3 offset": Mosaic(np.arange(9).reshape(3, 3), offset=(2, 1))}


def _check(raw, mosaic, dq, alpha, method):
    cube, cube_dq, cube_a = demosaic(raw, mosaic, method=method, dq=dq, alpha=alpha)
    ref, ref_dq, ref_a = plain_reference(raw, mosaic, dq, alpha, method)
    assert np.all(np.isfinite(cube))
    np.testing.assert_allclose(cube, ref, rtol=1e-6, atol=1e-6 * float(np.abs(raw).max()))
    np.testing.assert_array_equal(cube_dq, ref_dq)
    np.testing.assert_array_equal(cube_a, ref_a)
    return cube_dq


@pytest.mark.parametrize("method", ["bilinear", "ppid"])
@pytest.mark.parametrize("name", list(MOSAICS))
@pytest.mark.parametrize("fraction", [0.25, 0.7])
def test_kernel_equals_the_dq_rule_written_out(method, name, fraction):
    raw, dq, alpha = _frame((29, 43), MOSAICS[name], 3, fraction)
    cube_dq = _check(raw, MOSAICS[name], dq, alpha, method)
    # the frame exercises every branch of the rule: S1 empty (S2 used) and S2 empty too
    assert np.any(cube_dq & DQ.DO_NOT_USE)
    assert np.any((cube_dq != 0) & ~(cube_dq & DQ.DO_NOT_USE).astype(bool))


@pytest.mark.slow  # compiles the parallel build of the kernel
@pytest.mark.parametrize("method", ["bilinear", "ppid"])
def test_parallel_build_equals_the_dq_rule_written_out(method):
    raw, dq, alpha = _frame((192, 352), MOSAICS["2x4"], 4, 0.23)
    assert raw.size >= launch.PARALLEL_MIN
    _check(raw, MOSAICS["2x4"], dq, alpha, method)
