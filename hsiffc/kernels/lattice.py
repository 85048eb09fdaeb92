"""A mosaic frame as its sample lattices, and the interpolation's sums over them.

A band's samples sit on lattices: one per position of the band in the tile, every ``ph``-th
row and ``pw``-th column from a first sample ``(lat_r, lat_c)``. :data:`split_lattices`
copies the frame's values, DQ and (PPID) pseudo-panchromatic image into one contiguous plane
per lattice, ``(n_lattices, ceil(H / ph), ceil(W / pw))`` with zeros beyond the frame. The
interpolation kernel (:mod:`hsiffc.kernels.demosaic`) then reads a lattice row as a
contiguous vector, which LLVM vectorises, where the frame holds it every ``pw``-th value.

The sums of the twice-wide tent (S2) over every column of a row are then contiguous loops
instead of per-value sums over the strided frame. Only frames with flagged samples are split:
without flags S2 is never needed.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .launch import JIT_OPTIONS, Kernel

__all__ = ["band_samples", "lattice_arrays", "split_lattices", "tent_sums", "usable_weight",
           "wide_column_sums"]

_JIT = {**JIT_OPTIONS, "cache": False}
_INL = {**_JIT, "inline": "always"}
_ALL = np.uint32(0xFFFFFFFF)


def lattice_arrays(lattices):
    """``(lat_r, lat_c, lat_start)`` (int64) of per-band lattice lists (``lattices[b]``: the
    first sample (row, col) of each position of band ``b`` in the tile): the lattices of band
    ``b`` are ``lat_start[b]:lat_start[b + 1]``, as the kernels take them."""
    lat_r = np.array([r for lat in lattices for r, _ in lat], np.int64)
    lat_c = np.array([c for lat in lattices for _, c in lat], np.int64)
    lat_start = np.cumsum([0] + [len(lat) for lat in lattices]).astype(np.int64)
    return lat_r, lat_c, lat_start


def _split_loop(raw, dq, ppi, use_ppi, lat_r, lat_c, ph, pw, lr, lf, lp):
    """``lr[j, i, k] = raw[lat_r[j] + i ph, lat_c[j] + k pw]`` for the samples in the frame,
    likewise ``lf`` from ``dq`` and (``use_ppi``) ``lp`` from ``ppi``; the rest of the planes
    is left as the caller allocated it (zeros). Parallel over the frame's rows, so that each
    row is read once, by every lattice on it, while it is in cache."""
    H, W = raw.shape
    for ys in prange(H):
        for j in range(lat_r.shape[0]):
            if lat_r[j] != ys % ph:
                continue
            i = (ys - lat_r[j]) // ph
            c0 = lat_c[j]
            # strided views indexed from 0: no index numba must check for wraparound
            src = raw[ys, c0::pw]
            dst = lr[j, i]
            for k in range(src.size):
                dst[k] = src[k]
            fsrc = dq[ys, c0::pw]
            fdst = lf[j, i]
            for k in range(fsrc.size):
                fdst[k] = fsrc[k]
            if use_ppi:
                psrc = ppi[ys, c0::pw]
                pdst = lp[j, i]
                for k in range(psrc.size):
                    pdst[k] = psrc[k]


split_lattices = Kernel(_split_loop, 8)


def _samples_loop(raw, dq, has_dq, lat_r, lat_c, lat_start, bands, ph, pw, out, counts):
    """The usable samples of band ``bands[i]`` (every sample of its lattices whose DQ is 0,
    or every sample without ``dq``) into ``out[i, :counts[i]]``, lattice by lattice in row
    order; parallel over the bands (one strided pass each, listed branch-free)."""
    H, W = raw.shape
    for i in prange(bands.shape[0]):
        b = bands[i]
        n = 0
        for j in range(lat_start[b], lat_start[b + 1]):
            for y in range(lat_r[j], H, ph):
                for x in range(lat_c[j], W, pw):
                    out[i, n] = raw[y, x]
                    n += (dq[y, x] == 0) if has_dq else 1
        counts[i] = n


band_samples = Kernel(_samples_loop, 9)


@njit(**_JIT)
def tent_sums(raw, dq, has_dq, ppi, level, use_ppi, y, x, lat_r, lat_c, j0, j1, ph, pw, m):
    """Sums over the same-band samples (lattices ``j0:j1``) under the tent of half-width ``m``
    tiles at pixel (y, x): ``(sum w (v - level ppi), sum w v, sum w, flags)`` with ``w`` the
    tent weight of the usable samples and ``flags`` the OR of the DQ of every sample with a
    positive weight."""
    H, W = raw.shape
    n = 0.0
    r = 0.0
    d = 0.0
    flags = np.uint32(0)
    for j in range(j0, j1):
        ry = y - ((y - lat_r[j]) % ph)  # sample row at or above y
        cx = x - ((x - lat_c[j]) % pw)  # sample column at or left of x
        for t in range(1 - m, m + 1):
            ys = ry + t * ph
            wy = 1.0 - abs(y - ys) / (m * ph)
            if ys < 0 or ys >= H or wy <= 0.0:
                continue
            for s in range(1 - m, m + 1):
                xs = cx + s * pw
                wx = 1.0 - abs(x - xs) / (m * pw)
                if xs < 0 or xs >= W or wx <= 0.0:
                    continue
                f = dq[ys, xs] if has_dq else np.uint32(0)
                flags |= f
                if f == 0:
                    w = wy * wx
                    v = np.float64(raw[ys, xs])
                    r += w * v
                    if use_ppi:
                        v -= level * np.float64(ppi[ys, xs])
                    n += w * v
                    d += w
    return n, r, d, flags


@njit(**_INL)
def usable_weight(w, f):
    """A sample's weight ``w`` where its flags ``f`` are 0, else 0 (branch-free)."""
    return w * np.float64(f == 0)


@njit(**_INL)
def _usable(wa, wb, wc, wd, fa, fb, fc, fd):
    """The weights of four samples, each 0 where its flags are not (branch-free)."""
    return (usable_weight(wa, fa), usable_weight(wb, fb), usable_weight(wc, fc),
            usable_weight(wd, fd))


@njit(**_JIT)
def wide_column_sums(lr, lf, lp, use_ppi, level, j, y, H, W, lat_r, lat_c, ph, pw, rows, wts,
                     wnum, wraw, wden, cfl):
    """The vertical half of the twice-wide tent (S2) at output row ``y`` for every column
    ``k`` of lattice ``j``, into index ``k + 2`` of ``wnum`` (sum of ``w (v - level ppi)``),
    ``wraw`` (``w v``), ``wden`` (``w``) over S2's four sample rows with ``w`` the row weight
    of the usable samples, and ``cfl`` (the OR of the flags of S1's rows); two columns of zeros
    pad each side. ``rows`` and ``wts`` (4) are scratch."""
    ry0 = y - ((y - lat_r[j]) % ph)  # sample row at or above y
    nk = (W - lat_c[j] + pw - 1) // pw
    i0 = (ry0 - lat_r[j]) // ph
    n_i = max((H - lat_r[j] + ph - 1) // ph, 1)
    for t in range(4):  # S2's rows and their weights (0: outside)
        ys = ry0 + (t - 1) * ph
        wy = 1.0 - abs(y - ys) / (2.0 * ph)
        inside = ys >= 0 and ys < H and wy > 0.0
        rows[t] = min(max(i0 + t - 1, 0), n_i - 1)
        wts[t] = wy if inside else 0.0
    wa, wb, wc, wd = wts[0], wts[1], wts[2], wts[3]
    # rows 1 and 2 are S1's (row 2 has weight 0 in S1 when y is on a sample row)
    mb = _ALL if wb > 0.0 else np.uint32(0)
    mc = _ALL if (y != ry0 and wc > 0.0) else np.uint32(0)
    fa, fb, fc, fd = lf[j, rows[0]], lf[j, rows[1]], lf[j, rows[2]], lf[j, rows[3]]
    ra, rb, rc, rd = lr[j, rows[0]], lr[j, rows[1]], lr[j, rows[2]], lr[j, rows[3]]
    for k in range(nk):
        ga, gb, gc, gd = _usable(wa, wb, wc, wd, fa[k], fb[k], fc[k], fd[k])
        wraw[k + 2] = (ga * np.float64(ra[k]) + gb * np.float64(rb[k])
                       + gc * np.float64(rc[k]) + gd * np.float64(rd[k]))
        wden[k + 2] = ga + gb + gc + gd
        cfl[k + 2] = (fb[k] & mb) | (fc[k] & mc)
    if use_ppi:
        pa, pb, pc, pd = lp[j, rows[0]], lp[j, rows[1]], lp[j, rows[2]], lp[j, rows[3]]
        for k in range(nk):
            ga, gb, gc, gd = _usable(wa, wb, wc, wd, fa[k], fb[k], fc[k], fd[k])
            wnum[k + 2] = (ga * (np.float64(ra[k]) - level * pa[k])
                           + gb * (np.float64(rb[k]) - level * pb[k])
                           + gc * (np.float64(rc[k]) - level * pc[k])
                           + gd * (np.float64(rd[k]) - level * pd[k]))
    else:
        wnum[2:nk + 2] = wraw[2:nk + 2]
    for k in (0, 1, nk + 2, nk + 3):  # outside the lattice: zeros
        wnum[k] = 0.0
        wraw[k] = 0.0
        wden[k] = 0.0
        cfl[k] = 0
