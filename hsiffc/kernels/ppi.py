"""Compiled kernel of the pseudo-panchromatic image (PPI) of a mosaic frame.

This is the implementation behind :func:`hsiffc.reconstruct.prepare.pseudo_panchromatic`:
flagged samples replaced by the tent-weighted mean of their usable same-band neighbours one
tile away, every sample divided by its band's level, then a separable weighted average over a
tile-sized window with the frame extended by whole tiles (index maps ``rows``/``cols``). Two
passes parallel over rows: the samples, then the window sums (horizontal, then vertical) of a
block of rows at a time, so that the float64 horizontal sums stay in a block-sized buffer
instead of two frame-sized ones; sums in float64, in the same order as a frame-wide
horizontal pass followed by a vertical one. The window sums of 3 and 5 taps (periods 2 to 5)
are written out, one value per iteration with its taps in registers (vectorised); other sizes
loop over the taps outside and the pixels of a row inside. The flagged pixels of a row are
listed branch-free, and the neighbour sums that fill them are taken for the whole row, one
vectorised loop per neighbour, or pixel by pixel in a row with few of them.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .lattice import usable_weight
from .launch import JIT_OPTIONS, Kernel

__all__ = ["neighbour_offsets", "pixel_neighbour_sums", "ppi_image", "row_neighbour_sums"]

_ROWS = 16  # output rows per parallel task of the window pass
_JIT = {**JIT_OPTIONS, "cache": False}  # compiled into the cached kernel
_INL = {**_JIT, "inline": "always"}


def _ppi_rows(raw, dq, has_dq, band_of, inv_level, rows, cols, kx, ky, ppi, ok):
    """Fill ``ppi`` (H, W) float32 and ``ok`` (H, W) bool (weight sum above 1e-6).

    ``band_of`` (ph, pw): band of each (row % ph, col % pw); ``inv_level`` (B,) float32;
    ``rows`` (H + 2 my), ``cols`` (W + 2 mx): source row/column of each padded row/column;
    ``kx`` (2 mx + 1), ``ky`` (2 my + 1): the window's taps."""
    H, W = raw.shape
    ph, pw = band_of.shape
    vals = np.empty((H, W), np.float32)
    wts = np.empty((H, W), np.float32)
    offs = neighbour_offsets(ph, pw)
    inv_row = np.empty((ph, W), np.float32)  # 1 / level of the band of every (row phase, x)
    for yph in range(ph):
        for x in range(W):
            inv_row[yph, x] = inv_level[band_of[yph, x % pw]]
    for y in prange(H):  # samples: scaled to a common level, flagged ones filled from the lattice
        yph = y % ph
        row = np.int64(y)  # int64 for the calls below: numba types a parallel loop's index
        # uint64 and compiled each callee for both types (the serial build's is int64)
        for x in range(W):
            vals[y, x] = raw[y, x] * inv_row[yph, x]
            wts[y, x] = 1.0
        if not has_dq:
            continue
        fl_x = np.empty(W, np.int64)
        n_fl = 0
        for x in range(W):  # the flagged pixels of the row, listed branch-free
            fl_x[n_fl] = x
            n_fl += dq[y, x] != 0
        if n_fl == 0:
            continue
        acc = np.empty(W)
        wsum = np.empty(W)
        if 8 * n_fl < W:  # a few flagged pixels: their own sums (same terms, same order)
            for i in range(n_fl):
                x = fl_x[i]
                acc[x], wsum[x] = pixel_neighbour_sums(raw, dq, row, x, offs)
        else:  # many: the whole row, vectorised
            row_neighbour_sums(raw, dq, row, offs, acc, wsum)
        for i in range(n_fl):
            x = fl_x[i]
            if wsum[x] > 0.0:
                vals[y, x] = np.float32(acc[x] / wsum[x]) * inv_row[yph, x]
                wts[y, x] = 1.0
            else:
                vals[y, x] = 0.0
                wts[y, x] = 0.0
    my = ky.size // 2
    mx = kx.size // 2
    for blk in prange((H + _ROWS - 1) // _ROWS):  # window sums, a block of rows at a time
        _window_block(np.int64(blk), vals, wts, rows, cols, kx, ky, my, mx, ppi, ok)


@njit(**_JIT)
def neighbour_offsets(ph, pw):
    """(8, 2) int64: the (dy, dx) of a pixel's same-band neighbours one tile away, in the
    order their terms are summed (row above, own row, row below; left to right)."""
    offs = np.empty((8, 2), np.int64)
    n = 0
    for ty in range(3):
        for tx in range(3):
            if ty != 1 or tx != 1:
                offs[n, 0] = (ty - 1) * ph
                offs[n, 1] = (tx - 1) * pw
                n += 1
    return offs


@njit(**_JIT)
def row_neighbour_sums(raw, dq, y, offs, acc, wsum):
    """For every pixel of row ``y``: the tent-weighted sum of its usable same-band neighbours
    ``offs`` (:func:`neighbour_offsets`; 1/4 diagonal, 1/2 straight) and their weight. One
    contiguous (vectorised) loop per neighbour, every pixel of the row, in the order of a
    per-pixel loop over the neighbours; a flagged or outside neighbour adds exactly 0."""
    H, W = raw.shape
    acc[:] = 0.0
    wsum[:] = 0.0
    for n in range(offs.shape[0]):
        dy, dx = offs[n, 0], offs[n, 1]
        ny = y + dy
        x_lo = max(0, -dx)
        x_hi = min(W, W - dx)
        # outside the frame, or a frame narrower than the tile: no such neighbour
        if ny < 0 or ny >= H or x_hi <= x_lo:
            continue
        _add_neighbour(acc[x_lo:x_hi], wsum[x_lo:x_hi], raw[ny, x_lo + dx:x_hi + dx],
                       dq[ny, x_lo + dx:x_hi + dx], _neighbour_weight(dy, dx))


@njit(**_JIT)
def pixel_neighbour_sums(raw, dq, y, x, offs):
    """:func:`row_neighbour_sums` at one pixel ``(y, x)``: (sum, weight), the same terms added
    in the same order. Used for rows with few flagged pixels (under one in eight), where a
    whole-row pass would sum mostly unused neighbours."""
    H, W = raw.shape
    acc = 0.0
    wsum = 0.0
    for n in range(offs.shape[0]):
        dy, dx = offs[n, 0], offs[n, 1]
        ny, nx = y + dy, x + dx
        if ny < 0 or ny >= H or nx < 0 or nx >= W:
            continue
        g = usable_weight(_neighbour_weight(dy, dx), dq[ny, nx])
        acc += g * raw[ny, nx]
        wsum += g
    return acc, wsum


@njit(**_INL)
def _neighbour_weight(dy, dx):
    """The tent weight of a same-band neighbour one tile away: 1/4 diagonal, 1/2 straight."""
    return 0.25 if (dy != 0 and dx != 0) else 0.5


@njit(**_JIT)
def _add_neighbour(acc, wsum, r, f, wt):
    """``acc += g r`` and ``wsum += g`` with ``g = wt`` where ``f == 0``, else 0 (a function of
    its own: the same loop inline is not vectorised and is slower than the per-pixel
    branches it replaces)."""
    for i in range(acc.shape[0]):
        g = usable_weight(wt, f[i])
        acc[i] += g * r[i]
        wsum[i] += g


@njit(**_INL)
def _dot3(k0, k1, k2, v0, v1, v2):
    """``((0 + k0 v0) + k1 v1) + k2 v2``: a window sum in the order of a loop over its taps
    (scalars only, so that the loop that calls it vectorises)."""
    return ((0.0 + k0 * v0) + k1 * v1) + k2 * v2


@njit(**_INL)
def _dot5(k0, k1, k2, k3, k4, v0, v1, v2, v3, v4):
    """The five-tap window sum, in the same order as :func:`_dot3`."""
    return (_dot3(k0, k1, k2, v0, v1, v2) + k3 * v3) + k4 * v4


@njit(**_INL)
def _taps(k):
    """The taps of a 3- or 5-tap window as five scalars for :func:`_dot3` / :func:`_dot5`
    (zeros past the end, all zeros for other sizes, which do not use them)."""
    n = k.size
    return ((k[0], k[1], k[2], k[3], k[4]) if n == 5 else
            ((k[0], k[1], k[2], 0.0, 0.0) if n == 3 else (0.0, 0.0, 0.0, 0.0, 0.0)))


@njit(**_JIT)
def _window_block(blk, vals, wts, rows, cols, kx, ky, my, mx, ppi, ok):
    """The window sums of output rows ``blk * _ROWS`` on: horizontal sums of the input rows
    they reach, then vertical sums and the ratio. ``w v`` with ``w = kx wts`` equals ``kx v``
    (``wts`` is 0 or 1 and ``v`` is 0 where it is 0), so the numerator takes ``kx v`` and the
    denominator ``kx wts``. Every sum is taken in the order of a loop over the taps.

    Windows of 3 and 5 taps (periods 2 to 5: the usual mosaics) are written out, one value
    per iteration with its taps in registers (vectorised), with the same bits. Other sizes
    take a loop per tap that adds into the row (tap outer, pixel inner), indexed from the
    first interior pixel (an index below zero would keep numba's wraparound check in the
    loop)."""
    H, W = vals.shape
    y0 = blk * _ROWS
    y1 = min(H, y0 + _ROWS)
    n_in = y1 - y0 + 2 * my
    hnum = np.empty((n_in, W))
    hden = np.empty((n_in, W))
    nx = kx.size
    k0, k1, k2, k3, k4 = _taps(kx)
    n_left = min(mx, W)  # border columns: [0, n_left) and [right, W)
    right = max(W - mx, n_left)  # (a frame narrower than mx is all left border)
    for i in range(n_in):  # horizontal sums of the input rows the block's windows reach
        r = rows[y0 + i]
        hn = hnum[i]
        hd = hden[i]
        for j in range(n_left + W - right):  # border columns, through the index map
            x = j if j < n_left else right + j - n_left
            sn = 0.0
            sd = 0.0
            for t in range(nx):
                c = cols[x + t]
                sn += kx[t] * np.float64(vals[r, c])
                sd += kx[t] * np.float64(wts[r, c])
            hn[x] = sn
            hd[x] = sd
        # interior: cols[x + t] = x + t - mx (mx is 2 or 1 in the written-out forms: literal
        # bounds let LLVM drop numba's negative-index wraparound and vectorise)
        vr = vals[r]
        wr = wts[r]
        if nx == 5:
            for x in range(2, W - 2):
                hn[x] = _dot5(k0, k1, k2, k3, k4, np.float64(vr[x - 2]), np.float64(vr[x - 1]),
                              np.float64(vr[x]), np.float64(vr[x + 1]), np.float64(vr[x + 2]))
                hd[x] = _dot5(k0, k1, k2, k3, k4, np.float64(wr[x - 2]), np.float64(wr[x - 1]),
                              np.float64(wr[x]), np.float64(wr[x + 1]), np.float64(wr[x + 2]))
        elif nx == 3:
            for x in range(1, W - 1):
                hn[x] = _dot3(k0, k1, k2, np.float64(vr[x - 1]), np.float64(vr[x]),
                              np.float64(vr[x + 1]))
                hd[x] = _dot3(k0, k1, k2, np.float64(wr[x - 1]), np.float64(wr[x]),
                              np.float64(wr[x + 1]))
        else:
            hn_i = hn[mx:W - mx]  # x = mx + i: no index below zero to wrap around
            hd_i = hd[mx:W - mx]
            hn_i[:] = 0.0
            hd_i[:] = 0.0
            for t in range(nx):
                w = kx[t]
                vt = vals[r, t:]
                wt = wts[r, t:]
                for i in range(hn_i.size):
                    hn_i[i] += w * np.float64(vt[i])
                    hd_i[i] += w * np.float64(wt[i])
    ny = ky.size
    g0, g1, g2, g3, g4 = _taps(ky)
    n = np.empty(W)
    d = np.empty(W)
    for y in range(y0, y1):  # vertical sums and the ratio
        i = y - y0
        if ny == 5:
            a0, a1, a2, a3, a4 = hnum[i], hnum[i + 1], hnum[i + 2], hnum[i + 3], hnum[i + 4]
            b0, b1, b2, b3, b4 = hden[i], hden[i + 1], hden[i + 2], hden[i + 3], hden[i + 4]
            for x in range(W):
                n[x] = _dot5(g0, g1, g2, g3, g4, a0[x], a1[x], a2[x], a3[x], a4[x])
                d[x] = _dot5(g0, g1, g2, g3, g4, b0[x], b1[x], b2[x], b3[x], b4[x])
        elif ny == 3:
            a0, a1, a2 = hnum[i], hnum[i + 1], hnum[i + 2]
            b0, b1, b2 = hden[i], hden[i + 1], hden[i + 2]
            for x in range(W):
                n[x] = _dot3(g0, g1, g2, a0[x], a1[x], a2[x])
                d[x] = _dot3(g0, g1, g2, b0[x], b1[x], b2[x])
        else:
            n[:] = 0.0
            d[:] = 0.0
            for t in range(ny):
                w = ky[t]
                hn = hnum[i + t]
                hd = hden[i + t]
                for x in range(W):
                    n[x] += w * hn[x]
                    d[x] += w * hd[x]
        for x in range(W):
            good = d[x] > 1e-6
            ppi[y, x] = n[x] / d[x] if good else 0.0
            ok[y, x] = good


_ppi = Kernel(_ppi_rows, 0)


def ppi_image(raw, dq, band_of, inv_level, rows, cols, kx, ky):
    """The PPI (H, W) float32 and where it is defined (H, W) bool; ``dq`` may be None (no
    flagged sample). Arguments as in :func:`_ppi_rows`."""
    H, W = raw.shape
    ppi = np.empty((H, W), np.float32)
    ok = np.empty((H, W), np.bool_)
    _ppi(raw, np.zeros((1, 1), np.uint32) if dq is None else dq, dq is not None,
         np.ascontiguousarray(band_of, np.int64), np.asarray(inv_level, np.float32),
         np.asarray(rows, np.int64), np.asarray(cols, np.int64),
         np.asarray(kx, np.float64), np.asarray(ky, np.float64), ppi, ok)
    return ppi, ok
