"""Leakage linearisation stage (beyond the paper): wraps :func:`hsiffc.leakage.linearise.linearise`."""

from __future__ import annotations

import numpy as np

from ..leakage.linearise import linearise
from .common import CALIBRATION, THRESHOLD
from .base import PreparedWithCalibration, Stage


class LeakageLinearise(Stage):
    """Invert the leakage model per pixel: each response becomes the one without leakage.

    The new response is ``k t`` above the pixel's dark level (DN), with k the light rate that
    explains the measured raw response (``frame.raw``) under the calibrated model. Pixels whose
    model alpha exceeds ``alpha_limit_percent`` are flagged LEAKAGE (their value is still the
    best estimate); responses the model cannot explain are flagged as
    :func:`hsiffc.leakage.model.invert_response` says (BELOW_DARK, SATURATED, UNREACHABLE,
    NOT_CONVERGED).

    The output is the signal ``k t`` when a dark was removed, else the raw-scale ``d + k t``;
    :meth:`light_rate` gives the light-rate map (DN/ms) itself.

    Parameters
    ----------
    calibration : path or Calibration
    alpha_limit_percent : float
    """

    name = "linearise"
    #: fitted state as a pipeline file stores it (:func:`hsiffc.data.products.check_product`)
    state_schema = {"fitted_": "bool"}
    stateless = True
    requires = frozenset({"mosaic", "response"})
    removes = frozenset({"response"})
    param_spec = {"calibration": CALIBRATION, "alpha_limit_percent": THRESHOLD}

    def __init__(self, *, calibration=None, alpha_limit_percent: float = 90.0):
        self.calibration = calibration
        self.alpha_limit_percent = alpha_limit_percent

    def fit(self, frames):
        """Check the calibration against the training frames; returns ``self``."""
        self.validate_params()
        self.require_calibration()
        self.fitted_ = True
        return self

    def light_rate(self, frame):
        """Per-pixel light rate k (DN/ms), DQ flags and model alpha of a frame, and the
        calibration used."""
        cal = self.require_calibration()
        cal.check_frame(frame)
        lin = linearise(frame.raw, frame.exposure_ms, cal.a, cal.b, cal.dark, cal.dark_current,
                        full_scale_dn=2 ** frame.bit_depth - 1,
                        alpha_limit_percent=float(self.alpha_limit_percent))
        return lin.light_rate, lin.dq, lin.alpha, cal

    def prepare(self) -> "PreparedLinearise":
        """The calibration prepared (its dark line:
        :meth:`hsiffc.calibrate.Calibration.prepare`)."""
        self.check_is_fitted()
        return PreparedLinearise(self, self.require_calibration().prepare())

    def transform(self, frame):
        """The frame with each response replaced by ``k t`` (DN), the response without leakage."""
        return self.prepare().transform(frame)


class PreparedLinearise(PreparedWithCalibration):
    """A fitted :class:`LeakageLinearise` made ready for frames (``calibration``: its calibration,
    prepared)."""

    __slots__ = ()

    def transform(self, frame):
        """:meth:`LeakageLinearise.transform`."""
        k, dq, _, _ = self.stage.light_rate(frame)
        signal = k * frame.exposure_ms
        if frame.dark_removed is None:
            signal = signal + self.calibration.dark_at(frame.exposure_ms)
        return frame.replace(data=signal.astype(np.float32), dq=frame.dq | dq,
                             corrected_by=self.stage.name)
