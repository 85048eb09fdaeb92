"""A spectral cube with what its bands are: :class:`Cube`."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..data.dq import DQ_DTYPE, as_dq
from ..data.mosaic import band_labels

__all__ = ["Cube", "default_bands"]

#: wavelengths (nm) a red, green and blue display channel stand for
_RGB_NM = (640.0, 550.0, 460.0)


def default_bands(wavelengths_nm) -> list[int]:
    """Three band indices (red, green, blue) for a pseudo-colour view of a cube.

    Where the bands cover the visible range, those nearest 640, 550 and 460 nm; otherwise
    (a NIR sensor) the bands at 90, 50 and 10 % of the wavelength range, so that long
    wavelengths are shown red. Without wavelengths: the last, middle and first band.

    Examples
    --------
    >>> default_bands([450, 500, 550, 600, 650])
    [4, 2, 0]
    >>> default_bands([700, 800, 900])
    [2, 1, 0]
    """
    if wavelengths_nm is None:
        raise ValueError("default_bands needs the wavelengths (or give the bands yourself)")
    wl = np.asarray(wavelengths_nm, np.float64)
    n = len(wl)
    if n == 0:
        raise ValueError("a cube without bands has no default bands")
    if not np.all(np.isfinite(wl)):
        return [n - 1, n // 2, 0]
    lo, hi = float(wl.min()), float(wl.max())
    if lo <= _RGB_NM[2] + 20 and hi >= _RGB_NM[0] - 20:
        targets = _RGB_NM
    else:
        targets = tuple(lo + q * (hi - lo) for q in (0.9, 0.5, 0.1))
    return [int(np.argmin(np.abs(wl - t))) for t in targets]


def frame_unit(meta) -> str:
    """The unit of a frame's values: what a stage recorded (``meta["units"]``, e.g. the
    reflectance stage's "reflectance factor"), else DN."""
    return str(meta.get("unit") or meta.get("units") or "DN")


def _tuple(values, n, what):
    if values is None:
        return None
    out = tuple(values)
    if len(out) != n:
        raise ValueError(f"{what} has {len(out)} entries for a cube of {n} bands")
    return out


@dataclass(frozen=True, eq=False)
class Cube:
    """An ``(H, W, B)`` spectral cube, its DQ and alpha, and what its bands are.

    Attributes
    ----------
    data : (H, W, B) float32
        Values in :attr:`unit` (DN unless a stage changed the unit).
    dq : (H, W, B) uint32
        :class:`hsiffc.data.dq.DQ` bits.
    alpha : (H, W, B) float32 or None
        Leakage percentage (percent), None when the pipeline computed none.
    wavelengths_nm, fwhm_nm : tuple of B floats, or None
        Band centres and widths (nm).
    positions : tuple of B (row, col) or None entries, or None
        Where each band sits in the mosaic tile (None for virtual bands).
    band_index : tuple of B ints
        The band's index in the pipeline's cube (the mosaic's band order), kept by
        :meth:`sorted`.
    unit : str
    history : tuple of dict
        One entry per pipeline stage the data passed.
    attrs : dict
        Anything else worth keeping (exposure_ms, source, ...): JSON-able values.
    """

    data: np.ndarray
    dq: np.ndarray
    alpha: np.ndarray | None = None
    wavelengths_nm: tuple | None = None
    fwhm_nm: tuple | None = None
    positions: tuple | None = None
    band_index: tuple | None = None
    unit: str = "DN"
    history: tuple = ()
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        data = np.asarray(self.data)
        if data.ndim != 3:
            raise ValueError(f"a cube is (H, W, bands); got data of shape {data.shape}: "
                             "reconstruct the mosaic frame first (the reconstruct stage, or "
                             "hsiffc.reconstruct.demosaic / tile_cube)")
        if data.dtype != np.float32:
            data = data.astype(np.float32)
        dq = as_dq(self.dq)
        if dq.shape != data.shape:
            raise ValueError(f"dq has shape {dq.shape} but data has {data.shape}")
        alpha = self.alpha
        if alpha is not None:
            alpha = np.asarray(alpha, np.float32)
            if alpha.shape != data.shape:
                raise ValueError(f"alpha has shape {alpha.shape} but data has {data.shape}")
        n = data.shape[2]
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "dq", dq)
        object.__setattr__(self, "alpha", alpha)
        wl = _tuple(self.wavelengths_nm, n, "wavelengths_nm")
        object.__setattr__(self, "wavelengths_nm",
                           None if wl is None else tuple(float(w) for w in wl))
        fw = _tuple(self.fwhm_nm, n, "fwhm_nm")
        object.__setattr__(self, "fwhm_nm", None if fw is None else tuple(float(w) for w in fw))
        pos = _tuple(self.positions, n, "positions")
        object.__setattr__(self, "positions", None if pos is None else tuple(
            None if p is None else (int(p[0]), int(p[1])) for p in pos))
        idx = _tuple(self.band_index, n, "band_index")
        object.__setattr__(self, "band_index",
                           tuple(range(n)) if idx is None else tuple(int(i) for i in idx))
        object.__setattr__(self, "history", tuple(self.history))
        object.__setattr__(self, "attrs", dict(self.attrs))

    @classmethod
    def from_frame(cls, frame) -> "Cube":
        """The cube of a reconstructed :class:`~hsiffc.data.frame.Frame` (``frame.is_cube``), with
        the wavelengths, widths and positions the reconstruct stage recorded."""
        if not frame.is_cube:
            raise ValueError("this frame is a 2-D mosaic, not a cube: add a reconstruct stage "
                             "to the pipeline (or hsiffc correct --cube METHOD)")
        meta = frame.meta
        attrs = {"exposure_ms": meta.get("exposure_ms"), "bit_depth": meta.get("bit_depth"),
                 "kind": meta.get("kind"), "illumination": meta.get("illumination"),
                 "source": None if meta.get("source") is None else str(meta.get("source")),
                 "reconstruction": meta.get("reconstruction")}
        return cls(frame.data, frame.dq, frame.alpha, meta.get("wavelengths_nm"),
                   meta.get("fwhm_nm"), meta.get("band_positions"),
                   unit=frame_unit(meta), history=meta.get("history", ()),
                   attrs={k: v for k, v in attrs.items() if v is not None})

    @property
    def n_bands(self) -> int:
        """Number of bands B."""
        return int(self.data.shape[2])

    @property
    def is_sorted(self) -> bool:
        """Whether the bands run by wavelength, ascending (True without wavelengths)."""
        wl = self.wavelengths_nm
        return wl is None or all(a <= b for a, b in zip(wl, wl[1:]))

    def order(self) -> np.ndarray:
        """Band indices that sort the bands by wavelength, ascending (stable)."""
        if self.wavelengths_nm is None:
            return np.arange(self.n_bands)
        return np.argsort(np.asarray(self.wavelengths_nm), kind="stable")

    def select(self, bands) -> "Cube":
        """A cube of the given bands (indices into this cube), in that order."""
        idx = [int(b) for b in bands]

        def pick(seq):
            return None if seq is None else tuple(seq[i] for i in idx)

        take = (lambda a: None if a is None else np.take(a, idx, axis=2))
        return replace(self, data=take(self.data), dq=take(self.dq), alpha=take(self.alpha),
                       wavelengths_nm=pick(self.wavelengths_nm), fwhm_nm=pick(self.fwhm_nm),
                       positions=pick(self.positions), band_index=pick(self.band_index))

    def sorted(self) -> "Cube":
        """This cube with its bands by wavelength, ascending (itself when they already are)."""
        return self if self.is_sorted else self.select(self.order())

    def band_names(self) -> list[str]:
        """A name per band, in this cube's band order, as hsiffc names bands everywhere
        (:func:`hsiffc.data.mosaic.band_labels`): numbered from 1 by wavelength, with the
        mosaic position and the wavelength, e.g. ``"band 3 (r0c2 614.9 nm)"`` (``virtual``
        for a correction matrix's bands; no commas: ENVI lists are comma-separated)."""
        virtual = bool((self.attrs.get("reconstruction") or {}).get("correction"))
        return band_labels(self.n_bands, self.wavelengths_nm, self.positions, virtual=virtual)

    def default_bands(self) -> list[int]:
        """Red, green, blue band indices for a pseudo-colour view (:func:`default_bands`)."""
        if self.wavelengths_nm is None:
            n = self.n_bands
            return [n - 1, n // 2, 0]
        return default_bands(self.wavelengths_nm)

    def nearest_band(self, wavelength_nm: float) -> int:
        """Index of the band whose centre is nearest ``wavelength_nm``."""
        if self.wavelengths_nm is None:
            raise ValueError("this cube's bands have no wavelengths; choose bands by index")
        return int(np.argmin(np.abs(np.asarray(self.wavelengths_nm) - float(wavelength_nm))))

    def to_xarray(self):
        """An ``xarray.Dataset`` (see :func:`hsiffc.cubes.to_xarray`)."""
        from .xr import to_xarray

        return to_xarray(self)

    def describe(self) -> dict:
        """JSON-able description of the bands and the cube (for provenance and attributes)."""
        return {"shape": list(self.data.shape), "unit": self.unit,
                "band_order": "wavelength ascending" if self.is_sorted else "band index",
                "wavelengths_nm": None if self.wavelengths_nm is None
                else list(self.wavelengths_nm),
                "fwhm_nm": None if self.fwhm_nm is None else list(self.fwhm_nm),
                "band_index": list(self.band_index),
                "band_positions": None if self.positions is None
                else [None if p is None else list(p) for p in self.positions],
                "band_names": self.band_names(), "alpha": self.alpha is not None,
                "dq_dtype": np.dtype(DQ_DTYPE).name}
