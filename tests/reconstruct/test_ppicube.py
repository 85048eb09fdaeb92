"""The fused kernels of "ppid_edge" and "itsd" (hsiffc.kernels.ppicube) against the general
kernels they stand in for, and the spectral-difference step against a numpy evaluation of its
formula, on frames whose sizes are not whole tiles (every border case)."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.data.dq import DQ, DQ_DTYPE
from hsiffc.data.mosaic import Mosaic
from hsiffc.kernels.demosaic import interpolate_bands
from hsiffc.kernels.ppicube import (cube_of_planes, edge_ppi, fill_sparse, flagged_indices,
                                    spectral_difference)
from hsiffc.kernels.refined import refine_ppi
from hsiffc.reconstruct.prepare import prepare

LAYOUTS = [Mosaic.rectangular(2, 4), Mosaic.square(4), Mosaic(np.arange(15).reshape(3, 5),
                                                               offset=(1, 2))]


def _frame(shape, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(20, 900, shape).astype(np.float32)


@pytest.mark.parametrize("mosaic", LAYOUTS, ids=lambda m: m.name)
def test_cube_of_planes_equals_the_shared_pass(mosaic):
    """``l_b PPI + tent(R)`` from the lattice rows equals the shared pass's normalised
    convolution (PPID on an unflagged frame), borders included, to float32 rounding."""
    shape = (23, 37)
    p = prepare(_frame(shape, 1), mosaic, None)
    B = mosaic.n_bands
    ppi = _frame(shape, 2)
    levels = np.random.default_rng(3).uniform(0.5, 1.5, B)
    lev = levels[mosaic.band_map(shape)].astype(np.float32)
    res = p.raw - lev * ppi
    want = np.empty(shape + (B,), np.float32)
    interpolate_bands(p.raw, None, None, ppi, None, levels, p.lattices(), mosaic.tile_shape,
                      want, np.empty(shape + (B,), DQ_DTYPE), None)
    got = np.empty_like(want)
    got_dq = np.full(shape + (B,), 7, DQ_DTYPE)
    rc = [lat[0] for lat in p.lattices()]
    cube_of_planes(res, ppi, levels, rc, mosaic.tile_shape, got, got_dq)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * np.abs(want).max())
    assert not got_dq.any()


@pytest.mark.parametrize("mosaic", LAYOUTS, ids=lambda m: m.name)
def test_edge_ppi_equals_the_refined_ppi_and_its_differences(mosaic):
    shape = (29, 41)
    raw = _frame(shape, 4)
    mbar = _frame(shape, 5) * 0.1 + 300
    band_of = mosaic.band_map(mosaic.tile_shape)
    levels = np.random.default_rng(6).uniform(0.5, 1.5, mosaic.n_bands).astype(np.float32)
    ph, pw = mosaic.tile_shape
    want = np.empty(shape, np.float32)
    refine_ppi(raw, mbar, np.ascontiguousarray(band_of, np.int64), levels, True,
               np.float32(6.0), ph, pw, want, np.empty((1, 1, 9), np.float32), False)
    ppi, diff = edge_ppi(raw, mbar, band_of, levels, 6.0)
    np.testing.assert_allclose(ppi, want, rtol=1e-6)
    lev = levels[mosaic.band_map(shape)]
    np.testing.assert_allclose(diff, raw - lev * ppi, rtol=0, atol=1e-4)


def test_flagged_indices_and_the_sparse_fill():
    rng = np.random.default_rng(7)
    dq = np.where(rng.random((31, 45)) < 0.05, np.uint32(DQ.HOT), np.uint32(0))
    flat = flagged_indices(dq)
    assert np.array_equal(flat, np.flatnonzero(dq)) and flat.dtype == np.int64
    assert flagged_indices(np.zeros((3, 4), np.uint32)).size == 0
    raw = _frame(dq.shape, 8)
    out = fill_sparse(raw, dq, flat, 4, 4)
    assert np.array_equal(out[dq == 0], raw[dq == 0]) and out is not raw
    y, x = divmod(int(flat[len(flat) // 2]), dq.shape[1])
    terms = [(0.25 if sy and sx else 0.5, raw[y + 4 * sy, x + 4 * sx])
             for sy in (-1, 0, 1) for sx in (-1, 0, 1) if (sy or sx)
             and 0 <= y + 4 * sy < 31 and 0 <= x + 4 * sx < 45 and dq[y + 4 * sy, x + 4 * sx] == 0]
    if terms:
        w, v = np.array(terms).T
        assert out[y, x] == pytest.approx(float((w * v).sum() / w.sum()), rel=1e-6)


@pytest.mark.parametrize("mosaic", LAYOUTS[:2], ids=lambda m: m.name)
def test_spectral_difference_step_equals_its_formula(mosaic):
    """At a pixel of band c, band b is raw plus the normalised tent (half-width one tile) of
    ``raw(s) - prev_c(s)`` over b's samples s; band c itself is raw."""
    shape = (14, 19)
    raw = _frame(shape, 9)
    B = mosaic.n_bands
    prev = np.random.default_rng(10).uniform(20, 900, shape + (B,)).astype(np.float32)
    p = prepare(raw, mosaic, None)
    rc = [lat[0] for lat in p.lattices()]
    out = np.empty_like(prev)
    spectral_difference(raw, prev, rc, mosaic.band_map(mosaic.tile_shape), out)
    bm = mosaic.band_map(shape)
    ph, pw = mosaic.tile_shape
    rng = np.random.default_rng(11)
    for y, x in zip(rng.integers(0, shape[0], 12), rng.integers(0, shape[1], 12), strict=True):
        c = bm[y, x]
        for b in range(B):
            if b == c:
                assert out[y, x, b] == raw[y, x]
                continue
            num = den = 0.0
            for ys in range(max(0, y - ph + 1), min(shape[0], y + ph)):
                for xs in range(max(0, x - pw + 1), min(shape[1], x + pw)):
                    if bm[ys, xs] == b:
                        w = (1 - abs(ys - y) / ph) * (1 - abs(xs - x) / pw)
                        num += w * (raw[ys, xs] - prev[ys, xs, c])
                        den += w
            assert out[y, x, b] == pytest.approx(raw[y, x] + num / den, rel=1e-5, abs=1e-3)


@pytest.mark.parametrize("mosaic", LAYOUTS, ids=lambda m: m.name)
def test_fused_ppid_edge_equals_the_general_path_with_flags(mosaic, monkeypatch):
    """"ppid_edge" on the fused kernels gives the general kernels' cube and DQ (the path of a
    layout with a repeated band), given the same band levels, on a frame with lone flagged
    samples, a flagged block and flags at the borders."""
    from hsiffc.reconstruct import demosaic
    from hsiffc.reconstruct import refined

    rng = np.random.default_rng(12)
    y, x = np.mgrid[0:47, 0:61]
    raw = (400 + 300 * np.sin(x / 3.0) * np.cos(y / 4.0)
           * (1 + 0.2 * mosaic.band_map(x.shape))).astype(np.float32)
    dq = np.where(rng.random(raw.shape) < 0.02, np.uint32(DQ.DEAD), np.uint32(0))
    dq[20:23, 30:33] = DQ.HOT
    dq[0, 0] = dq[-1, -1] = DQ.DEAD
    monkeypatch.setattr(refined, "_sampled_levels", refined._levels)
    fused = demosaic(raw, mosaic, method="ppid_edge", dq=dq)
    monkeypatch.setattr(refined, "single_lattice", lambda p: False)
    general = demosaic(raw, mosaic, method="ppid_edge", dq=dq)
    np.testing.assert_allclose(fused.cube, general.cube, rtol=0, atol=1e-4 * raw.max())
    assert np.array_equal(fused.dq, general.dq)
