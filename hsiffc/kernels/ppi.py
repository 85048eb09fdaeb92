"""Compiled kernel of the pseudo-panchromatic image (PPI) of a mosaic frame.

This is the implementation behind :func:`hsiffc.reconstruct.prepare.pseudo_panchromatic`:
flagged samples replaced by the tent-weighted mean of their usable same-band neighbours one
tile away, every sample divided by its band's level, then a separable weighted average over a
tile-sized window with the frame extended by whole tiles (index maps ``rows``/``cols``). Two
passes parallel over rows (horizontal, then vertical); sums in float64.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from .launch import Kernel

__all__ = ["ppi_image"]


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
        xph = 0
        for x in range(W):
            inv = inv_level[band_of[yph, xph]]
            xph = xph + 1 if xph + 1 < pw else 0
            if not has_dq or dq[y, x] == 0:
                vals[y, x] = raw[y, x] * inv
                wts[y, x] = 1.0
                continue
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
    hnum = np.empty((H, W))
    hden = np.empty((H, W))
    for y in prange(H):  # horizontal window sums
        for x in range(W):
            n = 0.0
            d = 0.0
            for t in range(kx.size):
                c = cols[x + t]
                w = kx[t] * np.float64(wts[y, c])
                n += w * vals[y, c]
                d += w
            hnum[y, x] = n
            hden[y, x] = d
    for y in prange(H):  # vertical window sums and the ratio
        for x in range(W):
            n = 0.0
            d = 0.0
            for t in range(ky.size):
                r = rows[y + t]
                n += ky[t] * hnum[r, x]
                d += ky[t] * hden[r, x]
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
