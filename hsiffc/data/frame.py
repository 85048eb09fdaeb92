"""The data that flows through a pipeline: a frame with its data-quality plane and metadata."""

from __future__ import annotations

import math

from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np

from .dark import subtract_dark
from .dq import DQ, DQ_DTYPE, as_dq
from .mosaic import Mosaic, band_labels, mosaic_band_labels, single_band_map
from .sweep import Sweep


#: The states a stage can require, produce or remove (``Stage.requires`` / ``produces`` /
#: ``removes``): "mosaic" (a 2-D mosaic frame), "cube" (reconstructed), "raw" (no dark removed),
#: "dark_subtracted" (a dark removed), "response" (the data, plus the dark removed, are still the
#: sensor's response: no flat-field or linearisation yet), "alpha" (an alpha plane).
STATES = ("mosaic", "cube", "raw", "dark_subtracted", "response", "alpha")
#: What a frame read from a file offers.
INPUT_STATE = frozenset({"mosaic", "raw", "response"})


def _check_acquisition(meta: dict) -> None:
    """The exposure and bit depth a frame carries are what the stages compute with: refuse
    values no camera produces (a NaN or infinite exposure matched any master dark, a bit
    depth of 0 flagged every pixel SATURATED)."""
    e = meta.get("exposure_ms")
    if e is not None:
        try:
            ok = math.isfinite(float(e)) and float(e) >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"exposure_ms must be a finite time >= 0 in ms, got {e!r}; give "
                             "the frame's exposure time in milliseconds")
    depth = meta.get("bit_depth")
    if depth is not None:
        try:
            ok = float(depth) == int(depth) and 1 <= int(depth) <= 32
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"bit_depth must be a whole number 1..32, got {depth!r}; give the "
                             "ADC's bit depth (full scale 2**bit_depth - 1 DN)")


@dataclass(frozen=True, eq=False)
class Frame:
    """One raw mosaic frame ``(H, W)`` or reconstructed cube ``(H', W', bands)``.

    Attributes
    ----------
    data : ndarray, float32
        DN (raw or corrected; never silently rescaled).
    dq : ndarray, uint32
        :class:`hsiffc.data.dq.DQ` bits, same shape as ``data``.
    meta : mapping
        ``exposure_ms``, ``bit_depth``, ``mosaic`` (Mosaic or None), ``kind`` ("light"/"dark"),
        ``illumination``, ``wavelengths_nm`` (cubes), ``history`` (tuple of dicts, one per stage
        the frame passed), and anything else a stage records for information.
    alpha : ndarray or None
        Leakage percentage per pixel (percent) once an alpha stage has run; ``inf`` where no
        light rate can be estimated (always with the LEAKAGE bit).
    dark_removed : (H, W) ndarray, float32, or None
        The dark (DN) a stage subtracted from ``data`` (None: no dark removed yet). Kept by
        reference (no copy), so :attr:`raw` adds back exactly what was removed.
    corrected_by : str or None
        The stage that made ``data`` something other than the sensor's response less
        ``dark_removed`` (a flat-field or a linearisation); None while the data still are the
        response. The raw response is then no longer available.
    raw_response : (H, W) ndarray, float32, or None
        The sensor's raw response kept by the stage that removed the dark
        (:meth:`dark_subtracted`: the data before subtraction, read-only), so that :attr:`raw`
        is exact and not recomputed; None: :attr:`raw` is ``data + dark_removed``. Frames made
        by :meth:`replace` keep it while their data and dark stay the same.

    The state a stage needs (see :meth:`state`) is read from these typed fields, never from
    ``meta`` strings.

    Examples
    --------
    >>> f = Frame(np.full((4, 4), 100, np.uint16), np.zeros((4, 4), np.uint32),
    ...           {"exposure_ms": 10.0})
    >>> f
    <Frame frame 4 x 4 float32, 0.00 % flagged>
    >>> f.data.dtype, f.meta["exposure_ms"]
    (dtype('float32'), 10.0)
    """

    data: np.ndarray
    dq: np.ndarray
    meta: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    alpha: np.ndarray | None = None
    dark_removed: np.ndarray | None = None
    corrected_by: str | None = None
    raw_response: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        data = np.asarray(self.data)
        if data.dtype.kind not in "biuf":
            raise ValueError(f"data must hold real numbers, got dtype {data.dtype}")
        if data.dtype != np.float32:
            data = data.astype(np.float32)
        dq = as_dq(self.dq)
        if dq.shape != data.shape:
            raise ValueError(f"dq has shape {dq.shape} but data has {data.shape}; they must match")
        if data.ndim not in (2, 3):
            raise ValueError(f"a frame is (H, W) or a cube (H, W, bands); got shape {data.shape}")
        if self.dark_removed is not None and data.ndim == 2:
            dark = np.asarray(self.dark_removed, np.float32)
            if dark.shape != data.shape:
                raise ValueError(f"dark_removed has shape {dark.shape} but data has "
                                 f"{data.shape}; they must match")
            object.__setattr__(self, "dark_removed", dark)
        if self.raw_response is not None and np.shape(self.raw_response) != data.shape:
            raise ValueError(f"raw_response has shape {np.shape(self.raw_response)} but data "
                             f"has {data.shape}; they must match")
        meta = dict(self.meta)
        _check_acquisition(meta)
        meta.setdefault("history", ())
        meta["history"] = tuple(meta["history"])
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "dq", dq)
        object.__setattr__(self, "meta", MappingProxyType(meta))

    def __repr__(self) -> str:  # key figures, never the arrays
        shape = " x ".join(str(s) for s in self.data.shape)
        what = "cube" if self.is_cube else "frame"
        parts = [f"{what} {shape} {self.data.dtype}"]
        try:
            parts.append(f"{self.exposure_ms:g} ms, {self.bit_depth}-bit, {self.kind}")
        except (KeyError, TypeError, ValueError):
            pass
        if self.mosaic is not None:
            parts.append(f"mosaic {self.mosaic.describe()}")
        flagged = np.count_nonzero(self.dq) / max(1, self.dq.size)
        parts.append(f"{100 * flagged:.2f} % flagged")
        done = [name for name, there in (("dark removed", self.dark_removed is not None),
                                         ("alpha", self.alpha is not None)) if there]
        if self.corrected_by:
            done.append(f"corrected by {self.corrected_by}")
        steps = [str(h.get("step", h.get("stage", "?"))) for h in self.history
                 if isinstance(h, dict)]
        if steps:
            done.append(f"after {', '.join(steps)}")
        return f"<Frame {', '.join(parts + done)}>"

    # -- construction --------------------------------------------------------------------------
    @classmethod
    def from_raw(cls, raw, *, exposure_ms: float, bit_depth: int, mosaic: Mosaic | None = None,
                 kind: str = "light", **meta) -> "Frame":
        """Wrap raw counts: float32 data, SATURATED where at full scale, NONFINITE where NaN/inf
        (those pixels are set to 0 DN and flagged, so nothing downstream turns into NaN).

        Parameters
        ----------
        raw : (H, W) array_like, DN
            Raw counts as read (integers or floats; never rescaled).
        exposure_ms : float
            Exposure time in milliseconds.
        bit_depth : int
            ADC bit depth; full scale is ``2**bit_depth - 1`` DN.
        mosaic : Mosaic, optional
            Band layout (needed by per-band stages and reconstruction).
        kind : "light" or "dark"
        **meta
            Anything else to keep in ``meta`` (illumination, step, source, ...).

        Returns
        -------
        Frame

        Examples
        --------
        >>> f = Frame.from_raw(np.array([[10, 1023], [0, 512]], np.uint16), exposure_ms=16.125,
        ...                    bit_depth=10)
        >>> f.data.dtype.name, f.exposure_ms, bool(f.dq[0, 1] & DQ.SATURATED)
        ('float32', 16.125, True)
        """
        _check_acquisition({"exposure_ms": exposure_ms, "bit_depth": bit_depth})
        raw = np.asarray(raw)
        if raw.dtype.kind not in "biuf":
            raise ValueError(f"raw must hold real counts (DN), got dtype {raw.dtype}")
        data = raw.astype(np.float32)
        bad = None
        if raw.dtype.kind not in "biu":  # integer counts are finite: no test needed
            finite = np.isfinite(data)
            if not finite.all():
                bad = ~finite
                data = np.where(finite, data, 0.0).astype(np.float32)
        # one pass for SATURATED: the comparison's bytes times the bit, as uint32
        dq = np.multiply(data >= 2 ** int(bit_depth) - 1, DQ_DTYPE(DQ.SATURATED), dtype=DQ_DTYPE)
        if bad is not None:
            dq[bad] |= DQ_DTYPE(DQ.NONFINITE | DQ.DO_NOT_USE)
        return cls(data, dq, {"exposure_ms": float(exposure_ms), "bit_depth": int(bit_depth),
                              "mosaic": mosaic, "kind": kind, **meta})

    @classmethod
    def list_from_sweep(cls, sweep: Sweep) -> list["Frame"]:
        """Every frame of a sweep as a Frame (acquisition order kept).

        Parameters
        ----------
        sweep : Sweep
            Frames ``(N, H, W)`` with their per-frame metadata.

        Returns
        -------
        list of Frame
            N frames, each with exposure, bit depth, mosaic, kind, illumination, step, source.
        """
        return [cls.from_raw(sweep.data[i], exposure_ms=float(sweep.exposure_ms[i]),
                             bit_depth=sweep.bit_depth, mosaic=sweep.mosaic,
                             kind=str(sweep.kind[i]), illumination=str(sweep.illumination[i]),
                             step=int(sweep.step[i]), source=sweep.source)
                for i in range(sweep.n_frames)]

    # -- views ---------------------------------------------------------------------------------
    def replace(self, **changes) -> "Frame":
        """A new frame with some fields replaced; ``meta`` entries given as ``meta={...}`` are
        merged into the existing metadata."""
        if "meta" in changes:
            merged = dict(self.meta)
            merged.update(changes["meta"])
            changes["meta"] = merged
        if {"data", "dark_removed"} & changes.keys():  # another response: not the kept one
            changes.setdefault("raw_response", None)
        return replace(self, **changes)

    def dark_subtracted(self, dark, *, signal=None, **meta) -> "Frame":
        """This frame less ``dark`` (DN, :func:`hsiffc.data.dark.subtract_dark`: float32, nothing
        clipped), with ``dark_removed`` set and ``meta`` merged. Its :attr:`raw` is this
        frame's data itself: exact (no ``(raw - dark) + dark`` rounding) and not recomputed.
        ``signal`` is that difference when a fused pass already computed it
        (:func:`hsiffc.leakage.validity.subtract_dark_and_flag`). Raises ValueError when a dark was
        removed already."""
        if self.dark_removed is not None:
            raise ValueError("this frame is already dark-subtracted; a pipeline should have one "
                             "dark stage")
        data = subtract_dark(self.data, dark) if signal is None else signal
        raw = None
        if not self.is_cube and self.corrected_by is None:
            raw = self.data.view()
            raw.flags.writeable = False
        return self.replace(data=data, dark_removed=dark, meta=meta, raw_response=raw)

    @property
    def exposure_ms(self) -> float:
        """Exposure time (ms)."""
        return float(self.meta["exposure_ms"])

    @property
    def bit_depth(self) -> int:
        """ADC bit depth (full scale ``2**bit_depth - 1`` DN)."""
        return int(self.meta["bit_depth"])

    @property
    def mosaic(self) -> Mosaic | None:
        """The band layout, or None."""
        return self.meta.get("mosaic")

    @property
    def kind(self) -> str:
        """``"light"`` or ``"dark"``."""
        return str(self.meta.get("kind", "light"))

    @property
    def history(self) -> tuple:
        """One dict per stage the frame passed (step, stage, parameters, status)."""
        return self.meta["history"]

    @property
    def is_cube(self) -> bool:
        """True for a reconstructed cube ``(H, W, bands)``."""
        return self.data.ndim == 3

    def band_map(self) -> np.ndarray:
        """Band index per pixel of a mosaic frame (all zeros without a mosaic), read-only."""
        if self.mosaic is None:
            return single_band_map(self.data.shape[:2])
        return self.mosaic.band_map(self.data.shape[:2])

    def band_labels(self) -> list[str]:
        """Each band's label, by band index (:func:`hsiffc.data.mosaic.band_labels`:
        ``"band 3 (r0c2 550 nm)"``, numbered from 1 by wavelength): a mosaic's bands, a cube's
        channels (their wavelengths and positions as the reconstruct stage recorded them)."""
        if self.is_cube:
            meta = self.meta
            return band_labels(self.data.shape[2], meta.get("wavelengths_nm"),
                               meta.get("band_positions"),
                               virtual=bool((meta.get("reconstruction") or {}).get("correction")))
        return mosaic_band_labels(self.mosaic)

    @property
    def good(self) -> np.ndarray:
        """True where no DQ bit is set."""
        return self.dq == 0

    # -- what has been done to the data --------------------------------------------------------
    @property
    def signal(self) -> np.ndarray:
        """DN above the dark: ``data`` once a dark has been removed (float32, (H, W)).

        Raises ValueError when no dark has been removed (put a dark stage first)."""
        if self.dark_removed is None:
            raise ValueError("no dark has been removed from this frame: its data are the raw "
                             "response; put a dark stage first")
        return self.data

    @property
    def raw(self) -> np.ndarray:
        """The sensor's raw response (DN, float32): ``data`` plus the dark that was actually
        removed (:attr:`raw_response` where the dark stage kept it, else computed on each
        call, read-only). Raises ValueError for a cube or once a stage changed the data
        otherwise (``corrected_by``)."""
        if self.corrected_by is not None:
            raise ValueError(f"the data were changed by {self.corrected_by!r}: the raw response "
                             "is no longer available; run stages that need it before it")
        if self.is_cube:
            raise ValueError("a cube has no raw mosaic response; run this stage before "
                             "reconstruction")
        if self.dark_removed is None:
            return self.data
        if self.raw_response is not None:
            return self.raw_response
        raw = self.data + self.dark_removed
        raw.flags.writeable = False
        return raw

    def to_xarray(self, *, sort: bool = True):
        """This reconstructed cube as an ``xarray.Dataset``: dims (y, x, band), coordinate
        ``wavelength`` (ascending when ``sort``), variables ``data``, ``dq`` (with the DQ bit
        table) and ``alpha``; history in the attributes (:func:`hsiffc.cubes.to_xarray`;
        needs xarray: ``pip install 'hsiffc[xarray]'``). Raises ValueError for a mosaic
        frame."""
        from ..cubes import to_xarray

        return to_xarray(self, sort=sort)

    def state(self) -> frozenset[str]:
        """What this frame offers the next stage, in the words stages declare (see
        :data:`STATES`)."""
        out = {"cube" if self.is_cube else "mosaic",
               "raw" if self.dark_removed is None else "dark_subtracted"}
        if self.corrected_by is None:
            out.add("response")
        if self.alpha is not None:
            out.add("alpha")
        return frozenset(out)


def stack_mean(frames, *, robust: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Average of a stack of frames: the median when ``robust`` (outliers such as cosmic rays or
    a glitched frame do not move it), else the mean.

    Parameters
    ----------
    frames : sequence of Frame
        Frames of one shape ``(H, W)``.
    robust : bool
        Median (with 3 or more frames) instead of the mean.

    Returns
    -------
    data : (H, W) float32, DN
    dq : (H, W) uint32
        OR of the frames' DQ.

    Examples
    --------
    >>> fs = [Frame.from_raw(np.full((1, 2), v), exposure_ms=1, bit_depth=10) for v in (1, 2, 9)]
    >>> stack_mean(fs)[0].tolist(), stack_mean(fs, robust=False)[0].tolist()
    ([[2.0, 2.0]], [[4.0, 4.0]])
    """
    data = np.stack([f.data for f in frames])
    dq = np.bitwise_or.reduce(np.stack([f.dq for f in frames]), axis=0)
    avg = np.median(data, axis=0) if (robust and len(frames) >= 3) else data.mean(axis=0)
    return avg.astype(np.float32), dq
