"""From light to photo-electrons: per-band electron rates and test-chart reflectances."""

from __future__ import annotations

import numpy as np

from .grid import DEFAULT_GRID, as_grid, trapezoid_weights
from .bands import BandSet
from .illumination import Illumination

#: The SI defining constants (exact since the 2019 redefinition of the SI; the values
#: ``scipy.constants`` holds): written here so that importing hsiffc.spectral does not load
#: scipy (0.17 s, on the path of every command that touches the flat field or the calibration).
PLANCK_J_S = 6.62607015e-34
SPEED_OF_LIGHT_M_S = 299792458.0


def electron_rate(illumination: Illumination, bands: BandSet, *, pixel_pitch_um: float,
                  reflectance=None) -> np.ndarray:
    """Photo-electrons per millisecond collected by one pixel of each band.

    ``rate_b = A_pix * integral E(lambda) R(lambda) QE_b(lambda) lambda / (h c) dlambda / 1000``

    with ``E`` the spectral irradiance in W m^-2 nm^-1 (``illumination.spectral_irradiance``),
    ``lambda / (h c)`` photons per joule (lambda in m; the SI's exact h and c), ``QE_b`` the band's
    quantum-efficiency fraction (``bands.responses``), ``R`` the scene reflectance (1 = the
    irradiance reaches the pixel unchanged, as for a flat field), ``A_pix = pixel_pitch_um^2``
    converted to m^2 (100 % fill factor; fold a fill factor or micro-lens gain into the QE), the
    trapezoid rule over the illumination's grid in nm, and /1000 converting s^-1 to ms^-1.
    The result is for the centre of the field: multiply by ``illumination.spatial_gain`` for
    vignetting.

    Parameters
    ----------
    reflectance : None, (L,) or (..., L)
        None means 1. A (L,) spectrum gives (n_bands,); an (M, L) set gives (M, n_bands).
        Spectra must be sampled on the illumination's grid.

    Returns
    -------
    (n_bands,) or (..., n_bands) float, e-/ms/pixel.
    """
    if not isinstance(illumination, Illumination):
        raise TypeError(f"illumination must be an Illumination, got {type(illumination).__name__}")
    if not isinstance(bands, BandSet):
        raise TypeError(f"bands must be a BandSet, got {type(bands).__name__}")
    pitch = float(pixel_pitch_um)
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(f"pixel_pitch_um must be positive (micrometres), got {pixel_pitch_um!r}")
    wl = illumination.wavelengths_nm
    qe = bands.resample(wl).responses                                   # (n_bands, L)
    photons = illumination.spectral_irradiance * (wl * 1e-9) / (PLANCK_J_S * SPEED_OF_LIGHT_M_S)
    kernel = qe * (photons * trapezoid_weights(wl))                     # e- s^-1 m^-2 per band
    scale = (pitch * 1e-6) ** 2 * 1e-3                                  # m^2 per pixel, s -> ms
    if reflectance is None:
        return kernel.sum(axis=1) * scale
    r = np.asarray(reflectance, dtype=np.float64)
    if r.ndim == 0 or r.shape[-1] != wl.size:
        raise ValueError(f"reflectance must have {wl.size} samples on the illumination's "
                         f"grid along its last axis, got shape {r.shape}")
    return (r @ kernel.T) * scale


#: colour-science data set used by :func:`colorchecker_reflectances` by default.
COLORCHECKER_DATASET = "ISO 17321-1"


def colorchecker_reflectances(wavelengths_nm=DEFAULT_GRID, *,
                              dataset: str = COLORCHECKER_DATASET
                              ) -> tuple[np.ndarray, tuple[str, ...]]:
    """Spectral reflectances of the 24 ColorChecker patches, and their names.

    From ``colour.SDS_COLOURCHECKERS[dataset]`` (default "ISO 17321-1", 380-780 nm at 5 nm;
    "ColorChecker N Ohta" and "BabelColor Average" also work). Inside the table the values are
    interpolated with colour-science's interpolator; outside it each patch is held constant at
    the mean of its 3 last (or first) samples. Real patches become more reflective in the NIR, so
    values beyond 780 nm are a conservative stand-in. Clipped to [0, 1].

    Returns
    -------
    reflectances : (24, L) float
    names : tuple of 24 str, in chart order (row by row, "dark skin" first).
    """
    import colour

    wl = as_grid(wavelengths_nm)
    try:
        chart = colour.SDS_COLOURCHECKERS[dataset]
    except KeyError:
        raise ValueError(f"unknown ColorChecker data set {dataset!r}; valid: "
                         f"{', '.join(colour.SDS_COLOURCHECKERS.keys())}") from None
    names = tuple(chart.keys())
    out = np.empty((len(names), wl.size))
    for i, n in enumerate(names):
        sd = chart[n]
        tw, tv = np.asarray(sd.wavelengths, float), np.asarray(sd.values, float)
        inside = (wl >= tw[0]) & (wl <= tw[-1])
        if inside.any():
            out[i, inside] = np.asarray(sd[wl[inside]], dtype=np.float64)
        out[i, wl < tw[0]] = tv[:3].mean()
        out[i, wl > tw[-1]] = tv[-3:].mean()
    return np.clip(out, 0.0, 1.0), names
