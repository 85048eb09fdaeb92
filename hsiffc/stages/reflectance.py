"""Reflectance stage: scenes divided by a white reference panel (wraps :mod:`hsiffc.reflectance`).

Fitted on white-reference frames (kind "light"; darks are for the ``dark`` step before it) with
the panel's reflectance factor; applied to scenes, it returns the reflectance factor per band
with DQ. With a calibration (``method="auto"`` or ``"model"``) both are light rates recovered
through the leakage model, so a bright panel and a dark scene are compared in units linear in
the light; without one (``"ratio"``), DN above dark per ms. Works on mosaic frames and on
cubes: ``"ratio"`` after reconstruction (and after the IMEC correction matrix) divides band by
band; ``"model"`` inverts the model per pixel, so it comes before reconstruction (or put a
``linearise`` step before reconstruction and use ``"ratio"`` after it).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..data.dq import DQ, DQ_DTYPE
from ..data.mosaic import wavelength_order
from ..errors import CalibrationMismatchError, ParameterError, WarnedOnce
from ..files.jsonsafe import json_safe
from ..data.params import Param
from ..reflectance import (REFLECTANCE_METHODS, ExposureMismatchWarning, GainMismatchWarning,
                           SceneBrighterThanReferenceWarning, band_fraction, band_median,
                           panel_per_band, read_panel_spectrum, reference_warnings,
                           reflectance_factor, resolve_method, scene_brightness,
                           white_reference)
from .base import PreparedWithCalibration, Stage
from .common import AVERAGE, CALIBRATION, THRESHOLD

METHODS = tuple(REFLECTANCE_METHODS)  # the names (kept)
FRACTION = Param("number", low=0, low_open=True, high=1)
POSITIVE = Param("number", low=0, low_open=True)


def frame_bands(frame) -> tuple[np.ndarray, int, list | None]:
    """Band index of every value of ``frame``, the number of bands and their wavelengths (nm,
    band order; None when unknown): a mosaic's band map, or a cube's channel index."""
    if frame.is_cube:
        n = frame.data.shape[-1]
        wl = frame.meta.get("wavelengths_nm")
        return np.broadcast_to(np.arange(n), frame.data.shape), n, (
            None if wl is None else [float(w) for w in wl])
    mosaic = frame.mosaic
    if mosaic is None:
        return frame.band_map(), 1, None
    wl = None if mosaic.wavelengths_nm is None else [float(w) for w in mosaic.wavelengths_nm]
    return frame.band_map(), mosaic.n_bands, wl


class Reflectance(Stage):
    """Reflectance factor per band from a white reference panel (and the leakage model).

    ``R = R_panel * q_scene / q_white`` per pixel, q the scene's and the reference's rate
    (:mod:`hsiffc.reflectance`): the light rate k of the leakage model (``"model"``) or DN above
    dark per ms (``"ratio"``). A scene at another exposure than the reference is scaled by the
    exposure (an :class:`~hsiffc.reflectance.ExposureMismatchWarning` and the history say so);
    with several reference exposures the scene's own (else the nearest) is used.

    Checks (warnings with numbers, once per condition; see :mod:`hsiffc.reflectance._checks`):
    at fit, a reference too dark, saturated, in strong leakage, or with too few frames for
    ``precision_percent``; at transform, a scene brighter than the reference (more than
    ``max_bright_fraction`` of its good values above ``max_reflectance``) and an exposure or
    gain (``meta["gain"]``, when the frames carry one) different from the reference's.

    Fitted attributes: ``method_``, ``panel_`` (per band), ``panel_source_``,
    ``white_exposures_ms_``, ``white_rate_`` (references, one per exposure, DN/ms),
    ``dq_`` (their flags), ``white_gain_``, ``checks_`` (per reference: the figures of the
    checks and the warnings they gave).

    Output: ``data`` is the reflectance factor (float32, 1 = a perfect diffuse reflector),
    ``meta["units"] = "reflectance factor"``, ``meta["reflectance"]`` says how it was made.

    Parameters
    ----------
    panel : float or list of float, optional
        The panel's reflectance factor (e.g. 0.99), one value or one per band (band order).
    panel_file : path, optional
        The panel's spectrum (two columns: wavelength in nm, reflectance), interpolated at the
        bands' wavelengths; instead of ``panel``.
    calibration : path or Calibration, optional
        Leakage calibration; with it ``"auto"`` is ``"model"``.
    method : str
        One of :data:`hsiffc.reflectance.REFLECTANCE_METHODS` ("auto", "model", "ratio").
    average : "mean" or "median"
        How the reference frames are averaged.
    alpha_limit_percent : float
        ``"model"``: values whose model alpha exceeds this are flagged LEAKAGE.
    reference_alpha_percent : float
        Median model alpha of the reference over which it is "in strong leakage" (needs a
        calibration).
    min_reference_level : float
        Fraction of the sensor's range (full scale less dark) the reference should reach.
    min_reference_snr : float
        Single-frame signal-to-noise ratio the reference should reach.
    precision_percent : float
        Error of the averaged reference (percent per pixel) the reference frames should reach.
    max_saturated_percent : float
        Share of a band's reference pixels at full scale tolerated (percent).
    max_reflectance : float
        A scene value above it counts as brighter than the reference.
    max_bright_fraction : float
        Share of a scene's good values above ``max_reflectance`` that triggers the warning.

    """

    name = "reflectance"
    removes = frozenset({"response"})
    param_spec = {"panel_file": Param("path", optional=True), "calibration": CALIBRATION,
                  "method": Param("choice", choices=REFLECTANCE_METHODS), "average": AVERAGE,
                  "alpha_limit_percent": THRESHOLD, "reference_alpha_percent": THRESHOLD,
                  "min_reference_level": FRACTION, "min_reference_snr": POSITIVE,
                  "precision_percent": THRESHOLD, "max_saturated_percent": THRESHOLD,
                  "max_reflectance": POSITIVE, "max_bright_fraction": FRACTION}

    def __init__(self, *, panel=None, panel_file=None, calibration=None, method: str = "auto",
                 average: str = "mean", alpha_limit_percent: float = 50.0,
                 reference_alpha_percent: float = 12.0, min_reference_level: float = 0.1,
                 min_reference_snr: float = 20.0, precision_percent: float = 1.0,
                 max_saturated_percent: float = 0.1, max_reflectance: float = 1.2,
                 max_bright_fraction: float = 0.5):
        self.panel = panel
        self.panel_file = panel_file
        self.calibration = calibration
        self.method = method
        self.average = average
        self.alpha_limit_percent = alpha_limit_percent
        self.reference_alpha_percent = reference_alpha_percent
        self.min_reference_level = min_reference_level
        self.min_reference_snr = min_reference_snr
        self.precision_percent = precision_percent
        self.max_saturated_percent = max_saturated_percent
        self.max_reflectance = max_reflectance
        self.max_bright_fraction = max_bright_fraction

    # -- parameters ----------------------------------------------------------------------------
    def validate_params(self) -> None:
        super().validate_params()
        p = self.panel
        values = p if isinstance(p, (list, tuple)) else [p]
        if p is not None and (not values or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                or not 0 < v <= 1.5 for v in values)):
            raise ParameterError(f"reflectance: panel={p!r} is not valid; expected the panel's "
                                 "reflectance factor in (0, 1.5] (e.g. 0.99, not 99), one value "
                                 "or a list with one per band")
        if p is not None and self.panel_file is not None:
            raise ParameterError("reflectance: give panel= or panel_file=, not both")
        if REFLECTANCE_METHODS[self.method].leakage_aware and self.calibration is None:
            raise ParameterError("reflectance: method='model' needs calibration= (the leakage "
                                 "calibration from 'hsiffc calibrate'); or use method='ratio'")

    @property
    def method_used(self) -> str:
        """The method that runs: ``"model"`` or ``"ratio"`` (what ``"auto"`` resolves to,
        :func:`hsiffc.reflectance.resolve_method`)."""
        return resolve_method(self.method, self.calibration is not None)

    @property
    def requires(self):  # the model inverts the raw response of mosaic pixels
        return REFLECTANCE_METHODS[self.method_used].requires

    # -- rates ---------------------------------------------------------------------------------
    def _rate(self, frame, method: str, prepared=None):
        """(rate, dq, alpha or None, signal in DN above dark) of one frame (``prepared``: the
        calibration prepared, whose dark line gives the dark where no stage removed one)."""
        t = frame.exposure_ms
        if not t > 0:
            raise ParameterError(f"reflectance: a frame at exposure {t:g} ms integrates no "
                                 "light; give frames with an exposure > 0 ms")
        how = REFLECTANCE_METHODS[method]
        return how.rate(frame, self.require_calibration() if how.leakage_aware else None,
                        prepared=prepared, alpha_limit_percent=float(self.alpha_limit_percent))

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, frames):
        """Average the white-reference frames (kind "light") per exposure, check them and
        resolve the panel's value per band; returns ``self``."""
        self.validate_params()
        method = self.method_used
        whites = [f for f in frames if f.kind == "light"]
        if not whites:
            raise ParameterError("reflectance: no white-reference (light) frames among the "
                                 "training frames; give the panel's frames (hsiffc fit "
                                 "--white, kind light) and the darks (--dark)")
        if len({f.is_cube for f in whites}) > 1 or len({f.data.shape for f in whites}) > 1:
            raise ParameterError("reflectance: the white-reference frames differ in shape; give "
                                 "frames of one camera setting")
        bands, n_bands, wl = frame_bands(whites[0])
        if self.panel_file is not None:
            sw, sr, note = read_panel_spectrum(self.panel_file)
            panel = panel_per_band(None, n_bands=n_bands, wavelengths_nm=wl, spectrum=(sw, sr))
            source = f"{self.panel_file} ({note}, interpolated at the band centres)"
        else:
            panel = panel_per_band(self.panel, n_bands=n_bands, wavelengths_nm=wl)
            source = "panel parameter"
        groups: dict[float, list] = {}
        for f in whites:
            groups.setdefault(f.exposure_ms, []).append(f)
        darks: dict[float, list] = {}
        for f in frames:
            if f.kind == "dark" and f.data.shape == whites[0].data.shape:
                darks.setdefault(f.exposure_ms, []).append(f)
        rates, dqs, checks, gains = [], [], [], []
        for t, stack in sorted(groups.items()):
            ref, report = self._reference(stack, method, bands, n_bands, panel,
                                          darks.get(t, []))
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                texts = reference_warnings(
                    report, min_level_fraction=float(self.min_reference_level),
                    min_snr=float(self.min_reference_snr),
                    precision_percent=float(self.precision_percent),
                    max_saturated_percent=float(self.max_saturated_percent),
                    reference_alpha_percent=float(self.reference_alpha_percent), method=method)
            for w in caught:  # re-issued from here, so they point at the caller's fit
                warnings.warn(w.message, w.category, stacklevel=2)
            report["warnings"] = texts
            rates.append(ref.rate)
            dqs.append(ref.dq)
            checks.append(json_safe(report))
            gains.append(json_safe(stack[0].meta.get("gain")))
        self.method_ = method
        self.panel_ = [float(v) for v in panel]
        self.panel_source_ = source
        self.white_exposures_ms_ = [float(t) for t in sorted(groups)]
        self.white_rate_ = np.stack(rates)
        self.dq_ = np.stack(dqs)
        self.white_gain_ = gains
        self.checks_ = checks
        self.fitted_ = True
        return self

    def _reference(self, stack, method, bands, n_bands, panel, darks=()):
        """One exposure's reference and the figures of its checks (``darks``: dark frames at
        its exposure, for the temporal noise without light)."""
        per = [self._rate(f, method) for f in stack]
        dqs = [f.dq if d is None else f.dq | d for f, (_, d, _, _) in zip(stack, per)]
        ref = white_reference([p[0] for p in per], dqs, bands, n_bands,
                              average=self.average)
        signal = np.mean([p[3] for p in per], axis=0)
        f0 = stack[0]
        full = 2.0 ** f0.bit_depth - 1
        dark = f0.dark_removed
        if dark is None and REFLECTANCE_METHODS[method].leakage_aware:
            dark = self.require_calibration().dark_at(f0.exposure_ms)
        dark_level = float(np.median(dark)) if dark is not None else 0.0
        level = band_median(signal, bands, n_bands)
        # virtual bands (a correction matrix) are not in the sensor's DN: no level check
        mixed = bool(f0.is_cube and (f0.meta.get("reconstruction") or {}).get("correction"))
        snr = [None] * n_bands
        if ref.sigma is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                snr = band_median(ref.rate / ref.sigma, bands, n_bands).tolist()
        saturated = np.bitwise_or.reduce([f.dq for f in stack], axis=0) & DQ.SATURATED
        report = {"exposure_ms": f0.exposure_ms, "n_frames": len(stack), "method": method,
                  "panel": [float(v) for v in panel], "level_dn": level.tolist(),
                  "range_dn": [None if mixed else full - dark_level] * n_bands,
                  "snr_frame": snr,
                  "saturated_percent": (100 * band_fraction(saturated != 0, bands,
                                                            n_bands)).tolist(),
                  "alpha_percent": None, "loss_percent": None,
                  "temporal_var_dn2": None, "dark_var_dn2": None,
                  "band_labels": f0.band_labels(),
                  "band_order": wavelength_order(n_bands, frame_bands(f0)[2])}
        if len(stack) >= 2 and len(darks) >= 2:  # no shot noise left: the response stopped
            report["temporal_var_dn2"] = band_median(
                np.var([f.data for f in stack], axis=0, ddof=1), bands, n_bands).tolist()
            report["dark_var_dn2"] = band_median(
                np.var([f.data for f in darks], axis=0, ddof=1), bands, n_bands).tolist()
        cal = self.calibration_product()
        if cal is not None and not f0.is_cube and f0.corrected_by is None:
            if REFLECTANCE_METHODS[method].leakage_aware:
                alpha = np.mean([p[2] for p in per], axis=0)
                k = ref.rate
            else:  # the ratio method with a calibration at hand: say what leakage costs it
                k_per = [self._rate(f, "model") for f in stack]
                alpha = np.mean([p[2] for p in k_per], axis=0)
                k = np.mean([p[0] for p in k_per], axis=0)
            with np.errstate(divide="ignore", invalid="ignore"):
                loss = 100 * (1 - signal / (k * f0.exposure_ms))
            report["alpha_percent"] = band_median(alpha, bands, n_bands).tolist()
            report["loss_percent"] = band_median(loss, bands, n_bands).tolist()
        return ref, report

    # -- transform -----------------------------------------------------------------------------
    @staticmethod
    def _warn_once(warned, key, text, category, figures=None):
        if warned.first(key):  # once per file in a batch (hsiffc.errors.warning_scope)
            warnings.warn(category(text, figures=figures),
                          stacklevel=5)  # past _transform and Prepared.transform

    def reference_index(self, exposure_ms: float) -> int:
        """Index of the reference used for a scene at ``exposure_ms``: the same exposure, else
        the nearest (by ratio)."""
        self.check_is_fitted()
        exps = np.asarray(self.white_exposures_ms_, float)
        return int(np.argmin(np.abs(np.log(exps / max(exposure_ms, 1e-300)))))

    def prepare(self) -> "PreparedReflectance":
        """The calibration prepared (None for the ratio method): :class:`PreparedReflectance`."""
        self.check_is_fitted()
        cal = (self.calibration_product() if REFLECTANCE_METHODS[self.method_].leakage_aware
               else None)
        return PreparedReflectance(self, None if cal is None else cal.prepare())

    def transform(self, frame):
        """The frame's reflectance factor per value (float32) with the reference's flags."""
        return self.prepare().transform(frame)

    def _transform(self, frame, prepared, warned):
        """:meth:`transform` with the calibration ``prepared`` (:meth:`prepare`) and the
        warnings given so far (``warned``, a :class:`~hsiffc.errors.WarnedOnce`)."""
        t = frame.exposure_ms
        j = self.reference_index(t)
        white = self.white_rate_[j]
        if frame.data.shape != white.shape:
            raise CalibrationMismatchError(
                f"reflectance: the frame has shape {frame.data.shape} but the white reference "
                f"{white.shape}; fit the reference on frames of the scenes' size and stage "
                "(mosaic or cube)")
        rate, dq_model, _, _ = self._rate(frame, self.method_, prepared)
        bands, _, _ = frame_bands(frame)
        panel = np.asarray(self.panel_, np.float64)[bands]
        out = reflectance_factor(rate, white, panel)
        dq = frame.dq | self.dq_[j].astype(DQ_DTYPE, copy=False)
        if dq_model is not None:
            dq |= dq_model
        t_ref = self.white_exposures_ms_[j]
        scale = t_ref / t
        info = {"method": self.method_, "panel": self.panel_,
                "reference_exposure_ms": t_ref, "scene_exposure_ms": t,
                "exposure_scale": scale}
        if abs(scale - 1) > 1e-6:
            how = ("light rates of the leakage model, valid within the calibration's exposure "
                   "range" if REFLECTANCE_METHODS[self.method_].leakage_aware else
                   "a linear response and a dark matched to each exposure")
            self._warn_once(warned, ("exposure", t),
                            f"reflectance: scene at {t:g} ms, white reference at {t_ref:g} ms: "
                            f"scaled by the exposure (x {scale:.4g}), which assumes {how}; "
                            "record a reference at the scenes' exposure for the most direct "
                            "ratio", ExposureMismatchWarning,
                            {"scene_exposure_ms": t, "reference_exposure_ms": t_ref,
                             "exposure_scale": scale})
        g_ref, g = self.white_gain_[j], json_safe(frame.meta.get("gain"))
        if g is not None and g_ref is not None and g != g_ref:
            info["gain_mismatch"] = [g_ref, g]
            self._warn_once(warned, ("gain", str(g)),
                            f"reflectance: scene recorded at gain {g}, white reference at "
                            f"{g_ref}: not corrected, every reflectance is off by the gain "
                            "ratio; record the reference at the scenes' gain",
                            GainMismatchWarning, {"scene_gain": g, "reference_gain": g_ref})
        if frame.kind == "light":
            frac, med = scene_brightness(out, dq == 0,
                                         max_reflectance=float(self.max_reflectance))
            info["fraction_above_max"] = None if math.isnan(frac) else round(frac, 4)
            if frac > float(self.max_bright_fraction):
                self._warn_once(
                    warned, ("bright", t),
                    f"reflectance: scene brighter than the white reference: {100 * frac:.0f} % "
                    f"of its good values above {float(self.max_reflectance):g} (median "
                    f"{med:.3g}); scene at {t:g} ms, reference at {t_ref:g} ms: the scene was "
                    "probably recorded at another exposure, gain or light than the panel "
                    "(or the panel was in shade); record the panel under the scene's light "
                    "and settings", SceneBrighterThanReferenceWarning,
                    {"fraction_above_max": round(frac, 4), "median": float(med),
                     "max_reflectance": float(self.max_reflectance),
                     "scene_exposure_ms": t, "reference_exposure_ms": t_ref})
        return frame.replace(data=out, dq=dq, corrected_by=self.name,
                             meta={"units": "reflectance factor", "reflectance": info})


class PreparedReflectance(PreparedWithCalibration):
    """A fitted :class:`Reflectance` made ready for frames.

    Attributes
    ----------
    stage : Reflectance
    calibration : PreparedCalibration or None
        Its calibration, prepared (None for a method that needs none).
    warned : WarnedOnce
        The warnings it has given (:class:`hsiffc.errors.WarnedOnce`): each once per file
        of a batch, once per pipeline plan outside a batch.
    """

    __slots__ = ("warned",)

    def __init__(self, stage, calibration):
        super().__init__(stage, calibration)
        self.warned = WarnedOnce()

    def transform(self, frame):
        """:meth:`Reflectance.transform`."""
        return self.stage._transform(frame, self.calibration, self.warned)
