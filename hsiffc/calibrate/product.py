"""The calibration product: per-pixel leakage-model parameters in one versioned file.

The file is an ``.npz`` holding the per-pixel arrays and a JSON manifest (``manifest.json``
stored as a uint8 array): format name and version, hsiffc version, method, the validity domain
(exposure range, light-rate range and unit, bit depth, sensor size, mosaic) and what it was
fitted on. It loads with ``allow_pickle=False``: no code is ever executed from a calibration file.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..data.dark import dark_at
from ..errors import (CalibrationDomainWarning, CalibrationMismatchError, DataFormatError,
                      MissingMosaicWarning, ParameterError)
from ..data.mosaic import (Mosaic, band_labels, mosaic_band_labels,
                           wavelength_order)
from ..data.products import read_product, write_product

FORMAT = "hsiffc-calibration"
FORMAT_VERSION = 1
REQUIRED = ("a_dn_per_ms", "b_per_dn", "dark_dn")


@dataclass(frozen=True, eq=False)
class Calibration:
    """Per-pixel leakage-model calibration of one sensor.

    Attributes
    ----------
    arrays : dict of (H, W) arrays
        Always ``a_dn_per_ms``, ``b_per_dn``, ``dark_dn``; usually also ``responsivity``
        (DN/ms per unit of relative light rate: k = responsivity * rate), ``k_ref_dn_per_ms``
        (k under the calibration light), ``dark_current_dn_per_ms``, ``saturation_ref_dn``,
        ``sigma_ln_g``, ``sigma_ln_a``, ``sigma_ln_b``, ``sigma_dark_dn``, ``rms_dn``,
        ``n_valid``, ``n_clipped``, ``n_full_well`` and ``flags`` (uint32 DQ bits).
    domain : dict
        Validity domain: ``exposure_ms`` [min, max], ``light_rate`` [min, max] and
        ``light_rate_unit``, ``bit_depth``, ``frame_shape`` [H, W], ``mosaic`` (dict or None),
        ``full_scale_dn``.
    method : str
        ``"joint"`` or ``"paper"``.
    fitted_on : dict
        Source, frame and step counts, illuminations, noise model.
    path : str or None
        Provenance, not content: the file it was loaded from or last saved to (:meth:`load`,
        :meth:`save`; the one field :meth:`save` changes), None for a calibration that exists
        only in memory. Not part of :attr:`identity`.
    mosaic : Mosaic or None
        The band layout of ``domain["mosaic"]``, built when the calibration is made.
    identity : str
        Short content hash of the arrays (sha256, 16 hex digits), computed when the
        calibration is made: which calibration produced a result (provenance). The arrays
        are not to be changed afterwards (a changed calibration is a new one: make it with
        ``dataclasses.replace``).

    The calibration is plain data: what correcting a frame reads from it (float32 planes, the
    flag plane, the dark line) is made once by :meth:`prepare` and held by whoever corrects
    (a pipeline holds it in its plan).
    """

    arrays: dict
    domain: dict
    method: str
    fitted_on: dict = field(default_factory=dict)
    created: str = ""
    hsiffc_version: str = __version__
    path: str | None = field(default=None, compare=False)
    mosaic: Mosaic | None = field(init=False, repr=False, compare=False)
    identity: str = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        missing = [k for k in REQUIRED if k not in self.arrays]
        if missing:
            raise ValueError(f"a calibration needs the arrays {REQUIRED}; missing {missing}")
        shape = tuple(self.domain.get("frame_shape", ()))
        for name, arr in self.arrays.items():
            if np.shape(arr) != shape:
                raise ValueError(f"array {name!r} has shape {np.shape(arr)}, the domain says "
                                 f"frame_shape {shape}")
        self._flag_outside_model()
        m = self.domain.get("mosaic")
        object.__setattr__(self, "mosaic", Mosaic.from_dict(m) if m else None)
        object.__setattr__(self, "identity", _identity(self.arrays))
        if not self.created:
            object.__setattr__(self, "created",
                               _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))

    def _flag_outside_model(self) -> None:
        """Pixels whose leakage exponent b is finite but not positive are outside the model
        (the leakage grows with the signal): one such pixel would fail every frame it is
        applied to. They get b = NaN and DO_NOT_USE, as a pixel with a NaN parameter is
        flagged, and a :class:`~hsiffc.errors.CalibrationDomainWarning` says how many."""
        b = np.asarray(self.arrays["b_per_dn"])
        with np.errstate(invalid="ignore"):
            bad = np.isfinite(b) & (b <= 0)
        if not bad.any():
            return
        from ..data.dq import DQ

        arrays = dict(self.arrays)
        arrays["b_per_dn"] = np.where(bad, np.nan, b).astype(b.dtype)
        flags = np.asarray(arrays.get("flags", np.zeros(b.shape, np.uint32)), np.uint32)
        arrays["flags"] = flags | np.where(bad, np.uint32(DQ.DO_NOT_USE), np.uint32(0))
        object.__setattr__(self, "arrays", arrays)
        where = f" ({self.path})" if self.path else ""
        warnings.warn(CalibrationDomainWarning(
            f"calibration{where}: {int(bad.sum())} pixel(s) have leakage b <= 0 (1/DN), "
            "outside the model; they are flagged DO_NOT_USE (b set to NaN) and every other "
            "pixel is corrected; recalibrate to fit them", figures={"pixels": int(bad.sum())}),
            stacklevel=3)

    def __repr__(self) -> str:  # key figures, never the arrays (a REPL echo stays short)
        h, w = self.frame_shape
        lo, hi = self.domain.get("exposure_ms", (float("nan"), float("nan")))
        mos = self.mosaic
        layout = "no mosaic" if mos is None else f"mosaic {mos.describe()}, {mos.n_bands} bands"
        where = f", file {self.path!r}" if self.path else ", in memory"
        return (f"<Calibration {self.method}: {h} x {w} px, {self.bit_depth}-bit, {layout}, "
                f"exposures {lo:g}-{hi:g} ms, {len(self.arrays)} arrays, identity "
                f"{self.identity}{where}>")

    # -- convenient views ----------------------------------------------------------------------
    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    @property
    def a(self) -> np.ndarray:
        """Leakage amplitude a per pixel, (H, W), DN/ms."""
        return self.arrays["a_dn_per_ms"]

    @property
    def b(self) -> np.ndarray:
        """Leakage exponent b per pixel, (H, W), 1/DN."""
        return self.arrays["b_per_dn"]

    @property
    def dark(self) -> np.ndarray:
        """Dark level at zero exposure per pixel, (H, W), DN."""
        return self.arrays["dark_dn"]

    @property
    def flags(self) -> np.ndarray | None:
        """Per-pixel DQ flags (uint32, (H, W)) the fit set, or None."""
        return self.arrays.get("flags")

    @property
    def dark_current(self) -> np.ndarray:
        """Dark current per pixel, (H, W), DN/ms."""
        return self.arrays.get("dark_current_dn_per_ms", np.zeros(self.frame_shape))

    def prepare(self):
        """What correcting a frame reads from this calibration, made now: float32 leakage
        planes, the flag plane and the dark line (:class:`~hsiffc.calibrate.prepared.PreparedCalibration`).

        Returns
        -------
        PreparedCalibration
            Read-only planes; make it once and keep it where frames are corrected.
        """
        from .prepared import PreparedCalibration

        return PreparedCalibration.of(self)

    def dark_at(self, exposure_ms: float) -> np.ndarray:
        """The calibrated dark (DN, float32, (H, W)) at one exposure: dark level plus dark
        current times the exposure (ms).

        Parameters
        ----------
        exposure_ms : float, ms
            Exposure of the frame to correct.

        Returns
        -------
        ndarray of float32, DN
            (H, W), computed on each call (a prepared calibration keeps the darks of the last
            few exposures: :meth:`prepare`).
        """
        return dark_at(float(exposure_ms), self.dark, self.dark_current)

    @property
    def frame_shape(self) -> tuple[int, int]:
        """(H, W) of the frames it was fitted on."""
        return tuple(int(s) for s in self.domain["frame_shape"])

    @property
    def bit_depth(self) -> int:
        """ADC bit depth of the frames it was fitted on."""
        return int(self.domain["bit_depth"])

    def reference(self) -> dict:
        """How pipelines and histories name this calibration.

        Returns
        -------
        dict
            ``{"identity": str, "path": str or None}`` (the path is None for a calibration
            that exists only in memory).
        """
        return {"identity": self.identity, "path": self.path}

    def __deepcopy__(self, memo):
        return self  # an immutable product: copies (e.g. Stage.clone) share it

    @classmethod
    def resolve(cls, value) -> "Calibration | None":
        """A Calibration from an object, a path (read now) or None.

        Parameters
        ----------
        value : Calibration, str, Path or None
            What a stage or pipeline was given as ``calibration``.

        Returns
        -------
        Calibration or None
            ``value`` itself, the file read with :meth:`load`, or None.

        Raises
        ------
        ParameterError
            ``value`` is of another type.
        """
        if value is None or isinstance(value, cls):
            return value
        if not isinstance(value, (str, Path)):
            raise ParameterError(f"calibration={value!r} is not valid; expected a Calibration "
                                 "or the path of a calibration file (.npz)")
        return cls.load(value)

    def manifest(self) -> dict:
        """The JSON manifest saved with the arrays.

        Returns
        -------
        dict
            Format and versions, creation time, method, validity domain, training data,
            dtype and shape of every array, identity.
        """
        return {"format": FORMAT, "format_version": FORMAT_VERSION,
                "hsiffc_version": self.hsiffc_version, "created": self.created,
                "method": self.method, "domain": self.domain, "fitted_on": self.fitted_on,
                "arrays": {k: {"dtype": str(v.dtype), "shape": list(v.shape)}
                           for k, v in self.arrays.items()},
                "identity": self.identity}

    def summary(self) -> str:
        """Percentiles of each parameter, sample counts and flagged pixels, as text.

        Returns
        -------
        str
            What ``hsiffc calibrate`` prints (several lines).
        """
        d = self.domain
        h, w = self.frame_shape
        lines = [f"hsiffc calibration ({self.method}) of a {w} x {h} px, {d['bit_depth']}-bit "
                 f"sensor, fitted on {self.fitted_on.get('source', '?')}",
                 f"  exposure {d['exposure_ms'][0]:.4g}-{d['exposure_ms'][1]:.4g} ms, light rate "
                 f"{d['light_rate'][0]:.4g}-{d['light_rate'][1]:.4g} {d['light_rate_unit']}"]
        for name, unit in (("dark_dn", "DN"), ("b_per_dn", "1/DN"), ("a_dn_per_ms", "DN/ms"),
                           ("k_ref_dn_per_ms", "DN/ms"), ("saturation_ref_dn", "DN"),
                           ("rms_dn", "DN")):
            if name in self.arrays:
                v = np.asarray(self.arrays[name], float)
                v = v[np.isfinite(v)]
                if v.size:
                    q = np.percentile(v, [5, 50, 95])
                    lines.append(f"  {name:<20} median {q[1]:.4g} {unit} (5-95 %: {q[0]:.4g} to "
                                 f"{q[2]:.4g})")
        if "flags" in self.arrays:
            from ..data.dq import DQ

            f = self.arrays["flags"]
            for bit in (DQ.NOT_CONVERGED, DQ.LEAK_UNCONSTRAINED, DQ.DO_NOT_USE):
                n = int(((f & int(bit)) != 0).sum())
                lines.append(f"  pixels flagged {bit.name:<19} {n} ({100 * n / f.size:.2f} %)")
        n_px = int(np.prod(self.frame_shape))
        for reason, n in self.fitted_on.get("fit_status", {}).items():
            lines.append(f"  {n} px ({100 * n / n_px:.2f} %): {reason}")
        dark = self.fitted_on.get("dark_model")
        if dark:
            lines.append(f"  dark model: {dark.get('description', dark.get('model'))}"
                         + (f", dark level from {dark['dark_from']}" if "dark_from" in dark
                            else ""))
        t0 = self.fitted_on.get("exposure_offset_ms")
        if t0:
            lines.append(f"  exposure offset: light collected for t {'+' if t0 > 0 else '-'} "
                         f"{abs(t0):.4g} ms")
        lines += _choice_lines(self.fitted_on.get("model_choice"), self.mosaic)
        return "\n".join(lines)

    # -- validation ----------------------------------------------------------------------------
    def check_compatible(self, data=None, *, frame_shape=None, bit_depth=None, mosaic=None,
                         what: str = "the data") -> None:
        """Raise :class:`CalibrationMismatchError` if ``data`` (a Sweep, or the keyword facts)
        does not fit this calibration: other frame shape, bit depth or mosaic.

        Parameters
        ----------
        data : Sweep or Frame, optional
            Data whose ``frame_shape``, ``bit_depth`` and ``mosaic`` are checked.
        frame_shape : (int, int), optional
            (H, W) to check when no ``data`` is given.
        bit_depth : int, optional
            ADC bit depth to check.
        mosaic : Mosaic, optional
            Filter mosaic to check.
        what : str
            How the message names the data (default: its source).

        Raises
        ------
        CalibrationMismatchError
            Naming every mismatch and the calibration's values.
        """
        if data is not None:
            frame_shape = getattr(data, "frame_shape", frame_shape)
            bit_depth = getattr(data, "bit_depth", bit_depth)
            mosaic = getattr(data, "mosaic", mosaic)
            what = getattr(data, "source", "") or what
        problems = []
        if frame_shape is not None and tuple(frame_shape) != self.frame_shape:
            problems.append(f"frame shape {tuple(frame_shape)} but the calibration is for "
                            f"{self.frame_shape}")
        if bit_depth is not None and int(bit_depth) != self.bit_depth:
            problems.append(f"bit depth {bit_depth} but the calibration is for {self.bit_depth}")
        mine = self.mosaic
        if mosaic is not None and mine is not None and mosaic != mine:
            problems.append(f"mosaic {mosaic.describe()} differs from the calibration's "
                            f"{mine.describe()}" + (" (same tile size: other band order, "
                                                     "wavelengths or offset)"
                                                     if mosaic.tile_shape == mine.tile_shape
                                                     else ""))
        if problems:
            raise CalibrationMismatchError(
                f"{what} does not fit calibration {self.identity} "
                f"(fitted on {self.fitted_on.get('source', '?')}): " + "; ".join(problems)
                + ". Calibrate this sensor configuration (hsiffc calibrate) or use its calibration.")

    def check_frame(self, frame, what: str = "the frame") -> None:
        """Check one frame against this calibration: what every stage that applies it asks.

        Raises :class:`CalibrationMismatchError` as :meth:`check_compatible` does (frame
        shape, bit depth, mosaic), and warns when the
        frame gives no mosaic layout but the calibration has one
        (:class:`hsiffc.errors.MissingMosaicWarning`): the correction still runs
        pixel by pixel, but every per-band figure treats the frame as one band.

        Parameters
        ----------
        frame : Frame
            A 2-D frame (``data`` (H, W), ``bit_depth``, ``mosaic``).
        what : str
            How the messages name the frame.

        Examples
        --------
        >>> import warnings
        >>> import numpy as np
        >>> from hsiffc.data.frame import Frame
        >>> from hsiffc.calibrate import calibrate
        >>> from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
        >>> sweep = MosaicSensor((8, 8), seed=0).sweep(
        ...     np.geomspace(2.0, 400.0, 12), "lamp A", n_frames=2, seed=1,
        ...     irradiance_w_m2=PAPER_LIGHT_W_M2["training"] / 4)
        >>> cal = calibrate(sweep)
        >>> raw = np.full((8, 8), 100, np.uint16)
        >>> cal.check_frame(Frame.from_raw(raw, exposure_ms=10, bit_depth=cal.bit_depth,
        ...                                mosaic=cal.mosaic))      # fits: nothing happens
        >>> with warnings.catch_warnings(record=True) as seen:
        ...     warnings.simplefilter("always")
        ...     cal.check_frame(Frame.from_raw(raw, exposure_ms=10, bit_depth=cal.bit_depth))
        >>> "no mosaic layout" in str(seen[0].message)
        True
        """
        self.check_compatible(frame_shape=frame.data.shape, bit_depth=frame.bit_depth,
                              mosaic=frame.mosaic, what=what)
        if frame.mosaic is None and self.mosaic is not None:
            warnings.warn(
                f"{what} gives no mosaic layout but calibration {self.identity} is for "
                f"{self.mosaic.describe()}, {self.mosaic.n_bands} bands: corrected pixel by "
                "pixel, every per-band figure treats it as one band; give the frame its layout "
                "(Frame(..., mosaic=cal.mosaic) or frame.replace(mosaic=cal.mosaic))",
                MissingMosaicWarning, stacklevel=3)

    def in_domain(self, exposure_ms) -> np.ndarray:
        """True where an exposure lies inside the calibrated exposure range.

        Parameters
        ----------
        exposure_ms : array_like, ms
            Exposures to test.

        Returns
        -------
        ndarray of bool
            Shape of ``exposure_ms``.
        """
        lo, hi = self.domain["exposure_ms"]
        e = np.asarray(exposure_ms, float)
        return (e >= lo) & (e <= hi)

    # -- file I/O ------------------------------------------------------------------------------
    def save(self, path, *, overwrite: bool = False) -> Path:
        """Write the calibration to ``path`` (.npz) atomically (:mod:`hsiffc.data.products`).

        Parameters
        ----------
        path : str or Path
            Output file (``.npz``).
        overwrite : bool
            Replace an existing file (default: refuse).

        Returns
        -------
        Path
            The file written; the calibration's :attr:`path` now points to it.

        Raises
        ------
        OutputExistsError
            ``path`` exists and ``overwrite`` is False.
        """
        man = {k: v for k, v in self.manifest().items()
               if k not in ("format", "format_version")}
        path = write_product(path, format=FORMAT, format_version=FORMAT_VERSION, manifest=man,
                             arrays=self.arrays, overwrite=overwrite)
        object.__setattr__(self, "path", str(Path(path).resolve()))  # provenance (see above)
        return path

    @classmethod
    def load(cls, path) -> "Calibration":
        """Read a calibration file (never unpickles anything).

        Parameters
        ----------
        path : str or Path
            A file written by :meth:`save` or ``hsiffc calibrate``.

        Returns
        -------
        Calibration

        Raises
        ------
        DataFormatError
            Not a calibration file, another format version, or incomplete arrays.
        """
        man, arrays = read_product(path, format=FORMAT, format_version=FORMAT_VERSION,
                                   remedy="create one with 'hsiffc calibrate SWEEP -o CALIB.npz'")
        try:
            cal = cls(arrays=arrays, domain=man["domain"], method=man["method"],
                      fitted_on=man.get("fitted_on", {}), created=man.get("created", ""),
                      hsiffc_version=man.get("hsiffc_version", "?"),
                      path=str(Path(path).resolve()))
        except (KeyError, ValueError, TypeError) as exc:
            raise DataFormatError(f"calibration is incomplete or inconsistent: {exc}",
                                  path=path) from exc
        return cal


def _identity(arrays: dict) -> str:
    """:attr:`Calibration.identity` of ``arrays``: sha256 over the sorted names and bytes."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        h.update(name.encode())
        h.update(np.ascontiguousarray(arrays[name]).tobytes())
    return h.hexdigest()[:16]


def _choice_lines(choice, mosaic=None) -> list:
    """The summary's lines on the model the sensor kept and each band's held-out figures
    (:mod:`hsiffc.calibrate.choice`), bands by wavelength with their labels (``mosaic``'s)."""
    if not choice:
        return []
    if not choice.get("bands"):
        return [f"  model: leakage where the sweep determines it ({choice.get('reason', '')})"]

    def figures(row):
        errs = ", ".join(f"{name} {value:.3f}" for name, value in
                         row["held_out_fpn_percent"].items())
        pred = row.get("predicted_fpn_percent", float("nan"))
        ratio = row.get("held_out_over_predicted", float("nan"))
        return (errs + (f"; its own errors predict {pred:.3f}" if pred == pred else "")
                + (f"; held-out / predicted {ratio:.2f} per step (median)"
                   if ratio == ratio else ""))

    n = len(choice["held_out_steps"])
    lines = []
    if "kept" in choice:
        lines.append(f"  model kept: {choice['kept']}, by held-out prediction on {n} light "
                     f"steps the fit did not see (fixed-pattern non-uniformity, %: "
                     f"{figures(choice)})")
    lines.append(f"  model kept per band, by held-out fixed-pattern non-uniformity (% on {n} "
                 "light steps the fit did not see):")
    rows = {row["band"]: row for row in choice["bands"]}
    nb = 1 + max(rows)
    if mosaic is not None and mosaic.n_bands == nb:  # by wavelength, named as everywhere
        names, order = mosaic_band_labels(mosaic), wavelength_order(nb, mosaic.wavelengths_nm)
    else:
        names, order = band_labels(nb), range(nb)
    lines += [f"    {names[b]}: {rows[b]['kept']} ({figures(rows[b])})" for b in order if b in rows]
    return lines
