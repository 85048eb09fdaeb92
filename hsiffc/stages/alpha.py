"""The alpha validity mask: flag responses whose leakage percentage exceeds a threshold."""

from __future__ import annotations

import numpy as np

from .. import model
from ..dq import DQ, DQ_DTYPE
from ._common import load_calibration, raw_response
from .base import Stage


class AlphaMask(Stage):
    """Compute the leakage percentage alpha of every pixel and flag LEAKAGE above a threshold.

    Works on raw or dark-subtracted frames (the calibrated dark level is added back: the
    leakage acts on the raw response). The frame keeps its data; it gains an ``alpha`` plane
    (percent) and DQ bits: LEAKAGE (alpha over ``threshold_percent`` or no positive signal),
    OUT_OF_DOMAIN (exposure outside the calibrated range), and the calibration's own pixel flags.

    Parameters
    ----------
    calibration : path or Calibration
    threshold_percent : float
    method : "paper" (k ~ signal / exposure) or "model" (k by inverting the model)
    """

    name = "alpha_mask"

    stateless = True

    def __init__(self, *, calibration=None, threshold_percent: float = 12.0,
                 method: str = "paper"):
        self.calibration = calibration
        self.threshold_percent = threshold_percent
        self.method = method

    def _cal(self):
        if self.calibration is None:
            raise ValueError("AlphaMask needs calibration= (a calibration file from "
                             "'hsiffc calibrate')")
        return load_calibration(self.calibration)

    def _alpha_paper(self, frame, cal, t):
        """alpha = 100 a e^{bY} / ((Y - d) / t) in single precision, few passes (the hot path of
        batch correction). Non-positive signal gives inf (flagged)."""
        f32 = np.float32
        cache = getattr(self, "_consts", None)
        if cache is None or cache[0] is not cal:
            with np.errstate(divide="ignore"):
                ln_a = np.log(cal.a.astype(np.float64)).astype(f32)
            cache = (cal, ln_a, cal.b.astype(f32), cal.dark.astype(f32),
                     cal.dark_current.astype(f32))
            self._consts = cache
        _, ln_a, b, dark, dc = cache
        dark_t = dark + dc * f32(t)
        if frame.meta.get("dark_subtracted"):
            signal = frame.data.astype(f32, copy=True)
            y = signal + dark_t
        else:
            y = frame.data.astype(f32, copy=False)
            signal = y - dark_t
        positive = signal > 0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            np.log(signal, out=signal, where=positive)
            expo = ln_a + b * y
            expo -= signal
            expo += f32(np.log(100.0 * t))
            alpha = np.exp(expo, out=expo)
        alpha[~positive] = np.inf
        return alpha

    def fit(self, frames):
        cal = self._cal()
        for f in frames:
            if not f.is_cube:
                cal.check_compatible(frame_shape=f.data.shape, bit_depth=f.bit_depth,
                                     what="a training frame")
                break
        self.fitted_ = True
        return self

    def transform(self, frame):
        if self.method not in ("paper", "model"):
            raise ValueError(f"method must be 'paper' or 'model', got {self.method!r}")
        cal = self._cal()
        cal.check_compatible(frame_shape=frame.data.shape, bit_depth=frame.bit_depth,
                             what="the frame")
        t = frame.exposure_ms
        if self.method == "paper":
            alpha = self._alpha_paper(frame, cal, t)
        else:
            y = raw_response(frame, cal)
            a, b = cal.a.astype(np.float64), cal.b.astype(np.float64)
            inv = model.invert_response(y, t, a, b, cal.dark.astype(np.float64))
            alpha = np.where(inv.flags & int(DQ.BELOW_DARK), np.inf,
                             model.leakage_percentage(y, np.maximum(inv.k, 1e-300), a, b))
        dq = frame.dq.copy()
        dq[~np.isfinite(alpha) | (alpha > self.threshold_percent)] |= DQ_DTYPE(DQ.LEAKAGE)
        if not cal.in_domain(t):
            dq |= DQ_DTYPE(DQ.OUT_OF_DOMAIN)
        if "flags" in cal.arrays:
            dq |= cal["flags"].astype(DQ_DTYPE)
        alpha = np.where(np.isfinite(alpha), alpha, np.finfo(np.float32).max).astype(np.float32)
        return frame.replace(dq=dq, alpha=alpha,
                             meta={"alpha_threshold_percent": float(self.threshold_percent)})
