"""Dark subtraction with master darks matched to the exposure (wraps :mod:`hsiffc.data.dark`)."""

from __future__ import annotations

import numpy as np

from ..data.dark import DarkLine, fit_dark_line
from ..errors import ParameterError
from ..data.frame import stack_mean
from ..data.params import Param
from .common import (AVERAGE, CALIBRATION, GIVE_CALIBRATION, find_exposure,
                     group_by_exposure, unit_hint)
from .base import PreparedWithCalibration, Stage
from .refchecks import check_darks

MATCHES = ("exposure", "scale")


class DarkSubtract(Stage):
    """Subtract a master dark (robust average of a dark stack) matched to the frame's exposure.

    The frame keeps the dark it lost in ``dark_removed`` (so ``frame.raw`` is exact).

    Parameters
    ----------
    average : "median" or "mean"
        How a stack of dark frames becomes a master dark (the median resists outliers).
    match : "exposure" or "scale"
        ``"exposure"``: use the master of the same exposure, else fall back as ``"scale"`` does;
        ``"scale"``: per pixel ``d0 + slope * t`` fitted through the masters (two or more
        exposures), or the calibration's dark level and dark current.
    calibration : path or Calibration, optional
        Supplies the dark level at t = 0 and the dark current where no master matches.
    """

    name = "dark"
    gpu_as = "dark"
    #: fitted state as a pipeline file stores it (:func:`hsiffc.data.products.check_product`)
    state_schema = {"fitted_": "bool", "exposures_ms_": "numbers",
                    "masters_": ("f", ("exposures_ms_", "H", "W")),
                    "master_dq_": ("u", ("exposures_ms_", "H", "W")),
                    "dark0_": ("f", ("H", "W")), "dark_slope_": ("f", ("H", "W"))}
    fuses_as = "dark"
    requires = frozenset({"mosaic", "raw"})
    produces = frozenset({"dark_subtracted"})
    removes = frozenset({"raw"})
    param_spec = {"average": AVERAGE, "match": Param("choice", choices=MATCHES),
                  "calibration": CALIBRATION}

    def __init__(self, *, average: str = "median", match: str = "exposure", calibration=None):
        self.average = average
        self.match = match
        self.calibration = calibration

    def fit(self, frames):
        """Build master darks (DN) from the dark training frames, per exposure; returns ``self``."""
        self.validate_params()
        groups = group_by_exposure(frames, "dark")
        if not groups and self.calibration is None:
            raise ParameterError("dark: no dark frames among the training frames; add dark "
                                 "frames (--dark PATH, or kind 'dark' in their metadata) or "
                                 f"{GIVE_CALIBRATION} (its dark level is used)")
        self.calibration_product()  # a bad calibration fails here, not at the first frame
        self.exposures_ms_ = [float(e) for e in groups]
        if groups:
            stacks = [stack_mean(s, robust=self.average == "median") for s in groups.values()]
            check_darks("dark", groups, [m for m, _ in stacks], stacklevel=3)
            self.masters_ = np.stack([m for m, _ in stacks])
            self.master_dq_ = np.stack([dq for _, dq in stacks])
        if len(groups) >= 2:  # per-pixel line through the masters for unmatched exposures
            self.dark0_, self.dark_slope_ = fit_dark_line(self.exposures_ms_, self.masters_)
        self.fitted_ = True
        return self

    def prepare(self) -> "PreparedDark":
        """The dark line through the masters and the prepared calibration, made now
        (:class:`PreparedDark`)."""
        self.check_is_fitted()
        cal = self.calibration_product()
        line = (DarkLine(self.dark0_, self.dark_slope_) if getattr(self, "dark0_", None)
                is not None else None)
        return PreparedDark(self, line, None if cal is None else cal.prepare())

    def dark_for(self, exposure_ms: float, shape) -> tuple[np.ndarray, str]:
        """The dark (DN, float32) subtracted at this exposure and how it was obtained
        (:meth:`PreparedDark.dark_for`; prepared on each call)."""
        return self.prepare().dark_for(exposure_ms, shape)

    def transform(self, frame):
        """The frame less the dark matched to its exposure (DN in, DN out; ``dark_removed``
        set; :meth:`hsiffc.data.frame.Frame.dark_subtracted`)."""
        return self.prepare().transform(frame)


class PreparedDark(PreparedWithCalibration):
    """A fitted :class:`DarkSubtract` made ready for frames.

    Attributes
    ----------
    stage : DarkSubtract
    line : DarkLine or None
        ``d0 + slope t`` through the masters (two or more exposures), else None.
    calibration : PreparedCalibration or None
        The stage's calibration, prepared (its dark line where no master matches).
    """

    __slots__ = ("line",)

    def __init__(self, stage, line, calibration):
        super().__init__(stage, calibration)
        self.line = line

    def dark_for(self, exposure_ms: float, shape) -> tuple[np.ndarray, str]:
        """The dark (DN, float32) subtracted at this exposure and how it was obtained."""
        st = self.stage
        e = find_exposure(st.exposures_ms_, exposure_ms) if st.match == "exposure" else None
        if e is not None:
            return st.masters_[st.exposures_ms_.index(e)], f"master at {e:g} ms"
        if self.line is not None:
            return self.line.at(exposure_ms), "scaled (d0 + slope t)"
        cal = self.calibration
        if cal is not None:
            cal.check_compatible(frame_shape=shape, what="the frame")
            return cal.dark_at(exposure_ms), "calibration"
        only = f" (only at {st.exposures_ms_[0]:g} ms)" if st.exposures_ms_ else ""
        raise ParameterError(f"no master dark at {exposure_ms:g} ms{only} and nothing to scale "
                             "with: record darks at this exposure or at two exposures, or "
                             f"{GIVE_CALIBRATION}{unit_hint(exposure_ms, st.exposures_ms_)}")

    def transform(self, frame):
        """:meth:`DarkSubtract.transform`."""
        dark, how = self.dark_for(frame.exposure_ms, frame.data.shape)
        return frame.dark_subtracted(dark, dark_source=how)
