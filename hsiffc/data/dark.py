"""Dark subtraction (array functions): master darks, their exposure dependence, subtraction.

A dark is the response without light: a level at zero exposure plus a dark current that grows
with the exposure, ``dark(t) = d0 + slope * t`` (DN, t in ms). Raw DN stay DN: subtraction
never clips or rescales.
"""

from __future__ import annotations

import numpy as np


def subtract_dark(data, dark) -> np.ndarray:
    """``data - dark`` in float32 (DN in, DN out; negative values are kept, not clipped).

    Parameters
    ----------
    data : (..., H, W) array_like, DN
    dark : (H, W) array_like, DN

    Returns
    -------
    (..., H, W) float32

    Examples
    --------
    >>> subtract_dark(np.array([[10, 3]]), np.array([[4.5, 4.0]]))
    array([[ 5.5, -1. ]], dtype=float32)
    """
    data = np.asarray(data)
    dark = np.asarray(dark)
    if dark.shape != data.shape[-2:]:
        raise ValueError(f"dark has shape {dark.shape} but frames have {data.shape[-2:]}; use "
                         "a dark from the same sensor region and binning")
    return np.subtract(data, dark, dtype=np.float32)


def fit_dark_line(exposures_ms, masters) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel least-squares line ``d0 + slope * t`` through master darks.

    Parameters
    ----------
    exposures_ms : (E,) array_like, ms (E >= 2 distinct values)
    masters : (E, H, W) array_like, DN

    Returns
    -------
    d0 : (H, W) float32, DN (the dark level at zero exposure)
    slope : (H, W) float32, DN/ms (the dark current)
    """
    t = np.asarray(exposures_ms, np.float64)
    y = np.asarray(masters, np.float64)
    if t.ndim != 1 or y.shape[:1] != t.shape or np.unique(t).size < 2:
        raise ValueError(f"a dark line needs masters at two or more exposures; got exposures "
                         f"{t.tolist()} for masters of shape {y.shape}")
    tm = t.mean()
    slope = np.tensordot(t - tm, y - y.mean(axis=0), axes=(0, 0)) / ((t - tm) ** 2).sum()
    return (y.mean(axis=0) - slope * tm).astype(np.float32), slope.astype(np.float32)


def dark_at(exposure_ms: float, d0, slope) -> np.ndarray:
    """The dark (DN, float32) at one exposure: ``d0 + slope * exposure_ms``.

    Parameters
    ----------
    exposure_ms : float, ms
    d0 : (H, W) array_like, DN
    slope : (H, W) array_like, DN/ms
    """
    return np.asarray(d0, np.float32) + np.asarray(slope, np.float32) * np.float32(exposure_ms)


class DarkLine:
    """A dark that grows with the exposure, ``d0 + slope * t`` (:func:`dark_at`), as one object:
    the two planes in float32 and the darks of the last :attr:`keep` exposures asked for, in
    :attr:`recent` (a batch asks for the same exposure frame after frame).

    Made once where a correction is prepared (a pipeline's dark stage, a prepared
    calibration: :class:`hsiffc.calibrate.prepared.PreparedCalibration`) and held there in
    plain view.

    Parameters
    ----------
    d0 : (H, W) array_like, DN
        Dark level at zero exposure.
    slope : (H, W) array_like, DN/ms
        Dark current.
    keep : int
        How many exposures :attr:`recent` keeps (oldest dropped first).

    Examples
    --------
    >>> line = DarkLine(np.array([[10.0]]), np.array([[0.5]]))
    >>> line.at(4.0).tolist(), list(line.recent)
    ([[12.0]], [4.0])
    """

    def __init__(self, d0, slope, keep: int = 4):
        self.d0 = np.asarray(d0, np.float32)
        self.slope = np.asarray(slope, np.float32)
        self.keep = int(keep)
        #: exposure (ms) -> its dark (read-only float32), the last :attr:`keep` asked for
        self.recent: dict[float, np.ndarray] = {}

    def __repr__(self) -> str:
        return (f"<DarkLine {' x '.join(map(str, self.d0.shape))} px, darks kept at "
                f"{sorted(self.recent)} ms>")

    def at(self, exposure_ms: float) -> np.ndarray:
        """The dark (DN, float32, read-only) at ``exposure_ms``: :func:`dark_at`, taken from
        :attr:`recent` when this exposure was asked for lately."""
        key = float(exposure_ms)
        dark = self.recent.get(key)
        if dark is None:
            if len(self.recent) >= self.keep:
                self.recent.pop(next(iter(self.recent)))
            dark = dark_at(key, self.d0, self.slope)
            dark.flags.writeable = False
            self.recent[key] = dark
        return dark
