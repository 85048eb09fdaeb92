"""Wavelength grids shared by the spectral modules."""

from __future__ import annotations

import numpy as np

#: Default wavelength grid: 400 to 1000 nm inclusive at 1 nm (601 samples), the range and step of
#: IMEC factory calibrations and of silicon sensors' useful response.
DEFAULT_GRID = np.arange(400.0, 1001.0, 1.0)
DEFAULT_GRID.setflags(write=False)


def readonly(a) -> np.ndarray:
    """A float64 copy of ``a`` that cannot be written to (safe to keep in frozen dataclasses)."""
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def as_grid(wavelengths_nm, what: str = "wavelengths_nm") -> np.ndarray:
    """Validate a wavelength grid: 1-D, finite, at least 2 samples, strictly increasing (nm)."""
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError(f"{what} must be a 1-D array of at least 2 wavelengths in nm, "
                         f"got shape {wl.shape}")
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ValueError(f"{what} must be finite and strictly increasing (nm)")
    return wl


def trapezoid_weights(wavelengths_nm) -> np.ndarray:
    """Weights ``w`` (nm) such that ``w @ f`` is the trapezoid integral of ``f`` over the grid."""
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    d = np.diff(wl)
    w = np.zeros_like(wl)
    w[:-1] += d / 2
    w[1:] += d / 2
    return w


def uniform_step(wavelengths_nm) -> float | None:
    """The step of a uniformly spaced grid (nm), or None when the spacing is not uniform."""
    d = np.diff(np.asarray(wavelengths_nm, dtype=np.float64))
    if d.size and np.allclose(d, d[0], rtol=0, atol=1e-9 * max(1.0, abs(d[0]))):
        return float(d[0])
    return None


def per_band(value, n: int, what: str) -> np.ndarray:
    """Broadcast a scalar or length-``n`` sequence to a float array of ``n`` values."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        return np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"{what} must be a scalar or have one value per band ({n}), "
                         f"got shape {a.shape}")
    return a.copy()
