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
_DO_NOT_USE = np.uint32(DQ.DO_NOT_USE)
_JIT = {**JIT_OPTIONS, "cache": False}


@njit(**_JIT)
def _wide_columns(raw, dq, ppi, level, use_ppi, y, r_first, c0, ph, pw, out_num, out_raw,
                  out_den):
    """The twice-wide tent (S2) down one lattice's columns ``c0 + k pw`` at row ``y``: the
    weighted sums of its usable samples (``v - level ppi`` in ``out_num`` when ``use_ppi``,
    the raw values in ``out_raw``) and their weights, at index ``k + 2`` (two zero columns of
    padding on each side)."""
    H, W = raw.shape
    nk = (W - c0 + pw - 1) // pw
    out_num[:nk + 4] = 0.0
    out_raw[:nk + 4] = 0.0
    out_den[:nk + 4] = 0.0
    ry0 = y - ((y - r_first) % ph)
    for t in range(-1, 3):
        ys = ry0 + t * ph
        wy = 1.0 - abs(y - ys) / (2.0 * ph)
        if ys < 0 or ys >= H or wy <= 0.0:
            continue
        for k in range(nk):
            xs = c0 + k * pw
            g = wy if dq[ys, xs] == 0 else 0.0
            v = np.float64(raw[ys, xs])
            out_raw[k + 2] += g * v
            if use_ppi:
                v -= level * ppi[ys, xs]
            out_num[k + 2] += g * v
            out_den[k + 2] += g


def _interpolate_rows(raw, dq, has_dq, alpha, has_alpha, common, has_common, ppi, ppi_ok,
                      use_ppi, levels, lat_r, lat_c, lat_start, ph, pw, wide_col, wide_w,
                      cube, cube_dq, cube_alpha, missing_rows):
    """Fill ``cube`` (H, W, B) and, where present, ``cube_dq`` and ``cube_alpha``.

    ``lat_r/lat_c`` are the first sample row/column (0 <= r < ph, 0 <= c < pw, offset
    included) of each pattern position; those of band b are ``lat_start[b]:lat_start[b+1]``.
    Returns the number of values left NaN (no usable sample within twice the tile); their
    rows and bands are marked in ``missing_rows`` (H, B) bool. ``wide_col[j, x]`` is the
    padded index of the leftmost of the four S2 columns of lattice ``j`` at column ``x`` and
    ``wide_w[j, x]`` their tent weights (0 for a column outside the tent).

    Per output row and band: a vertical pass blends the two sample rows of each lattice at
    its columns (sums over usable samples only, their weight, the OR of the flags, the max
    alpha), a horizontal pass per column phase blends two neighbouring columns into per-pixel
    sums, and a final pass divides and writes the band's values and alpha, counting the
    values whose S1 has no usable sample. These loops are branch-free and vectorise. Only
    for those values (a few percent) is the twice-wide tent evaluated: its vertical pass for
    the row, then a per-value horizontal blend. The DQ plane is written sparsely (the samples'
    own flags at their sites, the flags of S1 where S1 has no usable sample).
    """
    H, W = raw.shape
    B = lat_start.shape[0] - 1
    n_lat = 1
    for b in range(B):
        n_lat = max(n_lat, lat_start[b + 1] - lat_start[b])
    nk_max = W // pw + 3  # lattice columns (at most ceil(W / pw)) plus padding
    need_raw = use_ppi and has_dq  # the plain bilinear value where the PPI is undefined
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
        empty = np.empty(W, np.int64)
        wnum = np.empty((n_lat, nk_max + 2))
        wraw = np.empty((n_lat, nk_max + 2))
        wden = np.empty((n_lat, nk_max + 2))
        yph = y % ph
        for b in range(B):
            level = levels[b]
            j0, j1 = lat_start[b], lat_start[b + 1]
            num[:] = 0.0
            den[:] = 0.0
            if need_raw:
                nraw[:] = 0.0
            if has_dq:
                orf[:] = 0
            if has_alpha:
                amax[:] = -np.inf
            for j in range(j0, j1):
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
                    if has_dq:
                        g0 = w0 if dq[r0, xs] == 0 else 0.0
                        g1 = w1 if dq[r1, xs] == 0 else 0.0
                        f0 = dq[r0, xs] if w0 > 0.0 else np.uint32(0)
                        f1 = dq[r1, xs] if w1 > 0.0 else np.uint32(0)
                        vor[k + 1] = f0 | f1
                    if need_raw:
                        vraw[k + 1] = g0 * v0 + g1 * v1
                    if use_ppi:
                        v0 -= level * ppi[r0, xs]
                        v1 -= level * ppi[r1, xs]
                    vnum[k + 1] = g0 * v0 + g1 * v1
                    vden[k + 1] = g0 + g1
                if has_alpha:
                    for k in range(nk):
                        xs = c0 + k * pw
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
                        den[x] += wl * vden[k] + wr * vden[k + 1]
                    if need_raw:
                        for k in range(k_lo, k_hi):
                            x = x0 + k * pw
                            nraw[x] += wl * vraw[k] + wr * vraw[k + 1]
                    if has_dq:
                        for k in range(k_lo, k_hi):
                            x = x0 + k * pw
                            orf[x] |= vor[k] | (vor[k + 1] if p > 0 else np.uint32(0))
                    if has_alpha:
                        for k in range(k_lo, k_hi):
                            x = x0 + k * pw
                            a = max(vmax[k], vmax[k + 1]) if p > 0 else vmax[k]
                            amax[x] = max(amax[x], a)
            # final: divide and write; list the values whose S1 has no usable sample
            n_empty = 0
            for x in range(W):
                d = den[x]
                est = num[x] / d
                if use_ppi:
                    est += level * ppi[y, x]
                    if need_raw:
                        est = est if ppi_ok[y, x] else nraw[x] / d
                cube[y, x, b] = est
                n_empty += d <= EPS
            if has_alpha:
                for x in range(W):
                    a = amax[x]
                    if has_common:
                        a = max(a, common[y, x])
                    cube_alpha[y, x, b] = a if a > -np.inf else 0.0
            if has_dq:  # the samples' own flags at their sites
                for j in range(j0, j1):
                    if lat_r[j] == yph:
                        for xs in range(lat_c[j], W, pw):
                            cube_dq[y, xs, b] = dq[y, xs]
            if n_empty:  # no usable sample in S1: its flags, and the estimate from S2
                n_empty = 0
                for x in range(W):
                    if den[x] <= EPS:
                        empty[n_empty] = x
                        n_empty += 1
                for j in range(j0, j1):
                    _wide_columns(raw, dq, ppi, level, use_ppi, y, lat_r[j], lat_c[j], ph, pw,
                                  wnum[j - j0], wraw[j - j0], wden[j - j0])
                for i in range(n_empty):
                    x = empty[i]
                    n2 = r2 = d2 = 0.0
                    for j in range(j0, j1):
                        c = wide_col[j, x]
                        cn, cr, cd = wnum[j - j0], wraw[j - j0], wden[j - j0]
                        for s in range(4):
                            w = wide_w[j, x, s]
                            n2 += w * cn[c + s]
                            r2 += w * cr[c + s]
                            d2 += w * cd[c + s]
                    flags = orf[x]
                    if d2 <= EPS:
                        est = np.nan
                        flags |= _DO_NOT_USE
                        missing += 1
                        missing_rows[y, b] = True
                    elif use_ppi and ppi_ok[y, x]:
                        est = n2 / d2 + level * ppi[y, x]
                    else:
                        est = r2 / d2
                    cube[y, x, b] = est
                    cube_dq[y, x, b] |= flags
    return missing


_interpolate = Kernel(_interpolate_rows, 0)


def _wide_taps(lat_c, W, pw):
    """Per lattice and column: the padded index of the first of the four lattice columns the
    twice-wide tent can reach (sample column at or left of x, minus one, plus two of padding)
    and their weights ``1 - |x - xs| / (2 pw)`` (0 where not positive)."""
    x = np.arange(W)
    m = (x[None, :] - lat_c[:, None]) // pw  # sample column at or left of x (may be -1)
    p = x[None, :] - lat_c[:, None] - m * pw
    s = np.arange(-1, 3)
    w = 1.0 - np.abs(p[..., None] - s * pw) / (2.0 * pw)
    return np.ascontiguousarray(m + 1, np.int64), np.ascontiguousarray(np.maximum(w, 0.0))


def interpolate_bands(raw, dq, alpha, common, ppi, ppi_ok, levels, lattices, period,
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
    period : (ph, pw)
    cube : (H, W, B) float32, out
    cube_dq : (H, W, B) uint32, zero-initialised out (only flagged values are written)
    cube_alpha : (H, W, B) float32 out, or None

    Returns ``(H, B)`` bool: the rows and bands holding values whose wide support has no usable
    sample; those values are NaN (fill them with the band median).
    """
    H, W = raw.shape
    dummy_f = np.zeros((1, 1), np.float32)
    if ppi is not None and ppi_ok is None:
        ppi_ok = np.ones((H, W), np.bool_)
    lat_r = np.array([r for lat in lattices for r, _ in lat], np.int64)
    lat_c = np.array([c for lat in lattices for _, c in lat], np.int64)
    lat_start = np.cumsum([0] + [len(lat) for lat in lattices]).astype(np.int64)
    missing_rows = np.zeros((H, len(lattices)), np.bool_)
    wide_col, wide_w = _wide_taps(lat_c, W, int(period[1]))
    _interpolate(
        raw, np.zeros((H, W), np.uint32) if dq is None else dq, dq is not None,
        dummy_f if alpha is None else alpha, alpha is not None,
        dummy_f if common is None else common, common is not None,
        np.zeros((H, W), np.float32) if ppi is None else ppi,
        np.zeros((H, W), np.bool_) if ppi_ok is None else ppi_ok, ppi is not None,
        np.asarray(levels, np.float64), lat_r, lat_c, lat_start,
        int(period[0]), int(period[1]), wide_col, wide_w,
        cube, cube_dq, np.zeros((1, 1, 1), np.float32) if cube_alpha is None else cube_alpha,
        missing_rows)
    return missing_rows
