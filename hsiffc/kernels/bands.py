"""Compiled per-band sums (the body of :func:`hsiffc.spectral.bandstats.band_reduce` for the mean) and
the two-point apply product (the body of :func:`hsiffc.flatfield.two_point.two_point_apply`).

One pass over the frame reads the values in their own dtype (no float64 copy), the band map
and the good mask, and accumulates a sum and a count per band in float64; row blocks run in
parallel with their own partial sums, added at the end in a fixed order (the result does not
depend on the thread count).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .launch import JIT_OPTIONS, Kernel
from .operands import at

__all__ = ["ROWS", "add_row", "band_scale_kernel", "band_sums", "block_arrays", "fold_block",
           "phase_scale_kernel", "scale_kernel"]

ROWS = 64  # rows per partial sum
_JIT = {**JIT_OPTIONS, "cache": False}


@njit(**_JIT)
def add_row(acc, cnt, row, use_row, want):
    """Add a row's finite values at pixels with ``use_row[x] == want`` into one phase's
    column sums ``acc`` (float64) and counts ``cnt``: the accumulation of
    :func:`band_sums` by row phase, also run inside a fused pass
    (:func:`hsiffc.kernels.leakage.alpha_flags_sums_kernel`, ``use_row`` its DQ row and
    ``want`` 0), so that both add the same values in the same order."""
    for x in range(acc.shape[0]):  # integer tests: a short-circuit ``and`` stops vectorising
        v = np.float64(row[x])
        use = np.int32(abs(v) < np.inf) & np.int32(use_row[x] == want)
        acc[x] += v if use != 0 else 0.0
        cnt[x] += use


@njit(**_JIT)
def fold_block(col_sum, col_count, phase_bands, sums, counts):
    """Fold a block's phase column sums into its per-band ``sums/counts`` (1-D rows of the
    block): row ``phase`` of ``col_sum`` belongs to band map row ``phase_bands[phase]``."""
    nb = sums.shape[0]
    for phase in range(phase_bands.shape[0]):
        for x in range(phase_bands.shape[1]):
            band = phase_bands[phase, x]
            if 0 <= band < nb:
                sums[band] += col_sum[phase, x]
                counts[band] += col_count[phase, x]


def block_arrays(n_rows: int, n_bands: int):
    """Zeroed partial sums and counts, one row per block of :data:`ROWS` rows."""
    nblk = max((n_rows + ROWS - 1) // ROWS, 1)
    return np.zeros((nblk, n_bands)), np.zeros((nblk, n_bands), np.int64)


def _band_sums_loop(values, band_map, good, has_good, period, sums, counts):
    """Partial sums and counts per block of ``ROWS`` rows into ``sums/counts[block, band]``;
    finite values of good pixels only.

    ``period`` > 0 says rows ``y`` and ``y + period`` of ``band_map`` hold the same bands (a
    mosaic's band map): a block then adds its rows into ``period`` column-sum rows, one per
    row phase (:func:`add_row`: a vectorised stream, no per-pixel scatter), and folds those
    into bands through the block's first ``period`` band-map rows (:func:`fold_block`).
    Otherwise every pixel is added to its band.
    """
    H, W = values.shape
    nb = sums.shape[1]
    for blk in prange((H + ROWS - 1) // ROWS):
        y0 = blk * ROWS
        y1 = min(H, y0 + ROWS)
        if period > 0:
            col_sum = np.zeros((period, W))
            col_count = np.zeros((period, W), np.int32)
            everywhere = np.ones(W, np.uint8)
            for y in range(y0, y1):
                phase = (y - y0) % period
                add_row(col_sum[phase], col_count[phase], values[y],
                        good[y] if has_good else everywhere, 1)
            fold_block(col_sum, col_count, band_map[y0:y0 + min(period, y1 - y0)],
                       sums[blk], counts[blk])
            continue
        for y in range(y0, y1):
            for x in range(W):
                v = np.float64(values[y, x])
                if (not has_good or good[y, x]) and abs(v) < np.inf:
                    band = band_map[y, x]
                    if 0 <= band < nb:
                        sums[blk, band] += v
                        counts[blk, band] += 1


#: Band sums do little per pixel (a block of rows is a short job for one thread): the
#: parallel build only pays on frames of a megapixel and more.
_kernel = Kernel(_band_sums_loop, 0, parallel_min=1 << 20)


def band_sums(values, band_map, good, n_bands: int, row_period: int = 0):
    """Sum and count of the finite ``values`` of ``good`` pixels per band.

    Parameters
    ----------
    values : (H, W) float32 or float64 array
    band_map : (H, W) integer array
    good : (H, W) bool array or None (all pixels)
    n_bands : int
    row_period : int
        ``p`` > 0 if rows ``y`` and ``y + p`` of ``band_map`` hold the same bands (see
        :func:`hsiffc.data.mosaic.row_period`): the faster phase-row sum; 0 if unknown.

    Returns
    -------
    sums : (n_bands,) float64
    counts : (n_bands,) int64
    """
    v = np.ascontiguousarray(values)
    if v.dtype not in (np.float32, np.float64):
        v = v.astype(np.float64)
    bm = np.ascontiguousarray(band_map, dtype=np.int64)
    g = np.zeros((1, 1), np.uint8) if good is None else np.ascontiguousarray(good, np.bool_)
    # the compiled loop indexes every plane by the values' rows and columns, unchecked
    if v.ndim != 2 or bm.shape != v.shape or (good is not None and g.shape != v.shape):
        raise ValueError(f"band_sums: values {v.shape}, band_map {bm.shape} and good "
                         f"{None if good is None else g.shape} must be 2-D of one shape")
    g = g.view(np.uint8)  # compiled code tests bytes (a bool load branches)
    sums, counts = block_arrays(v.shape[0], n_bands)
    if v.size:
        _kernel(v, bm, g, good is not None, int(row_period), sums, counts)
    return sums.sum(axis=0), counts.sum(axis=0)


def _scale_loop(signal, gain, scale, out):
    """``out = signal * gain * scale`` (float32 out, float64 arithmetic). Returns how many
    stored values are not finite (NaN in, or a product beyond the float32 range)."""
    bad = 0
    for i in prange(out.shape[0]):
        o = np.float32(at(signal, i) * at(gain, i) * at(scale, i))
        out[i] = o
        bad += 0 if abs(o) < np.inf else 1
    return bad


scale_kernel = Kernel(_scale_loop, 3)


def _band_scale_loop(signal, gain, ratio, band_map, out):
    """``out = signal * gain * ratio[band_map]``: the product of :func:`_scale_loop` with a
    per-band factor, looked up per pixel instead of read from a per-pixel map. Returns how
    many pixels have a band outside ``ratio`` (their output is NaN) and how many stored
    values are not finite (those included)."""
    n = ratio.shape[0]
    outside = 0
    bad = 0
    for i in prange(out.shape[0]):
        band = band_map[i]
        ok = band >= 0 and band < n
        # the index stays in bounds also where the vector code loads before it selects
        r = np.float64(ratio[band if ok else 0]) if ok else np.nan
        o = np.float32(np.float64(signal[i]) * np.float64(gain[i]) * r)
        out[i] = o
        outside += 0 if ok else 1
        bad += 0 if abs(o) < np.inf else 1
    return outside, bad


band_scale_kernel = Kernel(_band_scale_loop, 4)


@njit(**_JIT)
def _phase_scale_rows(signal, gain, table, phase0, out):
    """Rows of :func:`_phase_scale_loop`; row ``y`` takes factor row ``(phase0 + y) % P``.
    Returns how many stored values are not finite."""
    period = table.shape[0]
    bad = 0
    for y in range(out.shape[0]):
        factor = table[(phase0 + y) % period]
        sig = signal[y]
        g = gain[y]
        row = out[y]
        for x in range(row.shape[0]):
            o = np.float32(np.float64(sig[x]) * np.float64(g[x]) * np.float64(factor[x]))
            row[x] = o
            bad += 0 if abs(o) < np.inf else 1
    return bad


def _phase_scale_loop(signal, gain, table, out):
    """``out = signal * gain * table[y % P]`` for 2-D frames whose per-band factor repeats
    every ``P`` rows (a mosaic's): ``table`` holds each column's factor for the ``P`` row
    phases, so a pixel reads two values and writes one (no band map, no gather). Blocks of
    ``ROWS`` rows run in parallel, each a compiled row loop (vectorised). Returns how many
    stored values are not finite."""
    H = out.shape[0]
    bad = 0
    for blk in prange((H + ROWS - 1) // ROWS):
        y0 = blk * ROWS
        y1 = min(H, y0 + ROWS)
        bad += _phase_scale_rows(signal[y0:y1], gain[y0:y1], table, y0, out[y0:y1])
    return bad


phase_scale_kernel = Kernel(_phase_scale_loop, 3)
