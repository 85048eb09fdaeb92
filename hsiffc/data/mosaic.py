"""Snapshot-mosaic layouts: which band each pixel of the raw frame sees, and how bands are
named to users.

Band numbering, everywhere users see it (tables, warnings, cube band names, ``--bands``): bands
are numbered from 1 in ascending wavelength order, with the mosaic position (row and column in
the tile, counted from 0) and the centre wavelength beside the number, ``"band 3 (r0c2 550
nm)"`` (:func:`band_labels`). Bands without a wavelength come after the others, in band-index
order; without any wavelength the number is the band index plus 1. Inside the code a band is its
0-based band index (the mosaic pattern's value), which :func:`band_numbers` maps to the number.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

#: A mosaic name that states a tile size ("5x5", "4 x 4"); such a name must match the tile.
TILE_NAME = re.compile(r"\d+\s*x\s*\d+")


@dataclass(frozen=True, eq=False)
class Mosaic:
    """A repeating filter pattern of ``pattern.shape`` pixels.

    Parameters
    ----------
    pattern : (ph, pw) int array
        Band index (0-based) seen by each position of the repeating tile.
    wavelengths_nm : sequence of float, optional
        Centre wavelength of each band, in band-index order.
    offset : (row, col)
        Position of the tile origin on the sensor (IMEC filter areas start at an offset).
    fwhm_nm : sequence of float, optional
        Full width at half maximum of each band (nm), in band-index order; written into
        exported cubes (ENVI ``fwhm``). Not part of equality: it describes the bands, not the
        layout.

    Examples
    --------
    >>> m = Mosaic.square(4)
    >>> m.n_bands, m.tile_shape
    (16, (4, 4))
    >>> int(m.band_map((4, 8))[1, 5])                  # band seen by row 1, column 5
    5
    """

    pattern: np.ndarray
    wavelengths_nm: tuple[float, ...] | None = None
    offset: tuple[int, int] = (0, 0)
    name: str = field(default="", compare=False)
    fwhm_nm: tuple[float, ...] | None = field(default=None, compare=False)

    def __post_init__(self):
        p = np.asarray(self.pattern)
        if p.ndim != 2 or p.size == 0 or not np.issubdtype(p.dtype, np.integer):
            raise ValueError(
                f"pattern must be a non-empty 2-D integer array of band indices, got {p!r}")
        bands = np.unique(p)
        if bands.min() < 0 or not np.array_equal(bands, np.arange(bands.max() + 1)):
            raise ValueError(
                f"pattern must use every band index 0..n_bands-1 at least once, got {sorted(bands)}")
        object.__setattr__(self, "pattern", p.astype(np.int64))
        if self.wavelengths_nm is not None:
            wl = tuple(float(w) for w in self.wavelengths_nm)
            if len(wl) != self.n_bands:
                raise ValueError(
                    f"wavelengths_nm has {len(wl)} entries but the pattern has {self.n_bands} bands")
            object.__setattr__(self, "wavelengths_nm", wl)
        if self.fwhm_nm is not None:
            fw = tuple(float(w) for w in self.fwhm_nm)
            if len(fw) != self.n_bands:
                raise ValueError(
                    f"fwhm_nm has {len(fw)} entries but the pattern has {self.n_bands} bands")
            object.__setattr__(self, "fwhm_nm", fw)
        object.__setattr__(self, "offset", (int(self.offset[0]), int(self.offset[1])))

    def __eq__(self, other):
        if not isinstance(other, Mosaic):
            return NotImplemented
        return (np.array_equal(self.pattern, other.pattern)
                and self.wavelengths_nm == other.wavelengths_nm and self.offset == other.offset)

    def __hash__(self):
        return hash((self.pattern.tobytes(), self.pattern.shape, self.wavelengths_nm, self.offset))

    # -- constructors --------------------------------------------------------------------------
    @classmethod
    def square(cls, n: int, wavelengths_nm=None, name: str = "") -> "Mosaic":
        """An n x n tile with bands 0..n*n-1 in row-major order (IMEC 4x4, 5x5 sensors)."""
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        n = int(n)
        return cls(np.arange(n * n).reshape(n, n), wavelengths_nm, name=name or f"{n}x{n}")

    @classmethod
    def rectangular(cls, rows: int, cols: int, wavelengths_nm=None, name: str = "") -> "Mosaic":
        """A tile of ``rows`` x ``cols`` pixels with one band per position, row-major; named
        ``"{cols}x{rows}"``, width x height as ``--mosaic`` takes it."""
        return cls(np.arange(rows * cols).reshape(rows, cols), wavelengths_nm,
                   name=name or f"{cols}x{rows}")

    # -- properties ----------------------------------------------------------------------------
    @property
    def n_bands(self) -> int:
        """Number of bands in the pattern."""
        return int(self.pattern.max()) + 1

    @property
    def tile_shape(self) -> tuple[int, int]:
        """(rows, columns) of one mosaic tile."""
        return tuple(int(s) for s in self.pattern.shape)

    def describe(self) -> str:
        """The tile as the command line writes it, width x height (``--mosaic``, sidecars):
        ``"4x2 (W x H)"`` for 2 rows of 4 columns; an IMEC or other descriptive name follows.
        Stored names that look like a tile size are not repeated: files from earlier versions of
        the simulator name its 2 x 4 tile "2x4" (rows x columns) while ``--mosaic 2x4`` means 2
        wide, 4 high, so a name alone is ambiguous.

        >>> Mosaic.rectangular(2, 4).describe()
        '4x2 (W x H)'
        """
        rows, cols = self.tile_shape
        text = f"{cols}x{rows} (W x H)"
        if self.name and not TILE_NAME.fullmatch(self.name):
            text += f" {self.name}"
        return text

    def band_map(self, shape) -> np.ndarray:
        """Band index of every pixel of a frame of ``shape`` (H, W): a read-only
        :class:`BandMap` that knows its :func:`row_period` (the last few maps are kept, by
        pattern, offset and shape: a full frame's costs tens of milliseconds to build)."""
        return _band_map(self.pattern.tobytes(), self.pattern.shape, self.offset,
                         int(shape[0]), int(shape[1]))

    def to_dict(self) -> dict:
        """JSON-safe description (pattern, wavelengths, offset); :meth:`from_dict` inverts it."""
        return {
            "pattern": self.pattern.tolist(),
            "wavelengths_nm": None if self.wavelengths_nm is None else list(self.wavelengths_nm),
            "offset": list(self.offset),
            "name": self.name,
            **({} if self.fwhm_nm is None else {"fwhm_nm": list(self.fwhm_nm)}),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Mosaic":
        """The Mosaic described by :meth:`to_dict`'s output."""
        try:
            return cls(np.asarray(d["pattern"], dtype=np.int64), d.get("wavelengths_nm"),
                       tuple(d.get("offset", (0, 0))), name=d.get("name", ""),
                       fwhm_nm=d.get("fwhm_nm"))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"mosaic description {d!r} is missing 'pattern': {exc}") from exc


class BandMap(np.ndarray):
    """A band map built by :meth:`Mosaic.band_map` (read-only): an integer array of band
    indices that also says its :attr:`row_period`, the rows of its tile (rows ``y`` and
    ``y + row_period`` hold the same bands). A view or a copy of it is a plain band map
    again (:attr:`row_period` 0: unknown), and arithmetic on it gives plain arrays.
    """

    #: rows of the tile (0: unknown, as for any array not made by :meth:`Mosaic.band_map`)
    row_period: int = 0

    def __array_finalize__(self, obj):
        self.row_period = 0  # views and copies: the maker sets it on the map it made

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        plain = tuple(np.asarray(x) if isinstance(x, BandMap) else x for x in inputs)
        if "out" in kwargs:
            kwargs["out"] = tuple(np.asarray(x) if isinstance(x, BandMap) else x
                                  for x in kwargs["out"])
        return getattr(ufunc, method)(*plain, **kwargs)

    def __reduce__(self):  # pickled (to a worker process): a plain array of the same values
        return np.asarray(self).__reduce__()


@lru_cache(maxsize=8)
def _band_map(pattern: bytes, tile: tuple, offset: tuple, h: int, w: int) -> BandMap:
    p = np.frombuffer(pattern, np.int64).reshape(tile)
    rows = (np.arange(h) - offset[0]) % tile[0]
    cols = (np.arange(w) - offset[1]) % tile[1]
    out = p[rows[:, None], cols[None, :]].view(BandMap)
    out.row_period = int(tile[0])
    out.flags.writeable = False
    return out


def band_positions(mosaic) -> list:
    """(row, col) of each band's first position in the mosaic tile, in band-index order.

    >>> band_positions(Mosaic.rectangular(2, 2))
    [[0, 0], [0, 1], [1, 0], [1, 1]]
    """
    pattern = np.asarray(mosaic.pattern)
    out = []
    for b in range(mosaic.n_bands):
        r, c = np.argwhere(pattern == b)[0]
        out.append([int(r), int(c)])
    return out


def wavelength_order(n_bands: int, wavelengths_nm=None) -> list[int]:
    """Band indices in the order users count bands: ascending wavelength (stable; bands
    without a finite wavelength last, in index order); tables list bands in this order.

    >>> wavelength_order(4, [700, 500, 600, None])
    [1, 2, 0, 3]
    """
    n = int(n_bands)
    if wavelengths_nm is None:
        return list(range(n))
    if len(wavelengths_nm) != n:
        raise ValueError(f"wavelengths_nm has {len(wavelengths_nm)} entries for {n} bands")
    wl = np.array([np.nan if w is None else float(w) for w in wavelengths_nm], np.float64)
    return [int(b) for b in np.argsort(np.where(np.isfinite(wl), wl, np.inf), kind="stable")]


def band_numbers(n_bands: int, wavelengths_nm=None) -> list[int]:
    """The number users see for each band (given in band-index order): its 1-based rank in
    :func:`wavelength_order`.

    >>> band_numbers(4, [700, 500, 600, None])
    [3, 1, 2, 4]
    >>> band_numbers(3)
    [1, 2, 3]
    """
    out = [0] * int(n_bands)
    for rank, b in enumerate(wavelength_order(n_bands, wavelengths_nm)):
        out[b] = rank + 1
    return out


def band_labels(n_bands: int, wavelengths_nm=None, positions=None, *,
                virtual: bool = False) -> list[str]:
    """One label per band (given in band-index order), the way hsiffc names bands to users:
    ``"band 3 (r0c2 550 nm)"``, numbered by :func:`band_numbers`, with the mosaic position
    (``positions[b]`` = (row, col) in the tile, None for a virtual band) and the centre
    wavelength where known. No commas, so that a label is also an ENVI band name.

    Parameters
    ----------
    n_bands : int
    wavelengths_nm : sequence of n_bands float (or None entries), optional
    positions : sequence of n_bands (row, col) or None, optional
    virtual : bool
        The bands are virtual (a correction matrix's output, no mosaic position): said in
        the label.

    Examples
    --------
    >>> band_labels(3, [700.0, 500.0, 614.94], [(0, 0), (0, 1), (1, 0)])
    ['band 3 (r0c0 700 nm)', 'band 1 (r0c1 500 nm)', 'band 2 (r1c0 614.9 nm)']
    >>> band_labels(2)
    ['band 1', 'band 2']
    """
    numbers = band_numbers(n_bands, wavelengths_nm)
    out = []
    for b, k in enumerate(numbers):
        parts = []
        pos = None if positions is None else positions[b]
        if pos is not None:
            parts.append(f"r{int(pos[0])}c{int(pos[1])}")
        elif virtual:
            parts.append("virtual")
        wl = None if wavelengths_nm is None else wavelengths_nm[b]
        if wl is not None and np.isfinite(float(wl)):
            parts.append(f"{float(wl):.1f}".rstrip("0").rstrip(".") + " nm")
        out.append(f"band {k}" + (f" ({' '.join(parts)})" if parts else ""))
    return out


def mosaic_band_labels(mosaic, n_bands: int | None = None) -> list[str]:
    """:func:`band_labels` of a mosaic's bands (band-index order); without a mosaic (None),
    ``n_bands`` (default 1) plain labels ``"band 1"``, ...

    >>> mosaic_band_labels(Mosaic.rectangular(1, 2, [800.0, 700.0]))
    ['band 2 (r0c0 800 nm)', 'band 1 (r0c1 700 nm)']
    """
    if mosaic is None:
        return band_labels(1 if n_bands is None else n_bands)
    return band_labels(mosaic.n_bands, mosaic.wavelengths_nm, band_positions(mosaic))


def single_band_map(shape) -> np.ndarray:
    """The band map of a frame without a mosaic: every pixel band 0 (read-only, cached, and
    known to :func:`row_period`, so band statistics sum it by rows as a mosaic's)."""
    h, w = (int(n) for n in shape)
    return _band_map(np.zeros(1, np.int64).tobytes(), (1, 1), (0, 0), h, w)


def row_period(band_map) -> int:
    """Rows ``y`` and ``y + p`` of ``band_map`` hold the same bands: ``p`` for a band map
    built by :meth:`Mosaic.band_map` (a :class:`BandMap`: its tile's rows), 0 for any other
    array (unknown).

    Band statistics use it to sum a frame by row phase (vectorised, no per-pixel scatter) and
    fold the few phase rows into bands at the end.

    >>> bm = Mosaic.rectangular(2, 4).band_map((6, 8))  # tiles of 2 rows, 4 columns
    >>> row_period(bm), row_period(np.array(bm)), row_period(bm[1:])
    (2, 0, 0)
    """
    return int(band_map.row_period) if isinstance(band_map, BandMap) else 0
