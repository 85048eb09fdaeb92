"""Input handling and shared pieces of reconstruction: the prepared frame, separable filters,
the pseudo-panchromatic image and band statistics."""

from __future__ import annotations

from functools import cached_property

import cv2
import numpy as np

from ..data.dq import DQ, DQ_DTYPE, as_dq
from ..kernels.demosaic import EPS
from ..kernels.lattice import band_samples, lattice_arrays
from ..kernels.ppicube import flagged_indices
from ..kernels.ppi import ppi_image
from ..kernels.select import medians_of
from ..data.mosaic import Mosaic

__all__ = ["EPS", "Prepared", "band_levels", "band_median", "band_medians", "median_in_place",
           "periodic_index",
           "ppi_kernel", "prepare", "pseudo_panchromatic", "sep_filter", "tile_starts"]


def ppi_kernel(period: int) -> np.ndarray:
    """1-D averaging kernel of the pseudo-panchromatic image for one axis of the tile.

    Odd period p: a box of p ones / p. Even period p: p + 1 taps ``[1/2, 1, ..., 1, 1/2] / p``,
    centred, so that every tile position gets the same total weight 1/p (the two end taps
    see the same band). Separable in rows and columns, as in Mihoubi et al. (2017).

    Parameters
    ----------
    period : int
        Tile size along the axis (pixels, >= 1).

    Returns
    -------
    ndarray of float32, (p,) or (p + 1,)
        Taps summing to 1.

    Examples
    --------
    >>> ppi_kernel(2).tolist(), round(float(ppi_kernel(3).sum()), 6)
    ([0.25, 0.5, 0.25], 1.0)
    """
    p = int(period)
    if p % 2:
        return np.full(p, 1.0 / p, np.float32)
    k = np.ones(p + 1, np.float64)
    k[0] = k[-1] = 0.5
    return (k / p).astype(np.float32)


def sep_filter(img: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """Separable correlation with zero outside the frame (for normalised convolution).

    Parameters
    ----------
    img : (H, W) ndarray of float32
        Plane to filter.
    kx, ky : 1-D ndarray of float32
        Kernels along the columns (x) and the rows (y).

    Returns
    -------
    ndarray of float32, (H, W)
    """
    return cv2.sepFilter2D(img, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_CONSTANT)


class Prepared:
    """A raw frame made ready for interpolation (see :func:`prepare`).

    Attributes
    ----------
    raw : (H, W) float32, 0 where the input was not finite
    dq : (H, W) uint32 or None (None: no sample is flagged); NONFINITE | DO_NOT_USE added
        where the input was not finite
    mosaic : Mosaic
    medians : dict of int -> float
        The band medians computed so far (:func:`band_medians` fills it).
    """

    def __init__(self, raw: np.ndarray, dq: np.ndarray | None, mosaic: Mosaic):
        self.raw, self.dq, self.mosaic = raw, dq, mosaic
        self.medians: dict[int, float] = {}  # band -> median of its usable samples, once known

    @property
    def shape(self):
        """(H, W) of the frame."""
        return self.raw.shape

    @property
    def period(self):
        """Tile shape (ph, pw) of the mosaic."""
        return self.mosaic.tile_shape

    @property
    def any_flags(self) -> bool:
        """True when some sample is flagged (``dq`` is not None)."""
        return self.dq is not None

    @cached_property
    def good(self) -> np.ndarray:
        """(H, W) bool: usable as a source."""
        return np.ones(self.shape, bool) if self.dq is None else self.dq == 0

    @cached_property
    def flagged(self) -> np.ndarray:
        """(n,) int64: flat indices of the flagged samples (empty without flags)."""
        if self.dq is None:
            return np.zeros(0, np.int64)
        return flagged_indices(self.dq)

    @cached_property
    def band_map(self) -> np.ndarray:
        """(H, W) band index of every pixel."""
        return self.mosaic.band_map(self.shape)

    def lattices(self) -> list[list[tuple[int, int]]]:
        """Per band, the first sample (row, col) of each of its pattern positions.

        Returns
        -------
        list of list of (int, int)
            Indexed by band; one (row, col) per occurrence of the band in the tile.
        """
        ph, pw = self.period
        oy, ox = self.mosaic.offset
        out = [[] for _ in range(self.mosaic.n_bands)]
        for r, c in np.ndindex(ph, pw):
            out[int(self.mosaic.pattern[r, c])].append(((oy + r) % ph, (ox + c) % pw))
        return out

    def band_samples(self, b: int) -> np.ndarray:
        """The usable samples of band ``b`` (1-D float32, any order).

        Parameters
        ----------
        b : int
            Band index.

        Returns
        -------
        ndarray of float32, (n,)
            Unflagged samples of the band, in the unit of ``raw``.
        """
        return self.samples_of([b])[0]

    def samples_of(self, bands) -> list[np.ndarray]:
        """:meth:`band_samples` of each band in ``bands`` in one compiled pass (parallel over
        the bands, where numpy's strided ``compress`` takes one band after another).

        Parameters
        ----------
        bands : sequence of int

        Returns
        -------
        list of 1-D float32 arrays (views into one buffer)
        """
        out, counts = self.sample_rows(bands)
        return [out[i, :n] for i, n in enumerate(counts)]

    def sample_rows(self, bands) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`samples_of` as one buffer: ``(samples, counts)``, band ``bands[i]``'s
        usable samples in ``samples[i, :counts[i]]``."""
        lats = self.lattices()
        bands = np.asarray(bands, np.int64)
        ph, pw = self.period
        H, W = self.shape
        size = [sum(len(range(r, H, ph)) * len(range(c, W, pw)) for r, c in lats[b])
                for b in bands]
        out = np.empty((len(bands), max(size, default=0)), np.float32)
        counts = np.zeros(len(bands), np.int64)
        band_samples(self.raw, np.zeros((1, 1), DQ_DTYPE) if self.dq is None else self.dq,
                     self.dq is not None, *lattice_arrays(lats), bands, ph, pw, out, counts)
        return out, counts


def prepare(raw, mosaic, dq) -> Prepared:
    """Check a raw frame and its DQ; non-finite samples become 0 with NONFINITE | DO_NOT_USE.

    The frame is not copied when it is float32 and finite; ``dq`` is None when nothing is
    flagged (an all-zero plane is dropped).

    Parameters
    ----------
    raw : (H, W) array_like
        Mosaic frame (DN or any linear unit).
    mosaic : Mosaic
        Its layout.
    dq : (H, W) uint32 array or None
        DQ flags of the raw pixels.

    Returns
    -------
    Prepared

    Raises
    ------
    ValueError
        ``raw`` is not 2-D, or ``dq`` has another shape.
    """
    if not isinstance(mosaic, Mosaic):
        raise TypeError(f"mosaic must be a hsiffc.data.mosaic.Mosaic, got {type(mosaic).__name__}")
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"raw must be a 2-D mosaic frame (H, W), got shape {raw.shape}")
    if raw.dtype.kind not in "biuf":
        raise ValueError(f"raw must hold real numbers (DN), got dtype {raw.dtype}")
    data = np.ascontiguousarray(raw, dtype=np.float32)
    flags = None
    if dq is not None:
        flags = as_dq(dq)
        if flags.shape != data.shape:
            raise ValueError(f"dq has shape {flags.shape} but raw has {data.shape}")
        flags = np.ascontiguousarray(flags, dtype=DQ_DTYPE) if flags.any() else None
    finite = np.isfinite(data)
    if not finite.all():
        data = np.where(finite, data, np.float32(0.0))
        flags = np.zeros(data.shape, DQ_DTYPE) if flags is None else flags.copy()
        flags[~finite] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
    return Prepared(data, flags, mosaic)


def median_in_place(vals: np.ndarray) -> float:
    """``np.median(vals)`` (same value), partitioning ``vals`` itself instead of a copy.

    For an even count the lower middle value is the max of the lower part after one
    partition: numpy's partition for two positions is several times slower on band
    samples."""
    n = vals.size
    if n == 0:
        return 0.0
    k = n // 2
    vals.partition(k)
    if n % 2:
        return float(vals[k])
    return float(np.mean(np.array([vals[:k].max(), vals[k]], vals.dtype)))


def band_median(p: Prepared, b: int) -> float:
    """Median of the usable samples of band ``b`` (0 if there is none).

    Parameters
    ----------
    p : Prepared
        The frame.
    b : int
        Band index.

    Returns
    -------
    float
        In the unit of the frame.
    """
    return float(band_medians(p, [b])[0])


def band_medians(p: Prepared, bands) -> np.ndarray:
    """The median of the usable samples of each band in ``bands`` (0 for a band with none),
    cached in ``p.medians`` (PPID's band levels and the no-source fill share them). The
    samples of the bands not cached yet are gathered in one compiled pass
    (:meth:`Prepared.sample_rows`), then their medians taken in parallel, one band per
    thread (:func:`hsiffc.kernels.select.medians_of`, the value of :func:`median_in_place`).

    Parameters
    ----------
    p : Prepared
        The frame.
    bands : iterable of int
        Band indices.

    Returns
    -------
    ndarray of float64, (len(bands),)
    """
    bands = [int(b) for b in bands]
    todo = [b for b in dict.fromkeys(bands) if b not in p.medians]
    if todo:  # every band in its own thread (numba's partition: no GIL held)
        p.medians.update(zip(todo, medians_of(*p.sample_rows(todo)).tolist()))
    return np.array([p.medians[b] for b in bands], np.float64)


def band_levels(p: Prepared) -> np.ndarray:
    """Relative level of every band (median of its unflagged samples over the mean of those
    medians), or all ones when a band has no positive median (e.g. dark-subtracted noise).
    The samples of all bands are gathered in one compiled pass (:func:`band_medians`).

    Parameters
    ----------
    p : Prepared
        The frame.

    Returns
    -------
    ndarray of float64, (B,)
        Dimensionless levels (mean 1), or ones.
    """
    med = band_medians(p, range(p.mosaic.n_bands))
    if not np.all(np.isfinite(med)) or np.any(med <= 0):
        return np.ones(p.mosaic.n_bands)
    return med / med.mean()


def tile_starts(n: int, period: int, offset: int) -> np.ndarray:
    """First row (column) of the tile each row (column) belongs to (may be negative).

    Parameters
    ----------
    n : int
        Number of rows (columns).
    period : int
        Tile size along the axis.
    offset : int
        Mosaic offset along the axis.

    Returns
    -------
    ndarray of int, (n,)
    """
    i = np.arange(n)
    return i - (i - offset) % period


def periodic_index(n: int, period: int, margin: int) -> np.ndarray:
    """Indices -margin..n+margin-1 mapped into 0..n-1 by whole periods (same band).

    Parameters
    ----------
    n : int
        Length of the axis.
    period : int
        Tile size along the axis.
    margin : int
        Extension on each side (pixels).

    Returns
    -------
    ndarray of int, (n + 2 margin,)
    """
    i = np.arange(-margin, n + margin)
    low = i < 0
    i[low] += period * (-(i[low] // period))
    high = i >= n
    i[high] -= period * ((i[high] - n) // period + 1)
    return np.clip(i, 0, n - 1)


def pseudo_panchromatic(p: Prepared, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The PPI: the raw frame averaged over a tile-sized neighbourhood (:func:`ppi_kernel`).

    Flagged samples are first replaced by the tent-weighted mean of their unflagged same-band
    neighbours one tile away (8 neighbours; excluded when none is usable); each band is
    divided by its level; the frame is extended beyond its borders by whole tiles (same band),
    so that every PPI window sees every band and a spatially uniform scene gives a constant
    PPI. Evaluated by the compiled kernel :mod:`hsiffc.kernels.ppi`.

    Parameters
    ----------
    p : Prepared
        The frame.
    levels : (B,) ndarray
        Band levels from :func:`band_levels` (ones: no balancing).

    Returns
    -------
    ppi : ndarray of float32, (H, W)
        In the unit of the frame.
    defined : ndarray of bool, (H, W), or None
        Where the PPI window held a usable pixel (None: everywhere).
    """
    H, W = p.shape
    ph, pw = p.period
    kx, ky = ppi_kernel(pw), ppi_kernel(ph)
    rows = periodic_index(H, ph, ky.size // 2)
    cols = periodic_index(W, pw, kx.size // 2)
    inv = (1.0 / np.asarray(levels, np.float64)).astype(np.float32)
    ppi, ok = ppi_image(p.raw, p.dq, p.mosaic.band_map((ph, pw)), inv, rows, cols, kx, ky)
    return ppi, (None if p.dq is None else ok)
