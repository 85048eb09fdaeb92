"""Compiled kernel of mosaic interpolation: bilinear and PPID bands, their DQ and alpha.

This is the implementation behind :func:`hsiffc.reconstruct.demosaic` (methods "bilinear" and
"ppid") and :func:`hsiffc.reconstruct.reconstruct_alpha` (``resolution="full"``). It evaluates
the normalised convolution ``(K * (v w)) / (K * w)`` with the tent kernel ``K`` of half-width
one tile directly on each band's sample lattice: the tent covers at most two sample rows and
two sample columns of a lattice, so a row of output is a vertical blend of two sample rows
followed by a horizontal blend of two sample columns (separable, exact, no zero-filled planes).
One pass per output row writes every band of the cube, its DQ and its alpha (the max over the
same samples); pixels whose support holds no usable sample take the twice-wide tent (S2) and
are otherwise marked NaN for the caller's band-median fill. Arithmetic in float64 (results
within float32 rounding of the former ``cv2.sepFilter2D`` evaluation).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..dq import DQ
from .launch import JIT_OPTIONS, Kernel

__all__ = ["EPS", "interpolate_bands"]

#: Weight sums at or below this are "no source" (the smallest real weight is 1 / (4 ph pw)).
EPS = 1e-6
_DO_NOT_USE = int(DQ.DO_NOT_USE)
_JIT = {**JIT_OPTIONS, "cache": False}


@njit(**_JIT)
def _sample_value(raw, ppi, level, ys, xs, use_ppi):
    v = np.float64(raw[ys, xs])
    return v - level * ppi[ys, xs] if use_ppi else v


@njit(**_JIT)
def _wide(raw, dq, ppi, level, use_ppi, y, x, lat_r, lat_c, j0, j1, ph, pw, plain):
    """Estimate from the twice-wide tent (S2) over the good samples; NaN if none."""
    H, W = raw.shape
    num = 0.0
    den = 0.0
    for j in range(j0, j1):
        ry0 = y - ((y - lat_r[j]) % ph)
        cx0 = x - ((x - lat_c[j]) % pw)
        for iy in range(-1, 3):
            ys = ry0 + iy * ph
            wy = 1.0 - abs(y - ys) / (2.0 * ph)
            if ys < 0 or ys >= H or wy <= 0.0:
                continue
            for ix in range(-1, 3):
                xs = cx0 + ix * pw
                wx = 1.0 - abs(x - xs) / (2.0 * pw)
                if xs < 0 or xs >= W or wx <= 0.0 or dq[ys, xs] != 0:
                    continue
                w = wy * wx
                num += w * (raw[ys, xs] if plain else _sample_value(raw, ppi, level, ys, xs,
                                                                     use_ppi))
                den += w
    return num / den if den > EPS else np.nan


def _interpolate_rows(raw, dq, has_dq, alpha, has_alpha, common, has_common, ppi, ppi_ok,
                      use_ppi, levels, lat_r, lat_c, lat_start, band_of, ph, pw,
                      cube, cube_dq, cube_alpha):
    """Fill ``cube`` (H, W, B) and, where present, ``cube_dq`` and ``cube_alpha``.

    ``lat_r/lat_c`` are the first sample row/column (0 <= r < ph, 0 <= c < pw, offset
    included) of each pattern position; those of band b are ``lat_start[b]:lat_start[b+1]``.
    ``band_of`` is the (ph, pw) band of each (row % ph, col % pw) phase (offset included).
    Returns the number of values left NaN (no usable sample within twice the tile).

    Per output row and band: a vertical pass blends the two sample rows of each lattice at
    its columns (sums over usable samples only, their weight, the OR of the flagged ones'
    bits, the max alpha), a horizontal pass per column phase blends two neighbouring columns
    into per-pixel sums (the inner loops are branch-free and vectorise), a final pass divides
    and writes the cube, its flags and alpha.
    """
    H, W = raw.shape
    B = lat_start.shape[0] - 1
    nk_max = W // pw + 2
    missing = 0
    for y in prange(H):
        vnum = np.empty(nk_max)
        vraw = np.empty(nk_max)
        vden = np.empty(nk_max)
        vor = np.empty(nk_max, np.uint32)
        vmax = np.empty(nk_max, np.float32)
        num = np.empty(W)
        nraw = np.empty(W)
        den = np.empty(W)
        orf = np.empty(W, np.uint32)
        amax = np.empty(W, np.float32)
        yph = y % ph
        for b in range(B):
            level = levels[b]
            num[:] = 0.0
            nraw[:] = 0.0
            den[:] = 0.0
            orf[:] = 0
            amax[:] = -np.inf
            for j in range(lat_start[b], lat_start[b + 1]):
                ry0 = y - ((y - lat_r[j]) % ph)  # sample row at or above y
                wy1 = (y - ry0) / ph
                ry1 = ry0 + ph
                w0 = (1.0 - wy1) if ry0 >= 0 else 0.0
                w1 = wy1 if ry1 < H else 0.0
                r0 = ry0 if ry0 >= 0 else ry1
                r1 = ry1 if ry1 < H else r0
                c0 = lat_c[j]
                nk = (W - c0 + pw - 1) // pw
                # vertical: the lattice's columns c0 + k pw, padded by one on each side
                for k in range(nk):
                    xs = c0 + k * pw
                    v0 = np.float64(raw[r0, xs])
                    v1 = np.float64(raw[r1, xs])
                    g0 = w0
                    g1 = w1
                    f = np.uint32(0)
                    if has_dq:
                        if dq[r0, xs] != 0 and w0 > 0.0:
                            g0 = 0.0
                            f |= dq[r0, xs]
                        if dq[r1, xs] != 0 and w1 > 0.0:
                            g1 = 0.0
                            f |= dq[r1, xs]
                    vraw[k + 1] = g0 * v0 + g1 * v1
                    if use_ppi:
                        v0 -= level * ppi[r0, xs]
                        v1 -= level * ppi[r1, xs]
                    vnum[k + 1] = g0 * v0 + g1 * v1
                    vden[k + 1] = g0 + g1
                    vor[k + 1] = f
                    if has_alpha:
                        a0 = alpha[r0, xs] if w0 > 0.0 else np.float32(-np.inf)
                        a1 = alpha[r1, xs] if w1 > 0.0 else np.float32(-np.inf)
                        vmax[k + 1] = max(a0, a1)
                for arr in (vnum, vraw, vden):
                    arr[0] = 0.0
                    arr[nk + 1] = 0.0
                vor[0] = 0
                vor[nk + 1] = 0
                vmax[0] = -np.inf
                vmax[nk + 1] = -np.inf
                # horizontal: pixel x = c0 + (k - 1) pw + p lies between padded columns k, k+1
                for p in range(pw):
                    wr = p / pw
                    wl = 1.0 - wr
                    x0 = c0 - pw + p
                    k_lo = 0 if x0 >= 0 else 1
                    k_hi = min(nk + 1, (W - 1 - x0) // pw + 1)
                    for k in range(k_lo, k_hi):
                        x = x0 + k * pw
                        num[x] += wl * vnum[k] + wr * vnum[k + 1]
                        nraw[x] += wl * vraw[k] + wr * vraw[k + 1]
                        den[x] += wl * vden[k] + wr * vden[k + 1]
                    if has_dq:
                        for k in range(k_lo, k_hi):
                            x = x0 + k * pw
                            orf[x] |= vor[k] | (vor[k + 1] if p > 0 else np.uint32(0))
                    if has_alpha:
                        for k in range(k_lo, k_hi):
                            x = x0 + k * pw
                            a = max(vmax[k], vmax[k + 1]) if p > 0 else vmax[k]
                            amax[x] = max(amax[x], a)
            # final: divide, fall back where S1 had no usable sample, write
            j0, j1 = lat_start[b], lat_start[b + 1]
            for x in range(W):
                d = den[x]
                if use_ppi:
                    est = num[x] / d + level * ppi[y, x]
                else:
                    est = num[x] / d
                cube[y, x, b] = est
            if use_ppi and has_dq:  # where the PPI is undefined: plain bilinear
                for x in range(W):
                    if not ppi_ok[y, x]:
                        cube[y, x, b] = nraw[x] / den[x]
            fix = has_dq
            if not fix:  # without flags only a frame smaller than a tile leaves S1 empty
                for x in range(W):
                    if den[x] <= EPS:
                        fix = True
                        break
            if fix:
                xph = 0
                for x in range(W):
                    flags = np.uint32(0)
                    if den[x] <= EPS:  # no usable sample in S1: its flags, and S2
                        flags = orf[x]
                        ok_ppi = use_ppi and ppi_ok[y, x]
                        if ok_ppi:
                            est = _wide(raw, dq, ppi, level, True, y, x, lat_r, lat_c, j0, j1,
                                        ph, pw, False) + level * ppi[y, x]
                        else:
                            est = _wide(raw, dq, ppi, level, False, y, x, lat_r, lat_c, j0,
                                        j1, ph, pw, True)
                        if est != est:
                            flags |= _DO_NOT_USE
                            missing += 1
                        cube[y, x, b] = est
                    if has_dq and band_of[yph, xph] == b:
                        flags |= dq[y, x]
                    if flags:
                        cube_dq[y, x, b] = flags
                    xph += 1
                    if xph == pw:
                        xph = 0
            if has_alpha:
                for x in range(W):
                    a = amax[x]
                    if has_common:
                        a = max(a, common[y, x])
                    cube_alpha[y, x, b] = a if a > -np.inf else 0.0
    return missing


_interpolate = Kernel(_interpolate_rows, 0)


def interpolate_bands(raw, dq, alpha, common, ppi, ppi_ok, levels, lattices, band_of, period,
                      cube, cube_dq, cube_alpha):
    """Run the kernel; optional inputs (``dq``, ``alpha``, ``common``, ``ppi``) may be None.

    Parameters
    ----------
    raw : (H, W) float32, finite
    dq : (H, W) uint32 or None (no flagged sample)
    alpha : (H, W) float32 or None
    common : (H, W) float32 or None
        A per-pixel floor of the alpha of every band (PPID: the max alpha under the PPI window).
    ppi, ppi_ok : (H, W) float32 and bool, or None (bilinear)
    levels : (B,) float64, the PPI scale of each band
    lattices : list of B lists of (row, col): first sample row/column of each pattern position
    band_of : (ph, pw) int64, band of each (row % ph, col % pw)
    period : (ph, pw)
    cube : (H, W, B) float32, out
    cube_dq : (H, W, B) uint32, zero-initialised out (only flagged values are written)
    cube_alpha : (H, W, B) float32 out, or None

    Returns the number of values whose wide support has no usable sample: they are NaN (fill
    them with the band median).
    """
    H, W = raw.shape
    dummy_f = np.zeros((1, 1), np.float32)
    if ppi is not None and ppi_ok is None:
        ppi_ok = np.ones((H, W), np.bool_)
    lat_r = np.array([r for lat in lattices for r, _ in lat], np.int64)
    lat_c = np.array([c for lat in lattices for _, c in lat], np.int64)
    lat_start = np.cumsum([0] + [len(lat) for lat in lattices]).astype(np.int64)
    return _interpolate(
        raw, np.zeros((H, W), np.uint32) if dq is None else dq, dq is not None,
        dummy_f if alpha is None else alpha, alpha is not None,
        dummy_f if common is None else common, common is not None,
        np.zeros((H, W), np.float32) if ppi is None else ppi,
        np.zeros((H, W), np.bool_) if ppi_ok is None else ppi_ok, ppi is not None,
        np.asarray(levels, np.float64), lat_r, lat_c, lat_start,
        np.ascontiguousarray(band_of, np.int64), int(period[0]), int(period[1]),
        cube, cube_dq, np.zeros((1, 1, 1), np.float32) if cube_alpha is None else cube_alpha)
