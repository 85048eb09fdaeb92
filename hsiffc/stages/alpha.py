"""The alpha validity mask: flag responses whose leakage percentage exceeds a threshold."""

from __future__ import annotations

from ..data.params import Param
from ..leakage.validity import ALPHA_METHODS, validity_flags
from .common import CALIBRATION, THRESHOLD
from .base import PreparedWithCalibration, Stage


class AlphaMask(Stage):
    """Compute the leakage percentage alpha of every pixel and flag LEAKAGE above a threshold.

    Runs :func:`hsiffc.leakage.validity.validity_flags` on the frame's raw response (``frame.raw``: the
    data plus the dark a stage actually removed, since the leakage acts on the raw response);
    the dark under it is the one a dark stage removed, else the calibrated dark. The frame
    keeps its data; it gains an ``alpha`` plane (percent; ``inf`` where no light rate can be
    estimated) and DQ bits: LEAKAGE (alpha over ``threshold_percent`` or undefined),
    SATURATED, OUT_OF_DOMAIN (exposure outside the calibrated range), and the calibration's
    own pixel flags. In a pipeline, after a dark stage, it runs fused with it (and with a
    two-point FFC after it: :mod:`hsiffc.stages.fusion`, the same result).

    Parameters
    ----------
    calibration : path or Calibration
    threshold_percent : float
    method : "paper" (k ~ signal / exposure) or "model" (k by inverting the model)
    """

    name = "alpha_mask"
    gpu_as = "alpha_mask"
    #: fitted state as a pipeline file stores it (:func:`hsiffc.data.products.check_product`)
    state_schema = {"fitted_": "bool"}
    stateless = True
    requires = frozenset({"mosaic", "response"})
    produces = frozenset({"alpha"})
    param_spec = {"calibration": CALIBRATION, "threshold_percent": THRESHOLD,
                  "method": Param("choice", choices=ALPHA_METHODS)}

    def __init__(self, *, calibration=None, threshold_percent: float = 12.0,
                 method: str = "paper"):
        self.calibration = calibration
        self.threshold_percent = threshold_percent
        self.method = method

    def fit(self, frames):
        """Check the calibration against the training frames; returns ``self``."""
        self.validate_params()
        cal = self.require_calibration()
        for f in frames:
            if not f.is_cube:
                cal.check_frame(f, what="a training frame")
                break
        self.fitted_ = True
        return self

    @property
    def fuses_as(self):
        """``"alpha_mask"`` with an alpha a fused front end computes in its pass (the paper's:
        :attr:`hsiffc.leakage.validity.AlphaMethod.one_pass`; :mod:`hsiffc.stages.fusion`),
        else None."""
        how = ALPHA_METHODS.get(self.method)
        return "alpha_mask" if how is not None and how.one_pass else None

    def prepare(self) -> "PreparedAlphaMask":
        """The calibration prepared (:meth:`hsiffc.calibrate.Calibration.prepare`)."""
        self.check_is_fitted()
        return PreparedAlphaMask(self, self.require_calibration().prepare())

    def transform(self, frame):
        """The frame with its alpha plane (percent) and LEAKAGE / OUT_OF_DOMAIN flags added."""
        return self.prepare().transform(frame)

    def calibration_for(self, frame):
        """The calibration, checked against ``frame`` (shape, bit depth, mosaic)."""
        cal = self.require_calibration()
        cal.check_frame(frame)
        return cal

    def flagged(self, frame, alpha, dq):
        """``frame`` with this stage's alpha plane and DQ (computed by :meth:`transform`, or
        by a fused pass: :mod:`hsiffc.stages.fusion`)."""
        return frame.replace(dq=dq, alpha=alpha,
                             meta={"alpha_threshold_percent": float(self.threshold_percent)})


class PreparedAlphaMask(PreparedWithCalibration):
    """A fitted :class:`AlphaMask` made ready for frames (``calibration``: its calibration,
    prepared)."""

    __slots__ = ()

    def transform(self, frame):
        """:meth:`AlphaMask.transform`."""
        st = self.stage
        cal = self.calibration
        cal.check_frame(frame)
        alpha, dq = validity_flags(frame.raw, frame.exposure_ms, cal,
                                   threshold_percent=float(st.threshold_percent),
                                   method=st.method, dark=frame.dark_removed, dq=frame.dq)
        return st.flagged(frame, alpha, dq)
