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


def dark_at_cached(cache: dict, exposure_ms: float, d0, slope, keep: int = 4) -> np.ndarray:
    """:func:`dark_at`, kept in ``cache`` for the last ``keep`` exposures (a batch asks for
    the same exposure frame after frame). The result is read-only; an entry is used only
    while ``d0`` and ``slope`` are the very arrays it was computed from."""
    key = float(exposure_ms)
    hit = cache.get(key)
    if hit is not None and hit[0] is d0 and hit[1] is slope:
        return hit[2]
    if key not in cache and len(cache) >= keep:
        cache.pop(next(iter(cache)))
    dark = dark_at(key, d0, slope)
    dark.flags.writeable = False
    cache[key] = (d0, slope, dark)
    return dark
