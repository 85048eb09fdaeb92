"""Dark subtraction with master darks matched to the exposure."""

from __future__ import annotations

import numpy as np

from ..frame import stack_mean
from ._common import find_exposure, group_by_exposure, load_calibration
from .base import Stage

MATCHES = ("exposure", "scale")


class DarkSubtract(Stage):
    """Subtract a master dark (robust average of a dark stack) matched to the frame's exposure.

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

    def __init__(self, *, average: str = "median", match: str = "exposure", calibration=None):
        self.average = average
        self.match = match
        self.calibration = calibration

    def fit(self, frames):
        if self.average not in ("median", "mean"):
            raise ValueError(f"average must be 'median' or 'mean', got {self.average!r}")
        if self.match not in MATCHES:
            raise ValueError(f"match must be one of {MATCHES}, got {self.match!r}")
        groups = group_by_exposure(frames, "dark")
        if not groups and self.calibration is None:
            raise ValueError("no dark frames among the training frames; add dark frames (kind "
                             "'dark') or give calibration= to use its dark level")
        masters, dqs = [], []
        for stack in groups.values():
            m, dq = stack_mean(stack, robust=self.average == "median")
            masters.append(m)
            dqs.append(dq)
        self.exposures_ms_ = [float(e) for e in groups]
        if masters:
            self.masters_ = np.stack(masters)
            self.master_dq_ = np.stack(dqs)
        if len(masters) >= 2:  # per-pixel line through the masters for unmatched exposures
            t = np.asarray(self.exposures_ms_)
            tm = t.mean()
            y = self.masters_.astype(np.float64)
            slope = np.tensordot(t - tm, y - y.mean(axis=0), axes=(0, 0)) / ((t - tm) ** 2).sum()
            self.dark0_ = (y.mean(axis=0) - slope * tm).astype(np.float32)
            self.dark_slope_ = slope.astype(np.float32)
        self.fitted_ = True
        return self

    def dark_for(self, exposure_ms: float, shape) -> tuple[np.ndarray, str]:
        """The dark (DN) subtracted at this exposure and how it was obtained."""
        self.check_is_fitted()
        e = find_exposure(self.exposures_ms_, exposure_ms) if self.match == "exposure" else None
        if e is not None:
            return self.masters_[self.exposures_ms_.index(e)], f"master at {e:g} ms"
        if hasattr(self, "dark0_"):
            return self.dark0_ + self.dark_slope_ * np.float32(exposure_ms), "scaled (d0 + slope t)"
        cal = load_calibration(self.calibration)
        if cal is not None:
            cal.check_compatible(frame_shape=shape, what="the frame")
            return (cal.dark + cal.dark_current * exposure_ms).astype(np.float32), "calibration"
        if len(self.exposures_ms_) == 1:
            raise ValueError(f"no master dark at {exposure_ms:g} ms (only at "
                             f"{self.exposures_ms_[0]:g} ms) and nothing to scale with: record "
                             "darks at this exposure or at two exposures, or give calibration=")
        raise ValueError(f"no master dark at {exposure_ms:g} ms")

    def transform(self, frame):
        self.check_is_fitted()
        if frame.meta.get("dark_subtracted"):
            raise ValueError("this frame is already dark-subtracted; a pipeline should have one "
                             "dark stage")
        dark, how = self.dark_for(frame.exposure_ms, frame.data.shape)
        if dark.shape != frame.data.shape:
            raise ValueError(f"master dark has shape {dark.shape} but the frame has "
                             f"{frame.data.shape}; use darks of the same sensor region")
        return frame.replace(data=frame.data - dark,
                             meta={"dark_subtracted": True, "dark_source": how})
