"""Flat-field correction stages: two-point (eq. 5) with alpha-selected training, polynomial,
and ``flat_field``, which runs any method of :data:`hsiffc.flatfield.FFC_METHODS` learnt from a
calibration alone.

The two-point and polynomial stages wrap the array functions of
:mod:`hsiffc.flatfield.two_point` and :mod:`hsiffc.flatfield.polynomial` and work on
dark-subtracted frames (put a ``dark`` stage before them): they carry no dark handling of
their own. :func:`from_calibration` makes the flat-field step of a pipeline built from a
calibration alone (``hsiffc correct --ffc``), through the registry.
"""

from __future__ import annotations

import warnings
from dataclasses import fields

import numpy as np

from ..spectral.bandstats import band_reduce
from ..data.dq import DQ_DTYPE
from ..data.mosaic import mosaic_band_labels, wavelength_order
from ..errors import HsiffcWarning, ParameterError
from ..flatfield.two_point import (
    NORMALISATIONS,
    means_ratio,
    paper_ratio,
    two_point_apply,
    two_point_fit,
)
from ..data.frame import stack_mean
from ..data.params import Param, validate_method
from ..flatfield.methods import FFC_METHODS, FROM_CALIBRATION, correct_flat
from ..flatfield.polynomial import PolynomialFlat, polynomial_apply, polynomial_fit
from ..leakage.validity import alpha_table_of
from .common import (AVERAGE, CALIBRATION, GIVE_CALIBRATION, THRESHOLD, find_exposure,
                     group_by_exposure)
from . import registry
from .base import Stage
from .refchecks import check_flats


def _flats(frames, stage: str) -> dict:
    flats = group_by_exposure(frames, "light")
    if not flats:
        raise ParameterError(f"{stage}: no flat (light) frames among the training frames")
    if any(f.dark_removed is None for stack in flats.values() for f in stack):
        raise ParameterError(f"{stage}: the training flats are not dark-subtracted; put a "
                             "'dark' stage before this one in the pipeline")
    return flats


class TwoPointFFC(Stage):
    """Two-point flat-field correction (the paper's eq. 5) trained at the exposure alpha selects.

    Parameters
    ----------
    exposure_ms : float, optional
        Train at this flat exposure for every band. Default: per band, the longest flat exposure
        whose median alpha stays under ``threshold_percent`` (the paper's improved method);
        that needs ``calibration``.
    calibration : path or Calibration, optional
    threshold_percent : float
    normalisation : "paper" or "mean_gain"
        ``"paper"``: ``Avg(L3) (R3 - R1) / (R2 - R1)`` per band, Avg(L3) the mean raw response
        of the test frame's good pixels (:func:`hsiffc.flatfield.two_point.paper_scale`); ``"mean_gain"``:
        ``(R3 - R1) mean(R2 - R1) / (R2 - R1)`` (DN).
    average : "median" or "mean" (for the flat stacks)

    Fitted attributes: ``gain_`` (H, W), ``flat_mean_`` (per band), ``dq_`` (the flats' own
    DQ bits, read-only: fixed once fitted or loaded, so a fused front end keeps it merged with
    the calibration's flags) and ``selected_ms_`` (the flat exposure of each band).
    """

    name = "two_point_ffc"
    gpu_as = "two_point_ffc"
    fuses_as = "two_point_ffc"
    removes = frozenset({"response"})
    param_spec = {"exposure_ms": Param("number", low=0, low_open=True, optional=True, unit="ms"),
                  "calibration": CALIBRATION, "threshold_percent": THRESHOLD,
                  "normalisation": Param("choice", choices=NORMALISATIONS), "average": AVERAGE}
    state_schema = FFC_METHODS["two_point"].state_schema

    def __init__(self, *, exposure_ms: float | None = None, calibration=None,
                 threshold_percent: float = 12.0, normalisation: str = "paper",
                 average: str = "median"):
        self.exposure_ms = exposure_ms
        self.calibration = calibration
        self.threshold_percent = threshold_percent
        self.normalisation = normalisation
        self.average = average

    def set_state(self, js: dict, arrays: dict) -> "TwoPointFFC":
        """As :meth:`Stage.set_state`; the flat's flags ``dq_`` become a read-only copy, fixed
        as after :meth:`fit`."""
        super().set_state(js, arrays)
        if getattr(self, "dq_", None) is not None:
            self.dq_ = np.array(self.dq_, DQ_DTYPE)
            self.dq_.flags.writeable = False
        return self

    @property
    def requires(self):  # eq. (5) scales by the raw test level: it needs the raw response
        extra = {"response"} if self.normalisation == "paper" else set()
        return frozenset({"mosaic", "dark_subtracted", *extra})

    def fit(self, frames):
        self.validate_params()
        flats = _flats(frames, self.name)
        band_map = next(iter(flats.values()))[0].band_map()
        n_bands = int(band_map.max()) + 1
        table = None
        if self.exposure_ms is not None:
            e = find_exposure(flats, float(self.exposure_ms))
            if e is None:
                raise ParameterError(f"{self.name}: no flat frames at exposure_ms="
                                     f"{self.exposure_ms:g}; available: {list(flats)}")
            selected = [e] * n_bands
        else:
            selected, table = self._select(flats, band_map)
        gain = np.ones(band_map.shape, np.float32)
        flat_mean = np.full(n_bands, np.nan)
        dq = np.zeros(band_map.shape, DQ_DTYPE)
        for e in sorted(set(selected)):
            signal, sdq = stack_mean(flats[e], robust=self.average == "median")
            check_flats(self.name, flats[e], signal, stacklevel=3)  # as reflectance's checks
            ff = two_point_fit(signal, band_map=band_map, flat_dq=sdq)
            bands = [i for i, s in enumerate(selected) if s == e]
            mask = np.isin(band_map, bands)
            gain[mask] = ff.gain[mask]
            dq[mask] |= ff.dq[mask]
            flat_mean[bands] = ff.flat_mean[bands]
        dq.flags.writeable = False  # fixed once fitted (a fused pass keeps it merged)
        self.gain_, self.flat_mean_, self.dq_ = gain, flat_mean, dq
        self.selected_ms_ = selected
        self.alpha_table_ = None if table is None else table.to_dict()
        self.fitted_ = True
        return self

    def _select(self, flats, band_map):
        """Per band, the longest flat exposure with median alpha under the threshold."""
        cal = self.calibration_product()
        if cal is None:
            raise ParameterError(f"{self.name}: give the flats' exposure (exposure_ms = ... in "
                                 "the step's [[step]] table, exposure_ms= in Python) or a "
                                 "calibration to select the training exposure per band by the "
                                 f"leakage percentage ({GIVE_CALIBRATION})")
        raws = np.stack([np.mean([f.raw for f in s], axis=0) for s in flats.values()])
        darks = np.stack([s[0].dark_removed for s in flats.values()])
        mosaic = next(iter(flats.values()))[0].mosaic
        table = alpha_table_of(raws, list(flats), cal, darks=darks, band_map=band_map,
                               wavelengths_nm=mosaic.wavelengths_nm if mosaic else None)
        sel = table.select(float(self.threshold_percent)).selected_ms
        fallback = min(flats)
        if np.isnan(sel).any():
            names = mosaic_band_labels(mosaic, len(sel))
            order = wavelength_order(len(sel), table.wavelengths_nm or None)
            missing = ", ".join(names[i] for i in order if np.isnan(sel[i]))
            warnings.warn(f"no flat exposure has alpha under {self.threshold_percent:g} % "
                          f"in {missing}; using the shortest, {fallback:g} ms", HsiffcWarning,
                          stacklevel=3)
        return [fallback if np.isnan(s) else float(s) for s in sel], table

    def transform(self, frame):
        self.check_is_fitted()
        if frame.data.shape != self.gain_.shape:
            raise ValueError(f"frame shape {frame.data.shape} differs from the flat's "
                             f"{self.gain_.shape}")
        return self.corrected(frame, frame.dq | self.dq_)

    def band_flat_mean(self, band_map) -> np.ndarray:
        """The flat's per-band mean ``mean(R(L2) - R(L1))`` of eq. (5) (DN)."""
        flat_mean = np.asarray(self.flat_mean_)
        if flat_mean.ndim == 2:  # pipeline files of format 1 kept it per pixel
            flat_mean = band_reduce(flat_mean, band_map)
        return flat_mean

    def corrected(self, frame, dq, test_mean=None):
        """``frame`` corrected, given its DQ with the flat's own flags (``dq_``) merged in
        (:meth:`transform` merges them; a fused pass merges them in its own pass:
        :mod:`hsiffc.stages.fusion`). ``test_mean``: the per-band mean of the frame's raw
        response over the pixels with ``dq == 0``, when a fused pass took it already (else it
        is taken here: the ``"paper"`` normalisation's ``Avg(L3)``)."""
        scale, band_map = 1.0, None
        if self.normalisation == "paper":
            band_map = frame.band_map()
            flat_mean = self.band_flat_mean(band_map)
            scale = (paper_ratio(frame.raw, flat_mean, band_map=band_map, good=dq == 0)
                     if test_mean is None else means_ratio(test_mean, flat_mean))
        out = two_point_apply(frame.signal, self.gain_, scale, band_map=band_map, dq=dq)
        return frame.replace(data=out, dq=dq,
                             corrected_by=self.name,
                             meta={"ffc": "two_point", "ffc_training_ms": self.selected_ms_})


class PolynomialFFC(Stage):
    """Per-pixel polynomial flat-field correction over several flat levels
    (:func:`hsiffc.flatfield.polynomial.polynomial_fit` / :func:`~hsiffc.flatfield.polynomial.polynomial_apply`).

    One level per (exposure, illumination) of the training flats. Signals outside a pixel's
    trained range (with ``margin`` relative slack) continue along the end tangent and are
    flagged OUT_OF_DOMAIN; pixels whose flats define no correction pass through unchanged with
    NO_FLAT.

    Parameters
    ----------
    order : int (>= 1; needs order + 1 flat levels)
    margin : float (>= 0)
    average : "median" or "mean"
    """

    name = "polynomial_ffc"
    requires = frozenset({"mosaic", "dark_subtracted"})
    removes = frozenset({"response"})
    param_spec = {"order": Param("integer", low=1), "margin": Param("number", low=0),
                  "average": AVERAGE}
    state_schema = FFC_METHODS["polynomial"].state_schema

    def __init__(self, *, order: int = 2, margin: float = 0.05, average: str = "median"):
        self.order = order
        self.margin = margin
        self.average = average

    def fit(self, frames):
        self.validate_params()
        levels = {}
        for e, stack in _flats(frames, self.name).items():
            for f in stack:
                levels.setdefault((e, f.meta.get("illumination", "")), []).append(f)
        if len(levels) < int(self.order) + 1:
            raise ParameterError(f"{self.name}: a polynomial of order {self.order} needs at "
                                 f"least {int(self.order) + 1} flat levels; the training "
                                 f"frames have {len(levels)}")
        means = [stack_mean(s, robust=self.average == "median")
                 for _, s in sorted(levels.items())]
        fit = polynomial_fit(np.stack([m for m, _ in means]), order=int(self.order),
                             band_map=next(iter(levels.values()))[0].band_map(),
                             level_dq=np.stack([dq for _, dq in means]))
        self.coef_, self.scale_ = fit.coef, fit.scale
        self.x_min_, self.x_max_, self.dq_ = fit.x_min, fit.x_max, fit.dq
        self.n_levels_ = len(levels)
        self.fitted_ = True
        return self

    def transform(self, frame):
        self.check_is_fitted()
        flat = PolynomialFlat(self.coef_, self.scale_, self.x_min_, self.x_max_, self.dq_)
        out, dq = polynomial_apply(frame.signal, flat, margin=float(self.margin))
        return frame.replace(data=out, dq=frame.dq | dq, corrected_by=self.name,
                             meta={"ffc": f"polynomial order {int(self.order)}"})


class FlatFieldFFC(Stage):
    """Any flat-field method of :data:`hsiffc.flatfield.FFC_METHODS` that learns from a
    calibration alone (its ``learn``), run through the registry.

    ``fit`` stores what the method learnt (one fitted attribute ``<field>_`` per field of the
    method's ``learnt`` type); ``transform`` corrects the frame's raw response with
    :func:`hsiffc.flatfield.correct_flat` above the dark a preceding ``dark`` stage removed
    (else the calibration's dark at the frame's exposure) and returns it dark-subtracted.

    Parameters
    ----------
    method : str
        A name of :data:`~hsiffc.flatfield.FFC_METHODS` with a ``learn``.
    calibration : path or Calibration
    """

    name = "flat_field"
    requires = frozenset({"mosaic", "response"})
    produces = frozenset({"dark_subtracted"})
    removes = frozenset({"raw", "response"})
    param_spec = {"method": Param("choice", choices=FFC_METHODS), "calibration": CALIBRATION}

    def __init__(self, *, method: str = "model", calibration=None):
        self.method = method
        self.calibration = calibration

    @staticmethod
    def state_schema(params: dict) -> dict | None:
        """The fitted state of a step with these parameters: its method's ``state_schema``."""
        how = FFC_METHODS.get(params.get("method"))
        return None if how is None else {"fitted_": "bool", **how.state_schema}

    def fit(self, frames):
        self.validate_params()
        how = FFC_METHODS[self.method]
        if how.learn is None:
            raise ParameterError(f"{self.name}: method {self.method!r} learns from training "
                                 f"frames, not from a calibration alone; use the stage "
                                 f"{how.stage!r} (methods learnt from a calibration: "
                                 f"{', '.join(FROM_CALIBRATION)})")
        learnt = how.learn(self.require_calibration())
        for f in fields(learnt):
            setattr(self, f"{f.name}_", getattr(learnt, f.name))
        self.fitted_ = True
        return self

    def learnt(self):
        """What the method learnt, as its ``learnt`` type (from the fitted attributes)."""
        self.check_is_fitted()
        how = FFC_METHODS[self.method]
        return how.learnt(**{f.name: getattr(self, f"{f.name}_") for f in fields(how.learnt)})

    def transform(self, frame):
        flat = self.learnt()
        cal = self.require_calibration()
        cal.check_frame(frame)
        dark = (frame.dark_removed if frame.dark_removed is not None else
                cal.dark_at(frame.exposure_ms))
        res = correct_flat(self.method, frame.raw, dark, flat, dq=frame.dq,
                           band_map=frame.band_map(), exposure_ms=frame.exposure_ms,
                           calibration=cal)
        return frame.replace(data=res.out, dq=res.dq, dark_removed=np.asarray(dark, np.float32),
                             corrected_by=self.name, meta={"ffc": self.method})


def from_calibration(method: str, calibration) -> Stage:
    """The fitted flat-field step of ``method`` learnt from ``calibration`` alone: the stage
    its record in :data:`hsiffc.flatfield.FFC_METHODS` names, fitted with no training frames
    (what ``hsiffc correct --ffc METHOD`` runs).

    Raises
    ------
    ParameterError
        Unknown ``method``, or one that learns from training frames only.
    """
    how = validate_method(method, FFC_METHODS, "flat-field method")
    if how.learn is None:
        raise ParameterError(f"flat-field method {method!r} learns from training frames (fit a "
                             f"pipeline with its stage {how.stage!r}: hsiffc fit); from a "
                             f"calibration alone: {', '.join(FROM_CALIBRATION)}")
    stage_cls = registry.get(how.stage)
    params = {"calibration": calibration}
    if "method" in stage_cls.param_spec:
        params["method"] = method
    return stage_cls(**params).fit([])

