"""Compiled kernel of mosaic interpolation: bilinear and PPID bands, their DQ and alpha.

The implementation behind :func:`hsiffc.reconstruct.demosaic` ("bilinear", "ppid") and
:func:`hsiffc.reconstruct.reconstruct_alpha` (``resolution="full"``): the normalised
convolution ``(K * (v w)) / (K * w)`` with the tent ``K`` of half-width one tile, evaluated on
each band's sample lattice (the tent covers two sample rows and columns: a vertical blend of
two sample rows, then a horizontal blend of two columns; separable, exact, no zero-filled
planes). One pass over the output rows, parallel over blocks of rows, writes every band of the
cube and, when asked, its alpha: the max over the same samples (bilinear; PPID's alpha, the
max under the PPI window, is one plane for every band and is not made here). Per row and
band: the vertical blend of each lattice at its columns; the horizontal blend per column phase
``x mod pw`` (one contiguous, vectorised loop per phase); the division into a band-major row
buffer, whose finished row goes into the (W, B) cube row through flat indices
(:func:`_transpose_row`).

A frame with flagged samples is first split into lattice planes (:mod:`hsiffc.kernels.lattice`),
read contiguously. Each row of the DQ cube is zeroed by the pass itself (no separate fill of the
whole cube) and gets the samples' own flags at their sites; the values whose support S1 holds no
usable sample are listed from the vertical pass (with one lattice per band, read off its column
weights: a value is listed where its column and, off the column, the next one have none) and
take the flags of S1 and the estimate of the twice-wide tent S2 (S2's column sums over the row,
four columns per value); where S2 holds none either the value is NaN for the caller's
band-median fill. PPID values whose PPI is undefined take the plain bilinear value.

Arithmetic: the interpolation (the vertical and horizontal blends, the division, PPID's level
times the PPI) runs in float32, twice the values per vector of float64, because its error
stays far below the data's noise. Budget: every value within 2**-22 (4 float32 ulps) of
the frame's largest value of the same interpolation in float64, and, for bilinear, within 4
ulps of the value itself; PPID subtracts the PPI and adds it back, so its error scales with
the frame, not with a value near zero (tested against ``cv2.sepFilter2D`` in float64 on five
layouts), far below a sensor's read noise. The twice-wide (S2) estimates and the
PPI-undefined values stay in float64, and DQ, alpha and the NaN / DO_NOT_USE decisions do not
depend on the precision. The kernel's speed is on the benchmarks page.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..data.dq import DQ
from .lattice import lattice_arrays, split_lattices, tent_sums, wide_column_sums
from .launch import JIT_OPTIONS, Kernel

__all__ = ["EPS", "CubeOutputs", "LatticeLayout", "LatticePlanes", "MosaicPlanes",
           "interpolate_bands"]

#: Weight sums at or below this are "no source" (the smallest real weight is 1 / (4 ph pw)).
EPS = 1e-6
_DO_NOT_USE = np.uint32(DQ.DO_NOT_USE)
_NEG = np.float32(-np.inf)
_ZERO = np.float32(0.0)
_ROWS = 8  # output rows per parallel task (one set of row buffers each)
_JIT = {**JIT_OPTIONS, "cache": False}


# The kernel takes its operands in named groups (numba types a named tuple per combination of
# its members' types) and hands them to its block function as they are. Absent planes are
# size-1 placeholders with a flag saying so (never None: the leakage kernels pass their blocks
# separate arguments so that numba removes a None operand's branches, which this kernel has
# none of).

class MosaicPlanes(NamedTuple):
    """The frame's planes the interpolation reads: (H, W) arrays."""

    raw: object  #: float32 values, finite
    dq: object  #: uint32 DQ (read where ``has_dq``)
    has_dq: bool
    alpha: object  #: float32 alpha (read where ``has_alpha``)
    has_alpha: bool
    ppi: object  #: float32 pseudo-panchromatic image (read where ``use_ppi``)
    ppi_ok: object  #: bool, where the PPI is defined
    use_ppi: bool  #: PPID: interpolate ``value - level * ppi``, add ``level * ppi`` back
    levels: object  #: (B,) float64 PPI scale of each band


class LatticeLayout(NamedTuple):
    """Where each band's samples are (:func:`~hsiffc.kernels.lattice.lattice_arrays`)."""

    lat_r: object  #: (L,) int64 first sample row of each lattice (0 <= r < ph)
    lat_c: object  #: (L,) int64 first sample column (0 <= c < pw)
    lat_start: object  #: (B + 1,) int64: band b's lattices are lat_start[b]:lat_start[b + 1]
    col_left: object  #: (L, W) int64 lattice column at or left of each x (may be -1)
    ph: int  #: tile rows
    pw: int  #: tile columns


class LatticePlanes(NamedTuple):
    """The frame as one plane per lattice (:data:`~hsiffc.kernels.lattice.split_lattices`),
    (L, ceil(H / ph), ceil(W / pw)); size-1 placeholders without flags."""

    raw: object  #: float32
    dq: object  #: uint32
    ppi: object  #: float32


class CubeOutputs(NamedTuple):
    """What the interpolation writes."""

    cube: object  #: (H, W, B) float32
    dq: object  #: (H, W, B) uint32, every value written
    alpha: object  #: (H, W, B) float32, or a size-1 placeholder
    missing_rows: object  #: (H, B) bool, rows and bands with values left NaN


@njit(**_JIT)
def _transpose_row(src, dst):
    """``dst[x, b] = src[b, x]``: a band-major row buffer (B, W) into a cube row (W, B),
    through flat indices."""
    B, W = src.shape
    flat = dst.reshape(W * B)
    for x in range(W):
        base = x * B
        for b in range(B):
            flat[base + b] = src[b, x]


@njit(**_JIT)
def _interpolate_block(blk, planes, layout, lattice_planes, outputs, n_lat):
    """Rows ``blk * _ROWS`` on of :func:`_interpolate_rows`, a compiled function of its own
    as the other kernels' blocks are (no slower than the same loops in the ``prange``
    body); returns how many values it left NaN. It takes the kernel's named groups as they
    are (no operand is None here: absent planes are placeholders with a flag) and unpacks
    them, as the kernel does."""
    raw, dq, has_dq, alpha, has_alpha, ppi, ppi_ok, use_ppi, levels = planes
    lat_r, lat_c, lat_start, col_left, ph, pw = layout
    lr, lf, lp = lattice_planes
    cube, cube_dq, cube_alpha, missing_rows = outputs
    H, W = raw.shape
    B = lat_start.shape[0] - 1
    nk_max = W // pw + 3  # lattice columns (at most ceil(W / pw)) plus padding
    missing = 0
    vnum = np.empty(nk_max, np.float32)
    vden = np.empty(nk_max, np.float32)
    vmax = np.empty(nk_max, np.float32)
    nK = (W + pw - 1) // pw
    numA = np.empty((pw, nK), np.float32)
    denA = np.empty((pw, nK), np.float32)
    amaxA = np.empty((pw, nK), np.float32)
    todo = np.empty(W, np.int64)
    cand = np.empty(nk_max, np.int64)
    bad_x = np.empty(W, np.int64)  # PPI undefined: column, its phase and block
    bad_q = np.empty(W, np.int64)
    bad_k = np.empty(W, np.int64)
    # S2's column sums and the OR of the flags of S1's rows per lattice column, padded by
    # two columns of zeros on each side (index k + 2 holds column k)
    wnum = np.zeros((n_lat, nk_max + 4))
    wraw = np.zeros((n_lat, nk_max + 4))
    wden = np.zeros((n_lat, nk_max + 4))
    cfl = np.zeros((n_lat, nk_max + 4), np.uint32)
    rows2 = np.empty(4, np.int64)
    qa_of = np.empty(pw, np.int64)
    dk_of = np.empty(pw, np.int64)
    wtab = np.empty((pw, 4))  # S2's column weights at x - xs = p
    for p in range(pw):
        for t in range(4):
            wtab[p, t] = max(1.0 - abs(p - (t - 1) * pw) / (2.0 * pw), 0.0)
    wts2 = np.empty(4)
    row_v = np.empty((B, W), np.float32)  # the row's values and alpha, band-major: each
    row_a = np.empty((B, W), np.float32)  # band's pass writes contiguously
    for y in range(blk * _ROWS, min(H, blk * _ROWS + _ROWS)):
        yph = y % ph
        n_bad = 0
        dq_row = cube_dq[y].reshape(W * B)  # zeroed here, then flags OR-ed in while cached
        for i in range(W * B):
            dq_row[i] = 0
        if use_ppi and has_dq:
            for x in range(W):
                if not ppi_ok[y, x]:
                    bad_x[n_bad] = x
                    bad_q[n_bad] = x % pw
                    bad_k[n_bad] = x // pw
                    n_bad += 1
        for b in range(B):
            level = levels[b]
            lev = np.float32(level)  # the interpolation's arithmetic is float32
            j0, j1 = lat_start[b], lat_start[b + 1]
            for j in range(j0, j1):
                ry0 = y - ((y - lat_r[j]) % ph)  # sample row at or above y
                wy1 = (y - ry0) / ph
                ry1 = ry0 + ph
                w0 = np.float32((1.0 - wy1) if ry0 >= 0 else 0.0)
                w1 = np.float32(wy1 if ry1 < H else 0.0)
                r0 = ry0 if ry0 >= 0 else ry1
                r1 = ry1 if ry1 < H else r0
                c0 = lat_c[j]
                # the lattice's columns (none if it has no row in the frame: a small frame)
                nk = (W - c0 + pw - 1) // pw if r0 < H else 0
                if has_dq:  # from the lattice planes: contiguous
                    i_0 = min((r0 - lat_r[j]) // ph, lr.shape[1] - 1)
                    i_1 = min((r1 - lat_r[j]) // ph, lr.shape[1] - 1)
                    R0, R1, F0, F1 = lr[j, i_0], lr[j, i_1], lf[j, i_0], lf[j, i_1]
                    if use_ppi:
                        P0, P1 = lp[j, i_0], lp[j, i_1]
                        for k in range(nk):
                            g0 = w0 if F0[k] == 0 else _ZERO
                            g1 = w1 if F1[k] == 0 else _ZERO
                            vnum[k + 1] = (g0 * (R0[k] - lev * P0[k])
                                           + g1 * (R1[k] - lev * P1[k]))
                            vden[k + 1] = g0 + g1
                    else:
                        for k in range(nk):
                            g0 = w0 if F0[k] == 0 else _ZERO
                            g1 = w1 if F1[k] == 0 else _ZERO
                            vnum[k + 1] = g0 * R0[k] + g1 * R1[k]
                            vden[k + 1] = g0 + g1
                elif nk > 0:  # strided views indexed from 0 (no wraparound check)
                    V0, V1 = raw[r0, c0::pw], raw[r1, c0::pw]
                    if use_ppi:
                        P0, P1 = ppi[r0, c0::pw], ppi[r1, c0::pw]
                        for k in range(nk):
                            v0 = V0[k] - lev * P0[k]
                            v1 = V1[k] - lev * P1[k]
                            vnum[k + 1] = w0 * v0 + w1 * v1
                            vden[k + 1] = w0 + w1
                    else:
                        for k in range(nk):
                            vnum[k + 1] = w0 * V0[k] + w1 * V1[k]
                            vden[k + 1] = w0 + w1
                if has_alpha and nk > 0:
                    A0, A1 = alpha[r0, c0::pw], alpha[r1, c0::pw]
                    for k in range(nk):
                        a0 = A0[k] if w0 > 0.0 else _NEG
                        a1 = A1[k] if w1 > 0.0 else _NEG
                        vmax[k + 1] = max(a0, a1)
                vnum[0] = _ZERO
                vden[0] = _ZERO
                vmax[0] = _NEG
                for k in range(nk + 1, nK + 2):
                    vnum[k] = _ZERO
                    vden[k] = _ZERO
                    vmax[k] = _NEG
                # horizontal, per absolute column phase qa: pixel x = K pw + qa lies between
                # padded lattice columns K + 1 - s and K + 2 - s
                for qa in range(pw):
                    s = 0 if qa >= c0 else 1
                    p = qa - c0 + s * pw
                    wr = np.float32(p / pw)
                    wl = np.float32(1.0 - p / pw)
                    nKq = (W - qa + pw - 1) // pw
                    na = numA[qa]
                    da = denA[qa]
                    if j == j0:
                        for K in range(nKq):
                            k = K + 1 - s
                            na[K] = wl * vnum[k] + wr * vnum[k + 1]
                            da[K] = wl * vden[k] + wr * vden[k + 1]
                    else:
                        for K in range(nKq):
                            k = K + 1 - s
                            na[K] += wl * vnum[k] + wr * vnum[k + 1]
                            da[K] += wl * vden[k] + wr * vden[k + 1]
                    if has_alpha:
                        ma = amaxA[qa]
                        if j == j0:
                            for K in range(nKq):
                                k = K + 1 - s
                                a = max(vmax[k], vmax[k + 1]) if p > 0 else vmax[k]
                                ma[K] = max(_NEG, a)
                        else:
                            for K in range(nKq):
                                k = K + 1 - s
                                a = max(vmax[k], vmax[k + 1]) if p > 0 else vmax[k]
                                ma[K] = max(ma[K], a)
            # final: divide and write
            for qa in range(pw):
                nKq = (W - qa + pw - 1) // pw
                na = numA[qa]
                for K in range(nKq):
                    na[K] = na[K] / denA[qa, K]
                out_v = row_v[b, qa::pw]  # strided views indexed from 0, as above
                if use_ppi:
                    ppi_q = ppi[y, qa::pw]
                    for K in range(nKq):
                        out_v[K] = na[K] + lev * ppi_q[K]
                else:
                    for K in range(nKq):
                        out_v[K] = na[K]
            if has_alpha:
                for qa in range(pw):
                    nKq = (W - qa + pw - 1) // pw
                    ma = amaxA[qa]
                    out_a = row_a[b, qa::pw]
                    for K in range(nKq):
                        a = ma[K]
                        out_a[K] = a if a > _NEG else 0.0
            if not has_dq:  # then every S1 holds a usable sample and the PPI is defined
                continue
            for j in range(j0, j1):  # the samples' own flags at their sites
                if lat_r[j] == yph:
                    for xs in range(lat_c[j], W, pw):
                        cube_dq[y, xs, b] = dq[y, xs]
            for i in range(n_bad):  # PPI undefined, S1 not empty: the plain bilinear value
                x = bad_x[i]
                if denA[bad_q[i], bad_k[i]] > EPS:
                    _, r1s, d1, _ = tent_sums(raw, dq, has_dq, ppi, level, False, y, x,
                                               lat_r, lat_c, j0, j1, ph, pw, 1)
                    row_v[b, x] = r1s / d1
            # the values whose S1 has no usable sample: their column at or left of them
            # has none in the last lattice's vertical pass (vden), or there is no column
            c_last = lat_c[j1 - 1]
            n_cand = 0
            for k in range((W - c_last + pw - 1) // pw):  # branch-free lists
                cand[n_cand] = k
                n_cand += vden[k + 1] <= EPS
            n_todo = 0
            if j1 - j0 == 1:  # one lattice: x has no usable sample in S1 where its column
                # (and, off the column, the next one) has none: read off vden directly
                none0 = np.int64(vden[1] <= EPS)  # left of the first column: column 0
                for x in range(min(c_last, W)):
                    todo[n_todo] = x
                    n_todo += none0
                for i in range(n_cand):
                    k = cand[i]
                    x0 = c_last + k * pw
                    todo[n_todo] = x0
                    n_todo += 1
                    n_off = min(pw, W - x0) - 1
                    for d in range(n_off):
                        todo[n_todo + d] = x0 + 1 + d
                    n_todo += n_off * np.int64(vden[k + 2] <= EPS)
            else:
                for x in range(min(c_last, W)):  # K = 0, qa = x
                    todo[n_todo] = x
                    n_todo += denA[x, 0] <= EPS
                for i in range(pw):  # x = c_last + k pw + i: phase and block of x
                    qa_of[i] = (c_last + i) % pw
                    dk_of[i] = (c_last + i) // pw
                for i in range(n_cand):
                    k = cand[i]
                    x0 = c_last + k * pw
                    for d in range(min(pw, W - x0)):
                        todo[n_todo] = x0 + d
                        n_todo += denA[qa_of[d], k + dk_of[d]] <= EPS
            if n_todo == 0:
                continue
            for j in range(j0, j1):  # S2's column sums, every column of the lattice
                wide_column_sums(lr, lf, lp, use_ppi, level, j, y, H, W, lat_r, lat_c, ph, pw,
                                 rows2, wts2, wnum[j - j0], wraw[j - j0], wden[j - j0],
                                 cfl[j - j0])
            for i in range(n_todo):
                x = todo[i]
                # no usable sample in S1: the flags of S1, and the estimate from S2
                flags = np.uint32(0)
                n2 = 0.0
                r2 = 0.0
                d2 = 0.0
                for j in range(j0, j1):
                    jj = j - j0
                    k = col_left[j, x]
                    xs = lat_c[j] + k * pw
                    for t in range(4):  # branch-free over columns k - 1 .. k + 2 (weight 0
                        # at distance 2 pw and zeros outside the lattice add nothing)
                        wx = wtab[x - xs, t]
                        n2 += wx * wnum[jj, k + 1 + t]
                        r2 += wx * wraw[jj, k + 1 + t]
                        d2 += wx * wden[jj, k + 1 + t]
                    flags |= cfl[jj, k + 2]  # S1's columns: k, and k + 1 unless x is on k
                    if x != xs:
                        flags |= cfl[jj, k + 3]
                if d2 <= EPS:
                    est = np.nan
                    flags |= _DO_NOT_USE
                    missing += 1
                    missing_rows[y, b] = True
                elif use_ppi and ppi_ok[y, x]:
                    est = n2 / d2 + level * ppi[y, x]
                else:
                    est = r2 / d2
                row_v[b, x] = est
                cube_dq[y, x, b] |= flags
        _transpose_row(row_v, cube[y])  # the row into the cube: (W, B) contiguous
        if has_alpha:
            _transpose_row(row_a, cube_alpha[y])
    return missing


def _interpolate_rows(planes, layout, lattice_planes, outputs):
    """Fill ``cube`` (H, W, B), ``cube_dq`` (every value: each row is zeroed, then its flags
    are set) and, where present, ``cube_alpha`` (``outputs``, :class:`CubeOutputs`) from
    :class:`MosaicPlanes`, :class:`LatticeLayout` and :class:`LatticePlanes`.

    ``lat_r/lat_c`` are the first sample row/column (0 <= r < ph, 0 <= c < pw, offset
    included) of each pattern position; those of band b are ``lat_start[b]:lat_start[b+1]``.
    Returns the number of values left NaN (no usable sample within twice the tile); their
    rows and bands are marked in ``missing_rows`` (H, B) bool.

    Per output row and band: a vertical pass blends the two sample rows of each lattice at
    its columns (sum over usable samples, their weight, the max alpha), a horizontal pass per
    column phase blends two neighbouring columns into per-pixel sums, and a final pass
    divides and writes the band's values and alpha. Then, with flags only: the samples' own
    flags, the PPI-undefined values of the row (:func:`~hsiffc.kernels.lattice.tent_sums`
    with S1), and the values whose S1 holds no usable sample (``col_left[j, x]``: the sample
    column of lattice ``j`` at or left of ``x``, may be -1). ``lr, lf, lp``: the lattice
    planes of raw, DQ and PPI (:data:`~hsiffc.kernels.lattice.split_lattices`), read only
    with flags (size-1 placeholders otherwise).
    """
    raw = planes.raw
    lat_start = layout.lat_start
    H = raw.shape[0]
    B = lat_start.shape[0] - 1
    n_lat = np.int64(1)  # not a literal 1: see below
    for b in range(B):
        n_lat = max(n_lat, lat_start[b + 1] - lat_start[b])
    missing = 0
    for blk in prange((H + _ROWS - 1) // _ROWS):
        # int64 arguments: numba compiled the block once per type it saw (uint64 blk, literal 1)
        missing += _interpolate_block(np.int64(blk), planes, layout, lattice_planes,
                                      outputs, n_lat)
    return missing


_interpolate = Kernel(_interpolate_rows, (0, 0))


def interpolate_bands(raw, dq, alpha, ppi, ppi_ok, levels, lattices, period,
                      cube, cube_dq, cube_alpha):
    """Run the kernel; optional inputs (``dq``, ``alpha``, ``ppi``, ``ppi_ok``) may be None.

    Parameters
    ----------
    raw : (H, W) float32, finite
    dq : (H, W) uint32 or None (no flagged sample)
    alpha : (H, W) float32, finite, or None
        With ``cube_alpha``: each value's alpha is the max over its S1 samples (bilinear's;
        PPID's cube alpha is the PPI window's max, one plane for every band, which
        :func:`hsiffc.reconstruct.demosaic` takes without this kernel).
    ppi, ppi_ok : (H, W) float32 and bool (None: defined everywhere), or None (bilinear)
    levels : (B,) float64, the PPI scale of each band
    lattices : list of B lists of (row, col): first sample row/column of each pattern position
    period : (ph, pw)
    cube : (H, W, B) float32, out
    cube_dq : (H, W, B) uint32 out (any content: every value is written)
    cube_alpha : (H, W, B) float32 out, or None

    Returns ``(H, B)`` bool: the rows and bands holding values whose wide support has no usable
    sample, including every value of a band with no sample in the frame (a frame smaller than
    the tile), those with DO_NOT_USE; those values are NaN (fill them with the band median).
    """
    H, W = raw.shape
    dummy_f = np.zeros((1, 1), np.float32)
    lat_r, lat_c, lat_start = lattice_arrays(lattices)
    missing_rows = np.zeros((H, len(lattices)), np.bool_)
    if ppi is not None and ppi_ok is None:
        ppi_ok = np.ones((H, W), np.bool_)
    ph, pw = int(period[0]), int(period[1])
    # the lattice planes (only a frame with flagged samples needs them)
    size = (len(lat_r), -(-H // ph), -(-W // pw)) if dq is not None else (1, 1, 1)
    lr = np.zeros(size, np.float32)
    lf = np.zeros(size, np.uint32)
    lp = np.zeros(size if ppi is not None else (1, 1, 1), np.float32)
    if dq is not None:
        split_lattices(raw, dq, dummy_f if ppi is None else ppi, ppi is not None, lat_r, lat_c,
                       ph, pw, lr, lf, lp)
    _interpolate(
        MosaicPlanes(raw, np.zeros((1, 1), np.uint32) if dq is None else dq, dq is not None,
                     dummy_f if alpha is None else alpha, alpha is not None,
                     dummy_f if ppi is None else ppi,
                     np.ones((1, 1), np.bool_) if ppi_ok is None else ppi_ok, ppi is not None,
                     np.asarray(levels, np.float64)),
        LatticeLayout(lat_r, lat_c, lat_start, (np.arange(W)[None, :] - lat_c[:, None]) // pw,
                      ph, pw),
        LatticePlanes(lr, lf, lp),
        CubeOutputs(cube, cube_dq,
                    np.zeros((1, 1, 1), np.float32) if cube_alpha is None else cube_alpha,
                    missing_rows))
    for b, lattice in enumerate(lattices):  # a frame smaller than the tile may hold no sample
        if not any(r < H and c < W for r, c in lattice):  # of a band at all (the kernel
            cube[:, :, b] = np.nan  # marks missing values only where a sample is flagged)
            cube_dq[:, :, b] |= _DO_NOT_USE
            missing_rows[:, b] = True
    return missing_rows
