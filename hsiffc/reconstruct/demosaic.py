"""Full-resolution demosaicing (every band at every pixel) and the alpha of its values."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ..data.dq import DQ_DTYPE
from ..kernels.demosaic import interpolate_bands
from ..data.mosaic import Mosaic
from ..data.params import validate_method
from ..files.limits import default_limits
from .prepare import (Prepared, band_levels, band_medians, ppi_kernel, prepare,
                      pseudo_panchromatic, tile_starts)
from .refined import few_level_samples, itsd_cube, refined_cube
from .tiles import tile_alpha

__all__ = ["DEMOSAIC_METHODS", "DemosaicMethod", "Demosaiced", "demosaic", "reconstruct_alpha"]


class Demosaiced(NamedTuple):
    """What :func:`demosaic` returns, whatever the method.

    Attributes
    ----------
    cube : (H, W, B) float32
        Every band at every pixel, in the frame's unit (DN).
    dq : (H, W, B) uint32
        DQ of every band value.
    alpha : (H, W, B) float32, percent, or None
        The leakage percentage of every band value, when :func:`demosaic` was given the
        frame's ``alpha``; None otherwise.
    """

    cube: np.ndarray
    dq: np.ndarray
    alpha: np.ndarray | None


@dataclass(frozen=True)
class DemosaicMethod:
    """A registered demosaicking method: what :func:`demosaic` does differently for it.

    Most methods share one compiled pass (bilinear interpolation of every band on its sample
    lattice, with the DQ rule of :mod:`hsiffc.reconstruct`), and a method is what it adds to
    it; a method with ``cube`` computes its values itself (:mod:`hsiffc.reconstruct.refined`)
    and keeps the same DQ rule.

    Attributes
    ----------
    summary : str
        What the method does, in one line (help texts, docs).
    uses_ppi : bool
        The pass interpolates ``band - PPI`` and adds the pseudo-panchromatic image back;
        the alpha of a value is then the max over the PPI's window.
    refine : callable, optional
        ``refine(prepared, cube)``: overwrites values of the bilinear cube in place after the
        pass (e.g. "nearest" puts each pixel's own-tile sample back).
    cube : callable, optional
        ``cube(prepared, cube, cube_dq) -> missing``: computes every value and its DQ itself
        (``cube_dq`` uninitialised on entry), instead of the shared pass, on frames of at least
        two tiles each way (smaller frames take "ppid"); returns the (H, B) rows and bands
        with values left NaN for the band-median fill.
    alpha_tiles : int
        The alpha of a value is the max over a centred window of ``2 alpha_tiles ph - 1 +
        len(ppi_kernel(ph)) - 1`` rows (likewise columns) for PPI methods and methods with
        ``cube``: 1 for "ppid", whose values reach one tile; 2 for methods that refine the PPI
        from neighbours one tile away; 3 for "itsd", whose two steps each reach one tile
        further than the bilinear start.
    """

    summary: str
    uses_ppi: bool = False
    refine: Callable | None = None
    cube: Callable | None = None
    alpha_tiles: int = 1


def _nearest(p: Prepared, cube):
    """Overwrite the bilinear cube with the band's sample(s) of each pixel's own tile (mean
    if the band occurs more than once per tile) where one of them is usable; the bilinear
    value stays where all are flagged or outside the frame (incomplete border tiles)."""
    H, W = p.shape
    ph, pw = p.period
    oy, ox = p.mosaic.offset
    rows0, cols0 = tile_starts(H, ph, oy), tile_starts(W, pw, ox)
    for b in range(p.mosaic.n_bands):
        acc = np.zeros(p.shape, np.float32)
        cnt = np.zeros(p.shape, np.float32)
        for r, c in zip(*np.nonzero(p.mosaic.pattern == b), strict=True):
            sr, sc = rows0 + r, cols0 + c
            vr, vc = (sr >= 0) & (sr < H), (sc >= 0) & (sc < W)
            ir, ic = np.clip(sr, 0, H - 1), np.clip(sc, 0, W - 1)
            valid = vr[:, None] & vc[None, :]
            if p.any_flags:
                valid &= p.good.take(ir, axis=0).take(ic, axis=1)
            acc += np.where(valid, p.raw.take(ir, axis=0).take(ic, axis=1), np.float32(0))
            cnt += valid
        hit = cnt > 0
        plane = cube[:, :, b]
        plane[hit] = acc[hit] / cnt[hit]


def _ppid_paper(p: Prepared, cube, cube_dq):
    return refined_cube(p, cube, cube_dq, balance=False, weighted=True)


def _ppid_edge(p: Prepared, cube, cube_dq):
    return refined_cube(p, cube, cube_dq, balance=True, weighted=False)


def _itsd(p: Prepared, cube, cube_dq):
    return itsd_cube(p, cube, cube_dq)


#: Registered demosaicking methods: name -> :class:`DemosaicMethod`.
#:
#: Adding a method: register a :class:`DemosaicMethod` here (what it changes in the shared
#: pass); :func:`demosaic` looks the name up with
#: :func:`~hsiffc.data.params.validate_method` and returns a :class:`Demosaiced` for every
#: method. The ``reconstruct`` stage, ``hsiffc correct --cube`` and ``hsiffc reflectance fit
#: --cube`` take their choices from this mapping.
DEMOSAIC_METHODS = {
    "nearest": DemosaicMethod("block replication: each band copied from the same-band sample "
                              "of the pixel's tile", refine=_nearest),
    "bilinear": DemosaicMethod("per-band bilinear interpolation of the band's sub-grid "
                               "(normalised convolution with a separable tent kernel)"),
    "ppid": DemosaicMethod("pseudo-panchromatic image difference (Mihoubi et al., IEEE TCI "
                           "2017): bilinear interpolation of band - PPI, plus the PPI",
                           uses_ppi=True),
    "ppid_paper": DemosaicMethod(
        "PPID as in Mihoubi et al. (2017) in full: edge-sensitive full-resolution PPI and "
        "direction-weighted interpolation of the band differences (no band balancing)",
        uses_ppi=True, cube=_ppid_paper, alpha_tiles=2),
    "ppid_edge": DemosaicMethod(
        "hsiffc's best: the edge-sensitive full-resolution PPI with band balancing and "
        "bilinear interpolation of the band differences (sharper than ppid)",
        uses_ppi=True, cube=_ppid_edge, alpha_tiles=2),
    "itsd": DemosaicMethod(
        "iterative spectral differences (Brauers and Aach 2006; Mizutani et al. 2014): "
        "bilinear start, then two steps of each band's difference from the pixel's own band, "
        "interpolated bilinearly", cube=_itsd, alpha_tiles=3),
}


def _alpha_plane(alpha, shape):
    a = np.ascontiguousarray(alpha, dtype=np.float32)
    if a.shape != tuple(shape):
        raise ValueError(f"alpha has shape {a.shape} but the frame has {tuple(shape)}; give "
                         "the alpha plane of this frame")
    if a.size == 0 or (np.isfinite(a.min()) and np.isfinite(a.max())):  # NaN, inf show there
        return a
    return np.where(np.isfinite(a), a, np.finfo(np.float32).max).astype(np.float32)


def _ppi_window_max(a, mosaic, tiles=1):
    """PPID's alpha: the max alpha over every raw pixel that enters the PPI at the samples of
    a value (a centred window of ``2 ph - 1 + len(ppi_kernel(ph)) - 1`` rows, likewise
    columns: an odd size, since the PPI kernel's is odd). The window holds the value's S1
    (its same-band samples within ``ph - 1`` rows and ``pw - 1`` columns) too, so this is the
    alpha of the value in every band, and S1's max is not taken."""
    ph, pw = mosaic.tile_shape
    kh, kw = ppi_kernel(ph).size, ppi_kernel(pw).size
    big = np.ones((2 * tiles * ph - 1 + kh - 1, 2 * tiles * pw - 1 + kw - 1), np.uint8)
    return cv2.dilate(a, big, borderType=cv2.BORDER_REPLICATE)


def _every_band(plane, n_bands):
    """``plane`` (H, W) as the alpha of every band, ``(H, W, n_bands)``: a read-only view that
    repeats it along the band axis (stride 0), not a copy per band."""
    return np.broadcast_to(plane[:, :, None], plane.shape + (n_bands,))


def demosaic(raw, mosaic: Mosaic, *, method: str = "bilinear", dq=None,
             alpha=None) -> Demosaiced:
    """Reconstruct every band at every pixel of a raw mosaic frame.

    Parameters
    ----------
    raw : (H, W) array
        The raw (or dark-subtracted, flat-fielded ...) mosaic frame.
    mosaic : Mosaic
        Its layout; the band sub-grids have period ``mosaic.tile_shape`` and phase given by the
        pattern position of the band plus ``mosaic.offset``.
    method : str
        One of :data:`DEMOSAIC_METHODS`:

        ``"nearest"``
            block replication: each pixel takes the same-band sample of its own tile
            (tiles start at ``mosaic.offset``).
        ``"bilinear"``
            per band, the sparse samples interpolated to every pixel by normalised
            convolution ``(K * (v w)) / (K * w)`` with the separable tent kernel ``K`` of
            half-width one tile (zero outside the frame), evaluated by a compiled kernel
            (:mod:`hsiffc.kernels.demosaic`) directly on each band's sample lattice. On a
            regular sub-grid this is exactly bilinear interpolation; at the borders it falls
            back to the nearest samples, and flagged samples (``w = 0``) drop out uniformly.
        ``"ppid"``
            pseudo-panchromatic image difference, after S. Mihoubi, O. Losson, B. Mathon,
            L. Macaire, "Multispectral demosaicing using pseudo-panchromatic image",
            IEEE Trans. Computational Imaging 3(4):982-995, 2017
            (doi:10.1109/TCI.2017.2691553). The PPI (the average over all bands) is estimated
            by averaging the raw frame over a tile-sized window (:func:`ppi_kernel`); per band
            the differences ``sample - PPI`` at the band's sites are interpolated bilinearly as
            above and the PPI is added back. Because bands share their spatial texture, the
            differences are much smoother than the bands and the PPI carries full-resolution
            detail. Implemented is the paper's simple PPI (a mean filter); its edge-sensitive
            PPI refinement and direction-weighted difference interpolation are
            ``"ppid_paper"``.
            Our addition, band balancing: the bands are first scaled to a common level (each
            band divided by its median over the mean of the band medians, like a white
            balance) and the PPI is scaled back per band, ``est_b = l_b PPI + interp(b -
            l_b PPI)``. Without it a band far below the mean level inherits the PPI's texture
            error at full size (on a ColorChecker scene under an incandescent lamp the weak
            blue bands came out worse than with bilinear). Balancing is skipped (all levels 1)
            when a band's median is not positive, e.g. on dark-subtracted noise, and on a
            frame of fewer than ``MIN_LEVEL_SAMPLES`` (16) tiles, whose few samples of each
            band make no level (an 11 x 8 frame of a 4 x 4 mosaic with half its pixels
            flagged reached 5108 DN balanced, where the frame holds at most 1000). Flagged
            samples enter the PPI as the mean of their unflagged same-band neighbours one
            tile away; where a PPI window holds no usable pixel at all, the band value is
            the bilinear one.
        ``"ppid_paper"``
            the paper's PPID in full: the edge-sensitive, full-resolution PPI (each pixel's
            sample minus its offset from the mean-filter PPI, predicted from its same-band
            neighbours one tile away with weights that fall across edges) and the
            direction-weighted interpolation of the differences; no band balancing
            (:mod:`hsiffc.reconstruct.refined`).
        ``"ppid_edge"``
            hsiffc's best: that full-resolution PPI with ``"ppid"``'s band balancing, and
            bilinear interpolation of the differences. Frames under two tiles in either
            direction take ``"ppid"`` for both.
        ``"itsd"``
            iterative spectral differences, after J. Brauers, T. Aach, "A color filter array
            based multispectral camera", 12. Workshop Farbbildverarbeitung, 2006 (the
            spectral difference) and Y. Mizutani et al., "Multispectral demosaicking
            algorithm based on inter-channel correlation", IEEE VCIP 2014 (its iteration):
            start from "bilinear"; a step estimates band ``b`` at a pixel of band ``c`` as
            the pixel's own sample plus the bilinear interpolation, over ``b``'s samples, of
            ``b``'s difference from the previous estimate of ``c`` there. Two steps for every
            band pair (Mizutani et al. choose the number per pair from the bands' spectral
            distance; on the development scenes one step was worse than none and two better
            than three). No PPI. A band repeated in the tile, or a frame under two tiles,
            takes "ppid_edge" ("ppid").
    dq : (H, W) uint32, optional
        Raw DQ flags; non-zero samples are not used as sources (see the package docstring).
    alpha : (H, W) float32, optional
        The frame's leakage percentage; when given, its cube (as :func:`reconstruct_alpha`
        with ``resolution="full"``) is computed in the same pass.

    Returns
    -------
    Demosaiced
        ``(cube, dq, alpha)``, for every method:

        cube : (H, W, B) float32
            Finite everywhere; band axis in band-index order.
        dq : (H, W, B) uint32
            DQ of every band value, by the rule in the package docstring.
        alpha : (H, W, B) float32, or None when ``alpha`` is not given
            For the PPI methods one plane for every band (the PPI window's max): a read-only
            view that repeats it along the band axis (``np.broadcast_to``);
            ``np.array(result.alpha)`` gives a writable copy.

    Raises
    ------
    ParameterError
        ``method`` is not one of :data:`DEMOSAIC_METHODS` (one line with the valid names).

    Examples
    --------
    >>> import numpy as np
    >>> from hsiffc.data.mosaic import Mosaic
    >>> mosaic = Mosaic.square(2)                       # 2 x 2 tile, 4 bands
    >>> raw = np.tile(np.array([[10., 20.], [30., 40.]], np.float32), (4, 4))   # (8, 8) DN
    >>> cube, cube_dq, cube_alpha = demosaic(raw, mosaic, method="bilinear")
    >>> cube.shape, cube[3, 3].tolist(), int(cube_dq.max()), cube_alpha   # flat stays flat
    ((8, 8, 4), [10.0, 20.0, 30.0, 40.0], 0, None)
    """
    how = validate_method(method, DEMOSAIC_METHODS, "demosaic method")
    p = prepare(raw, mosaic, dq)
    H, W = p.shape
    B = mosaic.n_bands
    own = how.cube is not None and H >= 2 * mosaic.tile_shape[0] and W >= 2 * mosaic.tile_shape[1]
    if how.cube is not None and not own:  # a frame under two tiles: as "ppid"
        how = DEMOSAIC_METHODS["ppid"]
    windowed = how.uses_ppi or how.cube is not None  # alpha: one window max for every band
    per_value = 8 + (4 if alpha is not None and not windowed else 0)  # cube, DQ, alpha
    default_limits().check_bytes(  # before allocating: a 250 x 250 tile is 62,500 bands
        path=None, nbytes=H * W * B * per_value,
        what=f"the {method} cube of a {W} x {H} px frame with {B} bands "
             f"({mosaic.describe()})")
    ppi = ppi_ok = None
    levels = np.ones(B)
    if how.uses_ppi and not own:
        levels = np.ones(B) if few_level_samples(p) else band_levels(p)
        ppi, ppi_ok = pseudo_panchromatic(p, levels)
    a = cube_alpha = None
    if alpha is not None:
        a = _alpha_plane(alpha, p.shape)
        if windowed:  # the window max: every band's alpha (the window holds S1)
            a, cube_alpha = None, _every_band(_ppi_window_max(a, mosaic, how.alpha_tiles), B)
        else:
            cube_alpha = np.empty((H, W, B), np.float32)
    cube = np.empty((H, W, B), np.float32)
    if own:
        cube_dq = np.empty((H, W, B), DQ_DTYPE)  # every value written by the method
        missing = how.cube(p, cube, cube_dq)
    else:
        cube_dq = np.empty((H, W, B), DQ_DTYPE)  # every value written by the kernel
        missing = interpolate_bands(p.raw, p.dq, a, ppi, ppi_ok, levels, p.lattices(),
                                    mosaic.tile_shape, cube, cube_dq,
                                    None if a is None else cube_alpha)
    fill = np.flatnonzero(missing.any(axis=0))  # bands with values whose wide support
    for b, med in zip(fill, band_medians(p, fill), strict=True):  # has no usable sample
        med = np.float32(med)
        for y in np.flatnonzero(missing[:, b]):
            row = cube[y, :, b]
            row[np.isnan(row)] = med
    if how.refine is not None:
        how.refine(p, cube)
    return Demosaiced(cube, cube_dq, cube_alpha)


def reconstruct_alpha(alpha, mosaic: Mosaic, *, method: str = "bilinear",
                      resolution: str = "full") -> np.ndarray:
    """Leakage percentage of cube values: the max alpha of the raw pixels each value is made
    from, ``(H, W, B)`` or ``(H', W', B)`` float32.

    ``resolution="tile"``: the max over the band's samples in the tile. ``"full"``: the max
    over the same-band samples in the bilinear support ``S1`` (which holds the sources of
    "nearest" and "bilinear"); for "ppid" also over every raw pixel that enters the PPI at
    those samples (a window of ``2 ph - 1 + len(ppi_kernel(ph)) - 1`` rows, likewise columns).
    Fallback paths for flagged sources are not counted: those values carry DQ flags.
    Non-finite alpha counts as the largest float32. For ``"full"`` this is the alpha part of
    :func:`demosaic` (one kernel computes both); pass ``alpha=`` there to get it with the cube.

    Parameters
    ----------
    alpha : (H, W) array, percent
        Leakage percentage of every raw pixel.
    mosaic : Mosaic
        Layout of the raw frame.
    method : str
        Demosaicking method the cube was made with (one of :data:`DEMOSAIC_METHODS`).
    resolution : {"full", "tile"}
        Full-resolution cube (H, W, B) or one value per complete tile (H', W', B).

    Returns
    -------
    ndarray of float32, percent
        (H, W, B) or (H', W', B).
    """
    a = np.asarray(alpha)
    if a.ndim != 2:
        raise ValueError(f"alpha must be a 2-D plane (H, W), got shape {a.shape}")
    if resolution == "tile":
        return tile_alpha(_alpha_plane(a, a.shape), mosaic)
    if resolution != "full":
        raise ValueError(f"resolution must be 'full' or 'tile', got {resolution!r}")
    return demosaic(np.zeros(a.shape, np.float32), mosaic, method=method, alpha=a).alpha
