"""Demosaicking on a full-resolution pseudo-panchromatic image ("ppid_paper", "ppid_edge"), and
by iterative spectral differences ("itsd").

PPID as :data:`~hsiffc.reconstruct.DEMOSAIC_METHODS` ``"ppid"`` has it adds the bands'
differences to the mean-filter PPI ``M``, a blurred image: detail finer than a tile is lost
from every band. Mihoubi et al. (IEEE TCI 2017) restore it: at every pixel the PPI is the
pixel's own sample minus a prediction of that sample's offset from the PPI, made from its
same-band neighbours one tile away, whose weights fall across edges (the edge-sensitive PPI);
then each band's differences from that PPI are interpolated with weights that again fall
across edges (direction-weighted). :func:`refined_cube` computes both, with
:mod:`hsiffc.kernels.refined`:

``"ppid_paper"``
    the paper's structure: no band balancing, edge weights in the PPI and in the difference
    interpolation. The edge weight of a neighbour ``q`` of ``p`` is ours,
    ``1 / (eps + |raw(q) - raw(p)| / l_b + |M(q) - M(p)|)`` (a same-band difference and the
    blurred PPI's difference, ``eps`` 2 % of the frame's mean level); the paper's weight sums
    absolute raw differences along the direction instead.
``"ppid_edge"``
    hsiffc's: the band balancing of ``"ppid"`` (each band scaled by its median level), edge
    weights in the PPI, and plain bilinear (tent) interpolation of the differences, which on
    the benchmark scenes did as well as the direction weights, at a fraction of the time.

``"itsd"``
    iterative spectral differences (Brauers and Aach 2006; Mizutani et al. 2014), which need
    no PPI: from the bilinear cube, two steps of
    ``b(x) = raw(x) + bilinear_b(raw - previous estimate of x's band)`` (:func:`itsd_cube`).

On layouts with one sample of each band per tile, "ppid_edge" and "itsd" run on the fused
kernels of :mod:`hsiffc.kernels.ppicube`; a band repeated in the tile takes the general path.
Flagged samples first take the tent-weighted mean of their usable same-band neighbours (as in
the PPI), so that no flagged value is a source; then the DQ rule of the package is applied
around each flagged sample (the values whose one-tile support holds no usable sample take the
twice-wide bilinear estimate and the flags), so the DQ plane is that of every other method.
"""

from __future__ import annotations

import numpy as np

import cv2

from ..kernels.demosaic import interpolate_bands
from ..kernels.ppicube import cube_of_planes, edge_ppi, fill_sparse, spectral_difference
from ..kernels.refined import flag_values, interpolate_differences, refine_ppi, scaled_padded
from .prepare import (Prepared, band_levels, band_medians, periodic_index, ppi_kernel,
                      prepare)

__all__ = ["EDGE_EPS", "ITSD_STEPS", "MIN_LEVEL_SAMPLES", "few_level_samples", "itsd_cube",
           "refined_cube"]

#: ``eps`` of the edge weights, as a fraction of the frame's mean PPI level
EDGE_EPS = 0.02
#: Spectral-difference steps of "itsd" after its bilinear start
ITSD_STEPS = 2


def _filled(p: Prepared) -> np.ndarray:
    """The frame with flagged samples replaced by their same-band neighbours' mean (the band
    median where none is usable)."""
    if not p.any_flags:
        return p.raw
    flat = p.flagged
    out = fill_sparse(p.raw, p.dq, flat, *p.period)
    bad = flat[np.isnan(out.ravel()[flat])]
    if bad.size:
        ph, pw = p.period
        W = p.shape[1]
        bands = p.mosaic.band_map(p.period)[(bad // W) % ph, (bad % W) % pw]
        which = np.unique(bands)
        med = band_medians(p, which)
        out.ravel()[bad] = med[np.searchsorted(which, bands)].astype(np.float32)
    return out


#: At most this many samples of a band enter its level (:func:`_sampled_levels`)
LEVEL_SAMPLES = 1 << 14

#: A frame with fewer samples of each band than this is not balanced (levels of one): the
#: edge-sensitive PPI divides a pixel's own sample by its band's level, and a median of a
#: handful of samples can be a small fraction of the band's true level (on a 10 x 11 frame of
#: a 5 x 5 mosaic, four samples a band, a level of 0.13 made one PPI value 7168 DN where the
#: frame holds at most 1000)
MIN_LEVEL_SAMPLES = 16


def few_level_samples(p: Prepared) -> bool:
    """Whether some band has fewer than :data:`MIN_LEVEL_SAMPLES` samples in the frame (too
    few for a band level: its bands are not balanced).

    Parameters
    ----------
    p : Prepared
        The frame.

    Returns
    -------
    bool
    """
    H, W = p.shape
    ph, pw = p.period
    return (H // ph) * (W // pw) < MIN_LEVEL_SAMPLES


def _sampled_levels(p: Prepared, raw) -> np.ndarray:
    """The band levels (:func:`~hsiffc.reconstruct.prepare.band_levels`: medians over the
    mean of the medians, ones where a median is not positive) from a regular subgrid of each
    band's samples, at most :data:`LEVEL_SAMPLES` of them (the level is a scale, not a
    statistic of every pixel), of the filled frame (no flagged sample). One sample per band
    and tile (a layout without repeated bands)."""
    if few_level_samples(p):
        return np.ones(len(p.lattices()))
    H, W = p.shape
    ph, pw = p.period
    n_r, n_c = -(-H // ph), -(-W // pw)
    step = max(1, int(np.ceil(np.sqrt(n_r * n_c / LEVEL_SAMPLES))))
    med = np.array([np.median(raw[r::ph * step, c::pw * step]) for (r, c), in p.lattices()])
    if not np.all(np.isfinite(med)) or np.any(med <= 0):
        return np.ones(len(med))
    return med / med.mean()


def single_lattice(p: Prepared) -> bool:
    """Whether every band has exactly one sample per tile (the fast kernels' layouts)."""
    return all(len(lat) == 1 for lat in p.lattices())


def _levels(p: Prepared, raw) -> np.ndarray:
    """The band levels (:func:`~hsiffc.reconstruct.prepare.band_levels`) of one tile row in
    four: the medians of a quarter of the samples (the level is a scale, not a statistic of
    every pixel), from the filled frame (no flagged sample)."""
    if few_level_samples(p):
        return np.ones(p.mosaic.n_bands)
    ph = p.period[0]
    H = p.shape[0]
    rows = np.arange(H)
    keep = rows[(rows // ph) % 4 == 0]  # whole blocks of ph rows from multiples of ph: the
    if keep.size < 2 * ph:  # sub-frame's row phases are the frame's
        return band_levels(prepare(raw, p.mosaic, None))
    return band_levels(prepare(raw[keep], p.mosaic, None))


def _mean_ppi(p: Prepared, raw, levels) -> np.ndarray:
    """The mean-filter PPI ``M`` (:func:`~hsiffc.reconstruct.prepare.pseudo_panchromatic`) of
    the filled frame: each band divided by its level, extended by whole tiles beyond the
    borders, averaged over the tile-sized window (``cv2.sepFilter2D``, float32)."""
    H, W = p.shape
    ph, pw = p.period
    kx, ky = ppi_kernel(pw), ppi_kernel(ph)
    inv = (1.0 / np.asarray(levels, np.float64)).astype(np.float32)
    scale = inv[p.mosaic.band_map((ph, pw))]
    my, mx = ky.size // 2, kx.size // 2
    rows = periodic_index(H, ph, my)
    cols = periodic_index(W, pw, mx)
    pad = np.empty((rows.size, cols.size), np.float32)
    scaled_padded(raw, np.ascontiguousarray(scale), rows.astype(np.int64), cols.astype(np.int64),
                  mx, pad)
    out = cv2.sepFilter2D(pad, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_CONSTANT)
    return np.ascontiguousarray(out[my:my + H, mx:mx + W])


def refined_cube(p: Prepared, cube, cube_dq, *, balance: bool, weighted: bool) -> np.ndarray:
    """Every value of ``cube`` (H, W, B) and ``cube_dq`` (any content on entry; module docstring),
    for a frame of at least two tiles each way; returns the
    (H, B) rows and bands with values left NaN for the band-median fill."""
    B = p.mosaic.n_bands
    raw = _filled(p)
    if balance and not weighted and single_lattice(p):
        _fast_edge(p, raw, cube, cube_dq)
        return _flagged(p, cube, cube_dq)
    cube_dq[...] = 0
    levels = _levels(p, raw) if balance else np.ones(B)
    mbar = _mean_ppi(p, raw, levels)
    ph, pw = p.period
    band_of = p.mosaic.band_map((ph, pw))
    eps = EDGE_EPS * max(float(np.mean(mbar, dtype=np.float64)), 0.0) + 1e-6
    ppi = np.empty(p.shape, np.float32)
    gam = np.empty(p.shape + (9,) if weighted else (1, 1, 9), np.float32)
    refine_ppi(raw, mbar, np.ascontiguousarray(band_of, np.int64),
               np.asarray(levels, np.float32), True, np.float32(eps), ph, pw, ppi, gam, weighted)
    if weighted:
        interpolate_differences(raw, ppi, levels, p.lattices(), p.period, gam, cube)
    else:  # the shared pass on the unflagged frame: l_c PPI + bilinear(raw - l_c PPI)
        interpolate_bands(raw, None, None, ppi, None, levels, p.lattices(), p.period, cube,
                          cube_dq, None)
    return _flagged(p, cube, cube_dq)


def _flagged(p: Prepared, cube, cube_dq) -> np.ndarray:
    """The DQ rule around the flagged samples; the (H, B) rows and bands left NaN."""
    if not p.any_flags:
        return np.zeros((p.shape[0], p.mosaic.n_bands), bool)
    band_of = p.mosaic.band_map(p.period)
    return flag_values(p.raw, p.dq, p.flagged, band_of, p.lattices(), p.period, cube, cube_dq)


def edge_planes(p: Prepared, raw):
    """The band levels, the edge-sensitive full-resolution PPI and the difference plane
    ``raw - l_b PPI`` of the filled frame ``raw`` (layouts of one sample per band and tile)."""
    levels = _sampled_levels(p, raw)
    mbar = _mean_ppi(p, raw, levels)
    eps = EDGE_EPS * max(float(np.mean(mbar, dtype=np.float64)), 0.0) + 1e-6
    ppi, diff = edge_ppi(raw, mbar, p.mosaic.band_map(p.period), levels, eps)
    return levels, ppi, diff


def band_origins(p: Prepared) -> np.ndarray:
    """(B, 2) int64: the first sample (row, column) of each band."""
    return np.array([lat[0] for lat in p.lattices()], np.int64)


def _fast_edge(p: Prepared, raw, cube, cube_dq) -> None:
    """"ppid_edge" on a layout of one sample per band and tile (:mod:`hsiffc.kernels.ppicube`):
    ``l_b PPI + bilinear(raw - l_b PPI)``."""
    levels, ppi, diff = edge_planes(p, raw)
    cube_of_planes(diff, ppi, levels, band_origins(p), p.period, cube, cube_dq)


def itsd_cube(p: Prepared, cube, cube_dq, *, steps: int = ITSD_STEPS,
              start: str = "bilinear") -> np.ndarray:
    """"itsd" (module docstring): every value of ``cube`` and ``cube_dq``; returns the (H, B)
    rows and bands left NaN for the band-median fill."""
    if not single_lattice(p):  # a band repeated in the tile: "ppid_edge"
        return refined_cube(p, cube, cube_dq, balance=True, weighted=False)
    raw = _filled(p)
    B = p.mosaic.n_bands
    rc = band_origins(p)
    band_of = p.mosaic.band_map(p.period)
    other = np.empty_like(cube)
    bufs = (cube, other) if steps % 2 == 0 else (other, cube)
    if start == "bilinear":  # l = 0: the tent interpolation of the frame itself
        cube_of_planes(raw, raw, np.zeros(B), rc, p.period, bufs[0], cube_dq)
    else:
        levels, ppi, diff = edge_planes(p, raw)
        cube_of_planes(diff, ppi, levels, rc, p.period, bufs[0], cube_dq)
    for i in range(steps):
        spectral_difference(raw, bufs[i % 2], rc, band_of, bufs[(i + 1) % 2])
    return _flagged(p, cube, cube_dq)
