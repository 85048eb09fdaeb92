"""Compiled kernels of the refined-PPI demosaicking methods ("ppid_paper", "ppid_edge").

The implementation behind those methods of :func:`hsiffc.reconstruct.demosaic`; every kernel
takes a frame whose flagged samples were already replaced
(:func:`hsiffc.kernels.ppicube.fill_sparse`), so that no flagged value is ever a source, and
works in float32 with float64 sums where they are long.

* :func:`refine_ppi`: the full-resolution PPI. At pixel ``p`` of band ``b`` the sample
  minus a prediction of it from its 8 same-band neighbours ``q`` one tile away:
  ``PPI(p) = (raw(p) - sum_q w_q (raw(q) - l_b M(q)) / sum_q w_q) / l_b`` with ``M`` the
  mean-filter PPI, ``l_b`` the band level (1 without balancing) and ``w_q`` the tent weight
  (1/2 straight, 1/4 diagonal), times the edge weight ``g_q = 1 / (eps + |raw(q) - raw(p)|
  / l_b + |M(q) - M(p)|)`` when ``edge`` is set (a neighbour across an edge counts little).
  Edge weights of the 8 directions are written out for the direction-weighted interpolation.
* :func:`interpolate_differences`: every band ``c`` at every pixel,
  ``l_c PPI(p) + D_c(p)``, ``D_c`` the tent interpolation of ``raw - l_c PPI`` at the band's
  samples with each sample's tent weight times the edge weight of its direction from ``p``
  (Mihoubi et al.'s direction-weighted difference interpolation). Without the direction
  weights the same sum is the shared pass of :mod:`hsiffc.kernels.demosaic` on the unflagged
  frame, which "ppid_edge" calls.
* :func:`flag_values`: the DQ rule of :mod:`hsiffc.reconstruct` around the flagged samples.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..data.dq import DQ
from .demosaic import EPS
from .lattice import lattice_arrays, tent_sums
from .launch import JIT_OPTIONS, Kernel, cached_jit

__all__ = ["edge_term", "flag_values", "interpolate_differences", "refine_pixel", "refine_ppi",
           "scaled_padded"]

_JIT = {**JIT_OPTIONS, "cache": False}
_DO_NOT_USE = np.uint32(DQ.DO_NOT_USE)
_INL = {**_JIT, "inline": "always"}


def _pad_loop(raw, scale, rows, cols, mx, pad):
    """``pad[i, j] = raw[rows[i], cols[j]] * scale[rows[i] % ph, cols[j] % pw]``: the frame
    with each band divided by its level (``scale`` (ph, pw) of 1 / level), extended through
    the index maps ``rows``, ``cols``; ``cols[j] = j - mx`` between the ``mx`` border columns
    of each side (read contiguously there)."""
    ph, pw = scale.shape
    n_c = cols.shape[0]
    W = n_c - 2 * mx
    row_scale = np.empty((ph, n_c), np.float32)
    for r in range(ph):
        for j in range(n_c):
            row_scale[r, j] = scale[r, cols[j] % pw]
    for i in prange(rows.shape[0]):
        src = raw[rows[i]]
        sc = row_scale[rows[i] % ph]
        out = pad[i]
        for j in range(mx):
            out[j] = src[cols[j]] * sc[j]
            out[n_c - 1 - j] = src[cols[n_c - 1 - j]] * sc[n_c - 1 - j]
        o, s = out[mx:], sc[mx:]
        for x in range(W):
            o[x] = src[x] * s[x]


scaled_padded = Kernel(_pad_loop, 5)


@njit(**_JIT)
def _dir_index(sy, sx):
    """Direction (sy, sx) in {-1, 0, 1}^2 as 0..8 (4: none)."""
    return (sy + 1) * 3 + (sx + 1)


@njit(**_JIT)
def refine_pixel(raw, mbar, y, x, v, mp, lev, edge, eps, ph, pw, gam, store):
    """The refined PPI at one pixel, every neighbour checked against the frame's borders."""
    H, W = raw.shape
    num = np.float32(0.0)
    den = np.float32(0.0)
    for sy in range(-1, 2):
        qy = y + sy * ph
        for sx in range(-1, 2):
            if sy == 0 and sx == 0:
                continue
            qx = x + sx * pw
            g = np.float32(0.0)
            if qy >= 0 and qy < H and qx >= 0 and qx < W:
                w = np.float32(0.25 if (sy != 0 and sx != 0) else 0.5)
                rq = raw[qy, qx]
                mq = mbar[qy, qx]
                if edge:
                    g = np.float32(1.0) / (eps + abs(rq - v) / lev + abs(mq - mp))
                    w *= g
                num += w * (rq - lev * mq)
                den += w
            if store:
                gam[y, x, _dir_index(sy, sx)] = g
    return (v - num / den) / lev if den > 0.0 else mp


@njit(**_INL)
def edge_term(w, rq, mq, v, mp, lev, inv_lev, eps):
    """One neighbour's edge weight ``g`` and weighted term (interior pixels)."""
    g = np.float32(1.0) / (eps + abs(rq - v) * inv_lev + abs(mq - mp))
    return g, w * g, w * g * (rq - lev * mq)


def _refine_loop(raw, mbar, band_of, levels, edge, eps, ph, pw, ppi, gam, store):
    """The refined PPI (module docstring) into ``ppi`` (H, W); with ``store`` the edge weight
    of each direction into ``gam`` (H, W, 9) (index :func:`_dir_index`; 4, the pixel itself,
    is ``1 / eps``, an edge weight of no difference). Interior pixels (a tile from every
    border) with edge weights take a branch-free loop over the row."""
    H, W = raw.shape
    lev_row = np.empty((ph, W), np.float32)
    for yph in range(ph):
        for x in range(W):
            lev_row[yph, x] = levels[band_of[yph, x % pw]]
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    for y in prange(H):
        yph = y % ph
        lr = lev_row[yph]
        interior = edge and y >= ph and y < H - ph and W > 2 * pw
        x_lo, x_hi = (pw, W - pw) if interior else (0, 0)
        for x in range(W):
            if x >= x_lo and x < x_hi:
                continue
            ppi[y, x] = refine_pixel(raw, mbar, y, x, raw[y, x], mbar[y, x], lr[x], edge, eps,
                                      ph, pw, gam, store)
            if store:
                gam[y, x, 4] = np.float32(1.0) / eps
        if not interior:
            continue
        r, m = raw[y], mbar[y]
        ru, mu, rd, md = raw[y - ph], mbar[y - ph], raw[y + ph], mbar[y + ph]
        for x in range(x_lo, x_hi):
            v, mp, lev = r[x], m[x], lr[x]
            il = np.float32(1.0) / lev
            g0, w0, n0 = edge_term(quarter, ru[x - pw], mu[x - pw], v, mp, lev, il, eps)
            g1, w1, n1 = edge_term(half, ru[x], mu[x], v, mp, lev, il, eps)
            g2, w2, n2 = edge_term(quarter, ru[x + pw], mu[x + pw], v, mp, lev, il, eps)
            g3, w3, n3 = edge_term(half, r[x - pw], m[x - pw], v, mp, lev, il, eps)
            g5, w5, n5 = edge_term(half, r[x + pw], m[x + pw], v, mp, lev, il, eps)
            g6, w6, n6 = edge_term(quarter, rd[x - pw], md[x - pw], v, mp, lev, il, eps)
            g7, w7, n7 = edge_term(half, rd[x], md[x], v, mp, lev, il, eps)
            g8, w8, n8 = edge_term(quarter, rd[x + pw], md[x + pw], v, mp, lev, il, eps)
            num = ((n0 + n1) + (n2 + n3)) + ((n5 + n6) + (n7 + n8))
            den = ((w0 + w1) + (w2 + w3)) + ((w5 + w6) + (w7 + w8))
            ppi[y, x] = (v - num / den) * il
            if store:
                gg = gam[y, x]
                gg[0], gg[1], gg[2], gg[3] = g0, g1, g2, g3
                gg[4] = np.float32(1.0) / eps
                gg[5], gg[6], gg[7], gg[8] = g5, g6, g7, g8


refine_ppi = Kernel(_refine_loop, 8)


def _diff_loop(raw, ppi, levels, lat_r, lat_c, lat_band, ph, pw, gam, weighted, cube):
    """Every band at every pixel (module docstring) into ``cube`` (H, W, B)."""
    H, W = raw.shape
    n_lat = lat_r.shape[0]
    B = cube.shape[2]
    for y in prange(H):
        num = np.zeros(B)
        den = np.zeros(B)
        for x in range(W):
            num[:] = 0.0
            den[:] = 0.0
            for j in range(n_lat):
                b = lat_band[j]
                lev = levels[b]
                ry = y - ((y - lat_r[j]) % ph)  # sample row at or above y
                cx = x - ((x - lat_c[j]) % pw)  # sample column at or left of x
                for t in range(2):
                    ys = ry + t * ph
                    wy = 1.0 - abs(y - ys) / ph
                    if ys < 0 or ys >= H or wy <= 0.0:
                        continue
                    for s in range(2):
                        xs = cx + s * pw
                        wx = 1.0 - abs(x - xs) / pw
                        if xs < 0 or xs >= W or wx <= 0.0:
                            continue
                        w = wy * wx
                        if weighted:
                            sy = 1 if ys > y else (-1 if ys < y else 0)
                            sx = 1 if xs > x else (-1 if xs < x else 0)
                            w *= gam[y, x, _dir_index(sy, sx)]
                        num[b] += w * (raw[ys, xs] - lev * ppi[ys, xs])
                        den[b] += w
            p = ppi[y, x]
            for b in range(B):
                cube[y, x, b] = levels[b] * p + (num[b] / den[b] if den[b] > 0.0 else 0.0)


_diff = Kernel(_diff_loop, 10)


def interpolate_differences(raw, ppi, levels, lattices, period, gam, cube):
    """Fill ``cube`` (H, W, B) float32 with ``l_c PPI + D_c`` for every band, ``D_c``
    interpolated with the direction weights ``gam`` (H, W, 9) (module docstring; without
    them this is :func:`hsiffc.kernels.demosaic.interpolate_bands` of an unflagged frame).
    ``lattices[b]``: the first sample (row, col) of each position of band ``b`` in the
    tile."""
    ph, pw = int(period[0]), int(period[1])
    lat_r = np.array([r for lat in lattices for r, _ in lat], np.int64)
    lat_c = np.array([c for lat in lattices for _, c in lat], np.int64)
    lat_band = np.array([b for b, lat in enumerate(lattices) for _ in lat], np.int64)
    _diff(raw, ppi, np.asarray(levels, np.float32), lat_r, lat_c, lat_band, ph, pw, gam, True,
          cube)


@njit(**_JIT)
def _lone(dq, ys, xs, ph, pw):
    """Whether the 8 same-band neighbours one tile away of sample (ys, xs) are all in the
    frame and unflagged."""
    H, W = dq.shape
    if ys < ph or ys >= H - ph or xs < pw or xs >= W - pw:
        return False
    for sy in range(-1, 2):
        for sx in range(-1, 2):
            if (sy != 0 or sx != 0) and dq[ys + sy * ph, xs + sx * pw] != 0:
                return False
    return True


def _flag_loop(raw, dq, flagged, band_of, lat_r, lat_c, lat_start, ph, pw, cube, cube_dq,
               missing):
    """The DQ rule of :mod:`hsiffc.reconstruct` around the flagged samples ``flagged`` (flat
    indices): every value of the flagged sample's band within one tile of
    it whose S1 holds no usable sample takes the OR of S1's flags and the twice-wide tent's
    estimate (NaN with DO_NOT_USE, and ``missing[y, b]`` set, where that has none either);
    then each flagged sample's own flags at its site. ``cube_dq`` must be zero elsewhere.
    A value that two flagged samples a tile apart both reach is done once; the loop's
    ``prange`` would be safe (a value's estimate and flags depend only on its position, and
    the own flags are OR-ed in after), but the loop runs serially."""
    H, W = raw.shape
    dummy = np.zeros((1, 1), np.float32)
    for i in prange(flagged.shape[0]):
        ys, xs = flagged[i] // W, flagged[i] % W
        b = band_of[ys % ph, xs % pw]
        j0, j1 = lat_start[b], lat_start[b + 1]
        if j1 - j0 == 1 and _lone(dq, ys, xs, ph, pw):
            # its 8 same-band neighbours are in the frame and usable: every value within a
            # tile but the sample's own has one of them in S1, and S1 of its own site is the
            # sample alone
            _, r2, d2, f1 = tent_sums(raw, dq, True, dummy, 0.0, False, ys, xs, lat_r, lat_c,
                                      j0, j1, ph, pw, 2)
            cube[ys, xs, b] = np.float32(r2 / d2)
            cube_dq[ys, xs, b] = dq[ys, xs]
            continue
        for y in range(max(0, ys - ph + 1), min(H, ys + ph)):
            for x in range(max(0, xs - pw + 1), min(W, xs + pw)):
                if cube_dq[y, x, b] != 0:
                    continue  # done from another flagged sample
                _, _, d1, f1 = tent_sums(raw, dq, True, dummy, 0.0, False, y, x, lat_r, lat_c,
                                         j0, j1, ph, pw, 1)
                if d1 > EPS:
                    continue
                _, r2, d2, _ = tent_sums(raw, dq, True, dummy, 0.0, False, y, x, lat_r, lat_c,
                                         j0, j1, ph, pw, 2)
                if d2 > EPS:
                    cube[y, x, b] = np.float32(r2 / d2)
                    cube_dq[y, x, b] = f1
                else:  # for the band-median fill
                    cube[y, x, b] = np.nan
                    cube_dq[y, x, b] = f1 | _DO_NOT_USE
                    missing[y, b] = True
    for i in range(flagged.shape[0]):  # a sample's own flags at its site, always
        ys, xs = flagged[i] // W, flagged[i] % W
        cube_dq[ys, xs, band_of[ys % ph, xs % pw]] |= dq[ys, xs]


#: serial: a frame holds few flagged samples (0.1 % of 2 Mpx take 2 ms), fewer than pay for
#: starting threads
_flag_values = cached_jit(_flag_loop)


def flag_values(raw, dq, flagged, band_of, lattices, period, cube, cube_dq):
    """Apply the DQ rule around every flagged sample (:func:`_flag_loop`; ``flagged``: their
    flat indices, int64); ``cube_dq`` zero on entry. Returns ``missing`` (H, B) bool: rows
    and bands with values left NaN."""
    ph, pw = int(period[0]), int(period[1])
    lat_r, lat_c, lat_start = lattice_arrays(lattices)
    missing = np.zeros((raw.shape[0], len(lattices)), np.bool_)
    _flag_values(raw, dq, flagged, np.ascontiguousarray(band_of, np.int64), lat_r, lat_c,
                 lat_start, ph, pw, cube, cube_dq, missing)
    return missing
