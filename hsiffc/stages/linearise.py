"""Leakage linearisation (beyond the paper): recover the light rate from leaking responses."""

from __future__ import annotations

import numpy as np

from .. import model
from ..dq import DQ, DQ_DTYPE
from ._common import load_calibration, raw_response
from .base import Stage


class LeakageLinearise(Stage):
    """Invert the leakage model per pixel: each response becomes the one without leakage.

    The new response is ``k t`` above the pixel's dark level (DN), with k the light rate that
    explains the measured response under the calibrated model.

    A leaking response still determines k (the saturation level moves by 1/b DN per e-fold of
    k), but the closer to dynamic saturation, the more the noise is amplified: the error of k
    grows like ``1 / (1 - alpha)`` with the model alpha. Pixels whose model alpha exceeds
    ``alpha_limit_percent`` are flagged LEAKAGE (their value is still the best estimate);
    responses the model cannot explain are flagged as :func:`hsiffc.model.invert_response`
    says (BELOW_DARK, SATURATED, UNREACHABLE, NOT_CONVERGED).

    The output is the dark-subtracted signal ``k t`` when the input was dark-subtracted, else
    the raw-scale ``d + k t``; :meth:`light_rate` gives the light-rate map (DN/ms) itself.

    Parameters
    ----------
    calibration : path or Calibration
    alpha_limit_percent : float
    """

    name = "linearise"

    stateless = True

    def __init__(self, *, calibration=None, alpha_limit_percent: float = 90.0):
        self.calibration = calibration
        self.alpha_limit_percent = alpha_limit_percent

    def _cal(self):
        if self.calibration is None:
            raise ValueError("LeakageLinearise needs calibration= (from 'hsiffc calibrate')")
        return load_calibration(self.calibration)

    def light_rate(self, frame):
        """Per-pixel light rate k (DN/ms) and the inversion flags of a frame."""
        cal = self._cal()
        cal.check_compatible(frame_shape=frame.data.shape, bit_depth=frame.bit_depth,
                             what="the frame")
        y = raw_response(frame, cal)
        inv = model.invert_response(y, frame.exposure_ms, cal.a.astype(np.float64),
                                    cal.b.astype(np.float64), cal.dark.astype(np.float64),
                                    full_scale=2 ** frame.bit_depth - 1)
        k_light = np.maximum(inv.k - cal.dark_current, 0.0)
        alpha = model.leakage_percentage(y, np.maximum(inv.k, 1e-300), cal.a, cal.b)
        return k_light, inv.flags, alpha, cal

    def transform(self, frame):
        k, flags, alpha, cal = self.light_rate(frame)
        t = frame.exposure_ms
        signal = k * t
        if not frame.meta.get("dark_subtracted"):
            signal = signal + cal.dark + cal.dark_current * t
        dq = frame.dq | flags.astype(DQ_DTYPE)
        dq[~np.isfinite(alpha) | (alpha > self.alpha_limit_percent)] |= DQ_DTYPE(DQ.LEAKAGE)
        out = np.where(np.isfinite(signal), signal, 0.0).astype(np.float32)
        return frame.replace(data=out, dq=dq, meta={"linearised": True})
