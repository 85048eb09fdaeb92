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


@njit(**{**_JIT, "inline": "always"})  # inlined: a call passing arrays costs refcounting
def _add(j, xs, w, num, nraw, den, orf, amax, vnum, vraw, vden, vor, vmax, x):
    num[x] += w * vnum[xs]
    nraw[x] += w * vraw[xs]
    den[x] += w * vden[xs]
    orf[x] |= vor[xs]
    if vmax[xs] > amax[x]:
        amax[x] = vmax[xs]


@njit(**{**_JIT, "inline": "always"})
def _row_fast(raw, alpha, has_alpha, common, has_common, ppi, use_ppi, level, y, ry0, ry1,
              wy1, c0, pw, b, vk, mk, cube, cube_alpha):
    """One band of one output row from a single sample lattice with no flagged sample in
    its two rows: separable blends (vectorisable), no normalisation needed in the interior."""
    H, W = raw.shape
    nk = (W - c0 + pw - 1) // pw
    use0 = ry0 >= 0
    use1 = wy1 > 0.0 and ry1 < H
    w0 = (1.0 - wy1) if use0 else 0.0
    w1 = wy1 if use1 else 0.0
    norm = 1.0 / (w0 + w1)
    w0 *= norm
    w1 *= norm
    r0 = ry0 if use0 else ry1
    r1 = ry1 if use1 else r0
    for k in range(nk):
        xs = c0 + k * pw
        v0 = np.float64(raw[r0, xs])
        v1 = np.float64(raw[r1, xs])
        if use_ppi:
            v0 -= level * ppi[r0, xs]
            v1 -= level * ppi[r1, xs]
        vk[k] = w0 * v0 + w1 * v1
        if has_alpha:
            mk[k] = max(alpha[r0, xs], alpha[r1, xs])
    # the value at x: left of the first sample column that column, right of the last one
    # the last, in between the blend of the two around it (phase p: weights 1 - p/pw, p/pw)
    for x in range(min(c0, W)):
        cube[y, x, b] = vk[0]
    for p in range(pw):
        wr = p / pw
        wl = 1.0 - wr
        n_in = (W - c0 - p + pw - 1) // pw  # columns c0 + k pw + p inside the frame
        n_in = min(n_in, nk - 1) if p > 0 else n_in
        x0 = c0 + p
        if p == 0:
            for k in range(n_in):
                cube[y, x0 + k * pw, b] = vk[k]
        else:
            for k in range(n_in):
                cube[y, x0 + k * pw, b] = wl * vk[k] + wr * vk[k + 1]
            x = c0 + (nk - 1) * pw + p
            if x < W:
                cube[y, x, b] = vk[nk - 1]
    if use_ppi:
        for x in range(W):
            cube[y, x, b] += level * ppi[y, x]
    if has_alpha:
        for x in range(min(c0, W)):
            cube_alpha[y, x, b] = mk[0]
        for p in range(pw):
            n_in = (W - c0 - p + pw - 1) // pw
            n_in = min(n_in, nk - 1) if p > 0 else n_in
            x0 = c0 + p
            if p == 0:
                for k in range(n_in):
                    cube_alpha[y, x0 + k * pw, b] = mk[k]
            else:
                for k in range(n_in):
                    cube_alpha[y, x0 + k * pw, b] = max(mk[k], mk[k + 1])
                x = c0 + (nk - 1) * pw + p
                if x < W:
                    cube_alpha[y, x, b] = mk[nk - 1]
        if has_common:
            for x in range(W):
                cube_alpha[y, x, b] = max(cube_alpha[y, x, b], common[y, x])


def _interpolate_rows(raw, dq, has_dq, alpha, has_alpha, common, has_common, ppi, ppi_ok,
                      use_ppi, ppi_row_ok, levels, lat_r, lat_c, lat_start, band_of, ph, pw,
                      cube, cube_dq, cube_alpha):
    """Fill ``cube`` (H, W, B) and, where present, ``cube_dq`` and ``cube_alpha``.

    ``lat_r/lat_c`` are the first sample row/column (0 <= r < ph, 0 <= c < pw, offset
    included) of each pattern position; those of band b are ``lat_start[b]:lat_start[b+1]``.
    ``band_of`` is the (ph, pw) band of each (row % ph, col % pw) phase (offset included).
    Returns the number of values left NaN (no usable sample within twice the tile).
    """
    H, W = raw.shape
    B = lat_start.shape[0] - 1
    inv_pw = 1.0 / pw
    missing = 0
    for y in prange(H):
        vnum = np.zeros(W)
        vraw = np.zeros(W)
        vden = np.zeros(W)
        vor = np.zeros(W, np.uint32)
        vmax = np.full(W, -np.inf, np.float32)
        num = np.empty(W)
        nraw = np.empty(W)
        den = np.empty(W)
        orf = np.empty(W, np.uint32)
        amax = np.empty(W, np.float32)
        vk = np.empty(W // pw + 2)
        mk = np.empty(W // pw + 2, np.float32)
        yph = y % ph
        for b in range(B):
            level = levels[b]
            if lat_start[b + 1] - lat_start[b] == 1 and (not use_ppi or ppi_row_ok[y]):
                j = lat_start[b]
                ry0 = y - ((y - lat_r[j]) % ph)
                wy1 = (y - ry0) / ph
                ry1 = ry0 + ph
                clean = True
                if has_dq:
                    for xs in range(lat_c[j], W, pw):
                        if ((ry0 >= 0 and dq[ry0, xs] != 0)
                                or (wy1 > 0.0 and ry1 < H and dq[ry1, xs] != 0)):
                            clean = False
                            break
                if clean:
                    _row_fast(raw, alpha, has_alpha, common, has_common, ppi, use_ppi, level,
                              y, ry0, ry1, wy1, lat_c[j], pw, b, vk, mk, cube, cube_alpha)
                    continue
            num[:] = 0.0
            nraw[:] = 0.0
            den[:] = 0.0
            orf[:] = 0
            amax[:] = -np.inf
            for j in range(lat_start[b], lat_start[b + 1]):
                ry0 = y - ((y - lat_r[j]) % ph)  # sample row at or above y
                wy1 = (y - ry0) / ph
                wy0 = 1.0 - wy1
                ry1 = ry0 + ph
                use0 = ry0 >= 0
                use1 = wy1 > 0.0 and ry1 < H
                c0 = lat_c[j]
                # vertical blend of the two sample rows, at the lattice's columns
                for xs in range(c0, W, pw):
                    n_ = 0.0
                    r_ = 0.0
                    d_ = 0.0
                    f_ = np.uint32(0)
                    m_ = np.float32(-np.inf)
                    if use0:
                        if has_alpha:
                            m_ = max(m_, alpha[ry0, xs])
                        if has_dq and dq[ry0, xs] != 0:
                            f_ |= dq[ry0, xs]
                        else:
                            v = np.float64(raw[ry0, xs])
                            r_ += wy0 * v
                            n_ += wy0 * (v - level * ppi[ry0, xs] if use_ppi else v)
                            d_ += wy0
                    if use1:
                        if has_alpha:
                            m_ = max(m_, alpha[ry1, xs])
                        if has_dq and dq[ry1, xs] != 0:
                            f_ |= dq[ry1, xs]
                        else:
                            v = np.float64(raw[ry1, xs])
                            r_ += wy1 * v
                            n_ += wy1 * (v - level * ppi[ry1, xs] if use_ppi else v)
                            d_ += wy1
                    vnum[xs] = n_
                    vraw[xs] = r_
                    vden[xs] = d_
                    vor[xs] = f_
                    vmax[xs] = m_
                # horizontal blend of the two sample columns around each x
                for x in range(min(c0, W)):  # left of the first sample column
                    _add(j, c0, (x - c0 + pw) * inv_pw, num, nraw, den, orf, amax, vnum,
                         vraw, vden, vor, vmax, x)
                for xs in range(c0, W, pw):
                    has_next = xs + pw < W
                    for ph_x in range(pw):
                        x = xs + ph_x
                        if x >= W:
                            break
                        w1 = ph_x * inv_pw
                        _add(j, xs, 1.0 - w1, num, nraw, den, orf, amax, vnum, vraw, vden,
                             vor, vmax, x)
                        if ph_x > 0 and has_next:
                            _add(j, xs + pw, w1, num, nraw, den, orf, amax, vnum, vraw, vden,
                                 vor, vmax, x)
            j0, j1 = lat_start[b], lat_start[b + 1]
            xph = 0
            for x in range(W):
                ok_ppi = use_ppi and ppi_ok[y, x]
                flags = np.uint32(0)
                if den[x] > EPS:
                    if ok_ppi:
                        est = num[x] / den[x] + level * ppi[y, x]
                    elif use_ppi:
                        est = nraw[x] / den[x]
                    else:
                        est = num[x] / den[x]
                else:  # no usable sample in S1: its flags, and the wide tent (S2)
                    flags = orf[x]
                    if ok_ppi:
                        est = _wide(raw, dq, ppi, level, True, y, x, lat_r, lat_c, j0, j1,
                                    ph, pw, False) + level * ppi[y, x]
                    else:
                        est = _wide(raw, dq, ppi, level, False, y, x, lat_r, lat_c, j0, j1,
                                    ph, pw, True)
                    if est != est:
                        flags |= _DO_NOT_USE
                        missing += 1
                if has_dq and band_of[yph, xph] == b:
                    flags |= dq[y, x]
                cube[y, x, b] = est
                if flags:
                    cube_dq[y, x, b] = flags
                if has_alpha:
                    a = amax[x]
                    if has_common and common[y, x] > a:
                        a = common[y, x]
                    cube_alpha[y, x, b] = a if a > -np.inf else 0.0
                xph += 1
                if xph == pw:
                    xph = 0
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
        np.ones(H, np.bool_) if ppi_ok is None else ppi_ok.all(axis=1),
        np.asarray(levels, np.float64), lat_r, lat_c, lat_start,
        np.ascontiguousarray(band_of, np.int64), int(period[0]), int(period[1]),
        cube, cube_dq, np.zeros((1, 1, 1), np.float32) if cube_alpha is None else cube_alpha)
