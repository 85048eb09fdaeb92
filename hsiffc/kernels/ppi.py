"""Compiled kernel of the pseudo-panchromatic image (PPI) of a mosaic frame.

This is the implementation behind :func:`hsiffc.reconstruct.prepare.pseudo_panchromatic`:
flagged samples replaced by the tent-weighted mean of their usable same-band neighbours one
tile away, every sample divided by its band's level, then a separable weighted average over a
tile-sized window with the frame extended by whole tiles (index maps ``rows``/``cols``). Two
passes parallel over rows: the samples, then the window sums (horizontal, then vertical) of a
block of rows at a time, so that the float64 horizontal sums stay in a block-sized buffer
instead of two frame-sized ones; sums in float64, in the same order as a frame-wide
horizontal pass followed by a vertical one.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import Kernel

__all__ = ["ppi_image"]

_ROWS = 16  # output rows per parallel task of the window pass


def _ppi_rows(raw, dq, has_dq, band_of, inv_level, rows, cols, kx, ky, ppi, ok):
    """Fill ``ppi`` (H, W) float32 and ``ok`` (H, W) bool (weight sum above 1e-6).

    ``band_of`` (ph, pw): band of each (row % ph, col % pw); ``inv_level`` (B,) float32;
    ``rows`` (H + 2 my), ``cols`` (W + 2 mx): source row/column of each padded row/column;
    ``kx`` (2 mx + 1), ``ky`` (2 my + 1): the window's taps."""
    H, W = raw.shape
    ph, pw = band_of.shape
    vals = np.empty((H, W), np.float32)
    wts = np.empty((H, W), np.float32)
    for y in prange(H):  # samples: scaled to a common level, flagged ones filled from the lattice
        yph = y % ph
        for xph in range(pw):
            inv = inv_level[band_of[yph, xph]]
            for x in range(xph, W, pw):
                vals[y, x] = raw[y, x] * inv
                wts[y, x] = 1.0
        if not has_dq:
            continue
        for x in range(W):
            if dq[y, x] == 0:
                continue
            inv = inv_level[band_of[yph, x % pw]]
            acc = 0.0
            wsum = 0.0
            for dy in (-ph, 0, ph):
                for dx in (-pw, 0, pw):
                    ny, nx = y + dy, x + dx
                    if (dy == 0 and dx == 0) or ny < 0 or ny >= H or nx < 0 or nx >= W:
                        continue
                    if dq[ny, nx] == 0:
                        wt = 0.25 if (dy != 0 and dx != 0) else 0.5
                        acc += wt * raw[ny, nx]
                        wsum += wt
            if wsum > 0.0:
                vals[y, x] = np.float32(acc / wsum) * inv
                wts[y, x] = 1.0
            else:
                vals[y, x] = 0.0
                wts[y, x] = 0.0
    my = ky.size // 2
    mx = kx.size // 2
    for blk in prange((H + _ROWS - 1) // _ROWS):  # window sums, a block of rows at a time
        y0 = blk * _ROWS
        y1 = min(H, y0 + _ROWS)
        n_in = y1 - y0 + 2 * my
        hnum = np.empty((n_in, W))
        hden = np.empty((n_in, W))
        for i in range(n_in):  # horizontal sums of the input rows the block's windows reach
            r = rows[y0 + i]
            n_left = min(mx, W)
            right = max(W - mx, mx)
            for j in range(n_left + W - right):  # border columns, through the index map
                x = j if j < n_left else right + j - n_left
                n = 0.0
                d = 0.0
                for t in range(kx.size):
                    c = cols[x + t]
                    w = kx[t] * np.float64(wts[r, c])
                    n += w * vals[r, c]
                    d += w
                hnum[i, x] = n
                hden[i, x] = d
            for x in range(mx, W - mx):  # interior: cols[x + t] = x + t - mx
                n = 0.0
                d = 0.0
                for t in range(kx.size):
                    c = x + t - mx
                    w = kx[t] * np.float64(wts[r, c])
                    n += w * vals[r, c]
                    d += w
                hnum[i, x] = n
                hden[i, x] = d
        for y in range(y0, y1):  # vertical sums and the ratio
            for x in range(W):
                n = 0.0
                d = 0.0
                for t in range(ky.size):
                    n += ky[t] * hnum[y - y0 + t, x]
                    d += ky[t] * hden[y - y0 + t, x]
                good = d > 1e-6
                ppi[y, x] = n / d if good else 0.0
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
