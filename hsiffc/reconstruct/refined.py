"""Demosaicking on a full-resolution pseudo-panchromatic image: "ppid_paper" and "ppid_edge".

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

Flagged samples first take the tent-weighted mean of their usable same-band neighbours (as in
the PPI), so that no flagged value is a source; then the DQ rule of the package is applied
around each flagged sample (the values whose one-tile support holds no usable sample take the
twice-wide bilinear estimate and the flags), so the DQ plane is that of every other method.
"""

from __future__ import annotations

import numpy as np

from ..kernels.refined import fill_flagged, flag_values, interpolate_differences, refine_ppi
from .prepare import Prepared, band_levels, band_medians, pseudo_panchromatic

__all__ = ["EDGE_EPS", "refined_cube"]

#: ``eps`` of the edge weights, as a fraction of the frame's mean PPI level
EDGE_EPS = 0.02


def _filled(p: Prepared) -> np.ndarray:
    """The frame with flagged samples replaced by their same-band neighbours' mean (the band
    median where none is usable)."""
    if not p.any_flags:
        return p.raw
    out = np.empty(p.shape, np.float32)
    ph, pw = p.period
    fill_flagged(p.raw, p.dq, ph, pw, out)
    bad = np.isnan(out)
    if bad.any():
        bands = p.band_map[bad]
        med = band_medians(p, np.unique(bands))
        out[bad] = med[np.searchsorted(np.unique(bands), bands)].astype(np.float32)
    return out


def refined_cube(p: Prepared, cube, cube_dq, *, balance: bool, weighted: bool) -> np.ndarray:
    """Every value of ``cube`` (H, W, B) and ``cube_dq`` (zero on entry; module docstring),
    for a frame of at least two tiles each way; returns the
    (H, B) rows and bands with values left NaN for the band-median fill."""
    B = p.mosaic.n_bands
    levels = band_levels(p) if balance else np.ones(B)
    mbar, ok = pseudo_panchromatic(p, levels)
    if ok is not None and not ok.all():
        mbar = np.where(ok, mbar, np.float32(mbar[ok].mean() if ok.any() else 0.0))
    raw = _filled(p)
    ph, pw = p.period
    band_of = p.mosaic.band_map((ph, pw))
    eps = EDGE_EPS * max(float(np.mean(mbar, dtype=np.float64)), 0.0) + 1e-6
    ppi = np.empty(p.shape, np.float32)
    gam = np.empty(p.shape + (9,) if weighted else (1, 1, 9), np.float32)
    refine_ppi(raw, mbar, np.ascontiguousarray(band_of, np.int64),
               np.asarray(levels, np.float32), True, np.float32(eps), ph, pw, ppi, gam, weighted)
    interpolate_differences(raw, ppi, levels, p.lattices(), p.period, gam, weighted, cube)
    if not p.any_flags:
        return np.zeros((p.shape[0], B), bool)
    return flag_values(p.raw, p.dq, band_of, p.lattices(), p.period, cube, cube_dq)
