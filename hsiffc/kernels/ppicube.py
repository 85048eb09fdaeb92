"""Compiled kernels of the fast full-resolution-PPI methods ("ppid_edge", "ri").

The implementation behind those methods of :func:`hsiffc.reconstruct.demosaic`, for layouts
with one sample of each band per tile (every IMEC and most other mosaics; a band repeated in
the tile takes :mod:`hsiffc.kernels.refined`). Three passes, each parallel over rows:

* :func:`fill_sparse`: the flagged samples of a frame (flat indices) replaced, in a copy, by
  the tent-weighted mean of their usable same-band neighbours one tile away (the PPI's fill,
  :mod:`hsiffc.kernels.ppi`), NaN where none is (the caller fills those with the band
  median); every method on a full-resolution PPI starts from it.
* :func:`edge_ppi`: the edge-sensitive full-resolution PPI of
  :func:`hsiffc.kernels.refined.refine_ppi` (edge weights on, none stored) and, in the same
  pass, the difference plane ``raw - l_b PPI`` (``l_b`` the level of the pixel's band).
* :func:`cube_of_planes`: every band at every pixel, ``A_b(p) PPI(p) + R_b(p)``, with ``R_b``
  (``A_b``) the tent (bilinear) interpolation of the plane ``R`` (``A``) over band ``b``'s
  samples; without ``A`` the band level ``l_b`` stands in for it (PPID: ``R`` is the
  difference plane). The tent of half-width one tile covers two sample rows and two sample
  columns: per output row the two sample rows of each row phase are blended once for every
  band that shares the phase (a row of ``W`` values, padded by one tile each side so that the
  blend of two columns needs no border test: a missing column repeats its neighbour, the
  normalised convolution's value at the border), then each value is two loads and a blend
  from that row, written band-fastest into the cube row, which is contiguous. The DQ row is
  zeroed in the same pass.

Arithmetic is float32 (the budget of :mod:`hsiffc.kernels.demosaic`: the error scales with
the frame, far below a sensor's read noise).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .launch import JIT_OPTIONS, Kernel, cached_jit
from .ppi import neighbour_offsets, pixel_neighbour_sums
from .refined import refine_pixel, edge_term

__all__ = ["cube_of_planes", "edge_ppi", "fill_sparse", "flagged_indices", "spectral_difference"]

_JIT = {**JIT_OPTIONS, "cache": False}
_ROWS = 8  # output rows per parallel task of the cube pass


@cached_jit
def _flat_flagged(dq, out):
    flat = dq.reshape(dq.size)
    n = 0
    for i in range(flat.size):  # branch-free
        out[n] = i
        n += flat[i] != 0
    return n


def flagged_indices(dq):
    """(n,) int64: the flat indices of the non-zero values of ``dq`` (as ``np.flatnonzero``,
    a quarter of its time on a frame with few flags)."""
    dq = np.ascontiguousarray(dq)
    out = np.empty(dq.size + 1, np.int64)
    return out[:_flat_flagged(dq, out)].copy()


def _fill_loop(raw, dq, flat, ph, pw, out):
    """``out`` (a copy of ``raw``) at the flagged flat indices ``flat``: the neighbour mean."""
    W = raw.shape[1]
    offs = neighbour_offsets(ph, pw)
    for i in prange(flat.shape[0]):
        y, x = flat[i] // W, flat[i] % W
        s, w = pixel_neighbour_sums(raw, dq, np.int64(y), np.int64(x), offs)
        out[y, x] = np.float32(s / w) if w > 0.0 else np.float32(np.nan)


_fill = Kernel(_fill_loop, 2, parallel_min=1 << 16)


def fill_sparse(raw, dq, flat, ph, pw):
    """A copy of ``raw`` (H, W) float32 with every sample flagged in ``dq`` (flat indices
    ``flat``, int64) replaced by its usable same-band neighbours' tent-weighted mean (NaN
    where it has none); ``raw`` itself when ``dq`` is None."""
    if dq is None:
        return raw
    out = raw.copy()
    if flat.size:
        _fill(raw, dq, flat, int(ph), int(pw), out)
    return out


def _edge_ppi_loop(raw, mbar, lev_row, eps, ph, pw, ppi, diff):
    """The edge-sensitive PPI into ``ppi`` and ``raw - l PPI`` into ``diff`` (H, W); ``lev_row``
    (ph, W) float32: the level of the band of every (row phase, column)."""
    H, W = raw.shape
    dummy = np.zeros((1, 1, 9), np.float32)
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    for y in prange(H):
        lr = lev_row[y % ph]
        interior = y >= ph and y < H - ph and W > 2 * pw
        x_lo, x_hi = (pw, W - pw) if interior else (0, 0)
        for x in range(W):
            if x >= x_lo and x < x_hi:
                continue
            v = refine_pixel(raw, mbar, np.int64(y), np.int64(x), raw[y, x], mbar[y, x], lr[x],
                              True, eps, ph, pw, dummy, False)
            ppi[y, x] = v
            diff[y, x] = raw[y, x] - lr[x] * v
        if not interior:
            continue
        # the interior: every neighbour row read through a view starting at its first
        # column, indexed from 0 (an index below zero would keep numba's wraparound check in
        # the loop, which then is not vectorised)
        a, b, c = x_lo - pw, x_lo, x_lo + pw
        ru0, ru1, ru2 = raw[y - ph, a:], raw[y - ph, b:], raw[y - ph, c:]
        mu0, mu1, mu2 = mbar[y - ph, a:], mbar[y - ph, b:], mbar[y - ph, c:]
        r0, r1, r2 = raw[y, a:], raw[y, b:], raw[y, c:]
        m0, m1, m2 = mbar[y, a:], mbar[y, b:], mbar[y, c:]
        rd0, rd1, rd2 = raw[y + ph, a:], raw[y + ph, b:], raw[y + ph, c:]
        md0, md1, md2 = mbar[y + ph, a:], mbar[y + ph, b:], mbar[y + ph, c:]
        lv, out, dout = lr[b:], ppi[y, b:], diff[y, b:]
        for i in range(x_hi - x_lo):
            v, mp, lev = r1[i], m1[i], lv[i]
            il = np.float32(1.0) / lev
            _, w0, n0 = edge_term(quarter, ru0[i], mu0[i], v, mp, lev, il, eps)
            _, w1, n1 = edge_term(half, ru1[i], mu1[i], v, mp, lev, il, eps)
            _, w2, n2 = edge_term(quarter, ru2[i], mu2[i], v, mp, lev, il, eps)
            _, w3, n3 = edge_term(half, r0[i], m0[i], v, mp, lev, il, eps)
            _, w5, n5 = edge_term(half, r2[i], m2[i], v, mp, lev, il, eps)
            _, w6, n6 = edge_term(quarter, rd0[i], md0[i], v, mp, lev, il, eps)
            _, w7, n7 = edge_term(half, rd1[i], md1[i], v, mp, lev, il, eps)
            _, w8, n8 = edge_term(quarter, rd2[i], md2[i], v, mp, lev, il, eps)
            num = ((n0 + n1) + (n2 + n3)) + ((n5 + n6) + (n7 + n8))
            den = ((w0 + w1) + (w2 + w3)) + ((w5 + w6) + (w7 + w8))
            p = (v - num / den) * il
            out[i] = p
            dout[i] = v - lev * p


_edge = Kernel(_edge_ppi_loop, 6)


def edge_ppi(raw, mbar, band_of, levels, eps):
    """The edge-sensitive PPI and the difference plane, two (H, W) float32 planes, of a frame
    without flagged samples; ``band_of`` (ph, pw) the band of each tile position, ``levels``
    (B,) the band levels, ``eps`` the edge weights' floor (frame units)."""
    H, W = raw.shape
    ph, pw = band_of.shape
    lev = np.asarray(levels, np.float32)
    lev_row = np.ascontiguousarray(lev[np.asarray(band_of)[:, np.arange(W) % pw]])
    ppi = np.empty((H, W), np.float32)
    diff = np.empty((H, W), np.float32)
    _edge(raw, mbar, lev_row, np.float32(eps), int(ph), int(pw), ppi, diff)
    return ppi, diff


@njit(**_JIT)
def _cube_block(blk, res, ppi, levels, band_r, band_c, ph, pw, cube, cube_dq):
    """Output rows ``blk * _ROWS`` on of :func:`_cube_rows`.

    Per row: the PPI split by column phase (``pq[q, m]`` = ``ppi[y, q + m pw]``); per band its
    lattice row ``vl`` (the vertical tent blend of its two sample rows at its sample columns,
    padded by a repeat of the first and last column: the normalised tent's value beyond the
    border); then per distance ``d`` from the sample column at or left of ``x`` one contiguous
    loop over the tiles, ``vl[K] + (d / pw) (vl[K + 1] - vl[K]) + l_b ppi``, stored into the
    cube row (band-fastest) with a stride of one tile."""
    H, W = res.shape
    B = levels.shape[0]
    n_t = (W + pw - 1) // pw
    pq = np.empty((pw, n_t), np.float32)
    vl = np.empty(n_t + 2, np.float32)
    tw = np.empty(pw, np.float32)
    for d in range(pw):
        tw[d] = np.float32(d / pw)
    for y in range(blk * _ROWS, min(H, blk * _ROWS + _ROWS)):
        p_row = ppi[y]
        for q in range(pw):
            pr = pq[q]
            for m in range((W - q + pw - 1) // pw):
                pr[m] = p_row[q + m * pw]
        out = cube[y].reshape(W * B)
        dq_row = cube_dq[y].reshape(W * B)
        for i in range(W * B):
            dq_row[i] = 0
        for b in range(B):
            r, c = band_r[b], band_c[b]
            lev = levels[b]
            ry0 = y - ((y - r) % ph)
            ry1 = ry0 + ph
            n_b = (W - c + pw - 1) // pw  # sample columns of the band
            if ry0 < 0 or ry0 == y or ry1 >= H:  # one sample row (its own, or the border)
                src = res[ry1] if ry0 < 0 else res[ry0]
                s0 = src[c:]
                for k in range(n_b):
                    vl[k + 1] = s0[k * pw]
            else:
                w1 = np.float32((y - ry0) / ph)
                w0 = np.float32(1.0) - w1
                a0, a1 = res[ry0, c:], res[ry1, c:]
                for k in range(n_b):
                    vl[k + 1] = w0 * a0[k * pw] + w1 * a1[k * pw]
            vl[0] = vl[1]
            vl[n_b + 1] = vl[n_b]
            for d in range(pw):
                x0 = (c + d) % pw  # the first column at distance d, its phase
                k0 = (x0 - c - d) // pw + 1  # its left sample column in vl (0: beyond)
                t = tw[d]
                pr = pq[x0]
                ob = out[x0 * B + b:]
                step = pw * B
                v0 = vl[k0:]
                v1 = vl[k0 + 1:]
                for m in range((W - x0 + pw - 1) // pw):
                    ob[m * step] = v0[m] + t * (v1[m] - v0[m]) + lev * pr[m]


def _cube_rows(res, ppi, levels, band_r, band_c, ph, pw, cube, cube_dq):
    """Fill ``cube`` (H, W, B) and zero ``cube_dq`` (module docstring)."""
    H = res.shape[0]
    for blk in prange((H + _ROWS - 1) // _ROWS):
        _cube_block(np.int64(blk), res, ppi, levels, band_r, band_c, ph, pw, cube, cube_dq)


_cube = Kernel(_cube_rows, 7)


def cube_of_planes(res, ppi, levels, band_rc, period, cube, cube_dq):
    """Fill ``cube`` (H, W, B) float32 with ``l_b PPI + R_b`` (module docstring) and zero
    ``cube_dq`` (H, W, B).

    Parameters
    ----------
    res : (H, W) float32, the plane ``R`` (every sample finite)
    ppi : (H, W) float32
    levels : (B,) band levels
    band_rc : (B, 2) int, the first sample (row, column) of each band (``0 <= row < ph``,
        ``0 <= column < pw``)
    period : (ph, pw)
    """
    rc = np.asarray(band_rc, np.int64)
    _cube(res, ppi, np.asarray(levels, np.float32), np.ascontiguousarray(rc[:, 0]),
          np.ascontiguousarray(rc[:, 1]), int(period[0]), int(period[1]), cube, cube_dq)


def _sd_loop(raw, prev, band_r, band_c, band_of, ph, pw, out):
    """One spectral-difference step (:func:`spectral_difference`) into ``out`` (H, W, B).
    The tent's rows are chosen per output row and band, its columns per column phase and band
    (tables), with the weights normalised where a row or column is outside the frame or has
    weight 0, so that each value is four terms without a division."""
    H, W = raw.shape
    B = band_r.shape[0]
    dtab = np.empty((pw, B), np.int64)  # distance of x from b's sample column at or left
    wtab = np.empty((pw, B), np.float32)
    for q in range(pw):
        for b in range(B):
            dtab[q, b] = (q - band_c[b]) % pw
            wtab[q, b] = np.float32(dtab[q, b] / pw)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y in prange(H):
        yph = y % ph
        o = out[y]
        r0s = np.empty(B, np.int64)
        r1s = np.empty(B, np.int64)
        wy0s = np.empty(B, np.float32)
        wy1s = np.empty(B, np.float32)
        for b in range(B):
            r0 = y - ((y - band_r[b]) % ph)
            a1 = np.float32((y - r0) / ph)
            r1 = r0 + ph
            if r0 < 0:
                r0s[b], r1s[b], wy0s[b], wy1s[b] = r1, r1, zero, one
            elif r1 >= H or r0 == y:
                r0s[b], r1s[b], wy0s[b], wy1s[b] = r0, r0, one, zero
            else:
                r0s[b], r1s[b], wy0s[b], wy1s[b] = r0, r1, one - a1, a1
        for x in range(W):
            q = x % pw
            c = band_of[yph, q]
            v = raw[y, x]
            for b in range(B):
                if b == c:
                    o[x, b] = v
                    continue
                c0 = x - dtab[q, b]
                c1 = c0 + pw
                wx1 = wtab[q, b]
                wx0 = one - wx1
                if c0 < 0:
                    c0, wx0, wx1 = c1, zero, one
                elif c1 >= W or c0 == x:
                    c1, wx0, wx1 = c0, one, zero
                R0, R1 = r0s[b], r1s[b]
                t0 = wx0 * (raw[R0, c0] - prev[R0, c0, c]) + wx1 * (raw[R0, c1] - prev[R0, c1, c])
                t1 = wx0 * (raw[R1, c0] - prev[R1, c0, c]) + wx1 * (raw[R1, c1] - prev[R1, c1, c])
                o[x, b] = v + (wy0s[b] * t0 + wy1s[b] * t1)


_sd = Kernel(_sd_loop, 7)


def spectral_difference(raw, prev, band_rc, band_of, out):
    """One step of the spectral-difference interpolation (Brauers and Aach 2006), every band
    at every pixel into ``out`` (H, W, B) float32: at pixel ``x`` of band ``c``, band ``b`` is
    ``raw(x)`` plus the tent (bilinear) interpolation over ``b``'s samples ``s`` of
    ``raw(s) - prev_c(s)``, the band's difference from band ``c`` at its own sites, ``prev``
    (H, W, B) the previous estimate of every band; band ``c`` itself is ``raw(x)``.

    ``raw`` (H, W) float32 without flagged samples; ``band_rc`` (B, 2) the first sample (row,
    column) of each band (one per tile); ``band_of`` (ph, pw) the band of each tile position."""
    rc = np.asarray(band_rc, np.int64)
    bo = np.ascontiguousarray(band_of, np.int64)
    _sd(raw, prev, np.ascontiguousarray(rc[:, 0]), np.ascontiguousarray(rc[:, 1]), bo,
        int(bo.shape[0]), int(bo.shape[1]), out)
