"""Spectral band responses of snapshot-mosaic filters, synthetic Fabry-Perot bands and spectral
correction matrices."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .grid import DEFAULT_GRID, as_grid, per_band, readonly, trapezoid_weights


@dataclass(frozen=True, eq=False)
class BandSet:
    """Spectral responses of the bands of a filter mosaic.

    Parameters
    ----------
    wavelengths_nm : (L,) float
        Strictly increasing wavelength grid (nm).
    responses : (n_bands, L) float
        Quantum efficiency of each band as a FRACTION (electrons per incident photon), including
        everything in the optical path of the pixel (sensor QE, the band's filter and any
        rejection / band-pass filter). Measured data may contain small negative values (noise)
        and, for vendor data in relative units, values above 1.
    centres_nm, fwhm_nm : (n_bands,) float
        Nominal centre wavelength and full width at half maximum of each band's main peak.
    name : str
        Free-form label.
    """

    wavelengths_nm: np.ndarray
    responses: np.ndarray
    centres_nm: np.ndarray
    fwhm_nm: np.ndarray
    name: str = ""

    def __post_init__(self):
        wl = as_grid(self.wavelengths_nm)
        r = np.asarray(self.responses, dtype=np.float64)
        if r.ndim == 1:
            r = r[None, :]
        if r.ndim != 2 or r.shape[1] != wl.size or r.shape[0] < 1:
            raise ValueError(f"responses must have shape (n_bands, {wl.size}) to match "
                             f"wavelengths_nm, got {r.shape}")
        if not np.all(np.isfinite(r)):
            raise ValueError("responses must be finite")
        n = r.shape[0]
        c = np.asarray(self.centres_nm, dtype=np.float64).reshape(-1)
        f = np.asarray(self.fwhm_nm, dtype=np.float64).reshape(-1)
        for what, a in (("centres_nm", c), ("fwhm_nm", f)):
            if a.shape != (n,):
                raise ValueError(f"{what} must have one value per band ({n}), got {a.shape}")
        object.__setattr__(self, "wavelengths_nm", readonly(wl))
        object.__setattr__(self, "responses", readonly(r))
        object.__setattr__(self, "centres_nm", readonly(c))
        object.__setattr__(self, "fwhm_nm", readonly(f))
        object.__setattr__(self, "name", str(self.name))

    @property
    def n_bands(self) -> int:
        """Number of bands."""
        return int(self.responses.shape[0])

    def __eq__(self, other):
        if not isinstance(other, BandSet):
            return NotImplemented
        return (self.name == other.name
                and all(np.array_equal(getattr(self, k), getattr(other, k))
                        for k in ("wavelengths_nm", "responses", "centres_nm", "fwhm_nm")))

    __hash__ = None

    def resample(self, wavelengths_nm) -> "BandSet":
        """The same bands on another grid: linear interpolation, zero outside the measured range."""
        wl = as_grid(wavelengths_nm)
        if wl.shape == self.wavelengths_nm.shape and np.array_equal(wl, self.wavelengths_nm):
            return self
        out = np.empty((self.n_bands, wl.size))
        for i, r in enumerate(self.responses):
            out[i] = np.interp(wl, self.wavelengths_nm, r, left=0.0, right=0.0)
        return BandSet(wl, out, self.centres_nm, self.fwhm_nm, self.name)

    def to_dict(self) -> dict:
        """A JSON-safe description (plain lists and floats)."""
        return {
            "name": self.name,
            "wavelengths_nm": self.wavelengths_nm.tolist(),
            "responses": self.responses.tolist(),
            "centres_nm": self.centres_nm.tolist(),
            "fwhm_nm": self.fwhm_nm.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "BandSet":
        """The BandSet described by :meth:`to_dict`'s output."""
        try:
            return cls(np.asarray(d["wavelengths_nm"], dtype=np.float64),
                       np.asarray(d["responses"], dtype=np.float64),
                       np.asarray(d["centres_nm"], dtype=np.float64),
                       np.asarray(d["fwhm_nm"], dtype=np.float64),
                       name=d.get("name", ""))
        except (KeyError, TypeError) as exc:
            raise ValueError(
                f"band set description is missing or has a bad field: {exc!r}; "
                "expected keys wavelengths_nm, responses, centres_nm, fwhm_nm") from exc


# -- synthetic Fabry-Perot bands ------------------------------------------------------------------

def fabry_perot_bands(centres_nm, fwhm_nm, *, peak_qe=0.5, second_order=0.0, order: int = 1,
                      wavelengths_nm=DEFAULT_GRID, name: str = "fabry-perot") -> BandSet:
    """Narrow Fabry-Perot (Airy) band responses with an exact FWHM and optional higher-order lobe.

    Each band is a cavity of interference order ``order`` resonant at its centre: the round-trip
    phase is ``phi(lambda) = pi * order * centre / lambda`` and the Airy transmission is
    ``1 / (1 + F sin^2 phi)``, periodic in ``1 / lambda`` with peaks at ``centre * order / k``
    (k = 1, 2, ...). The response is built period by period: in the period containing peak k the
    Airy function, shifted and rescaled to run from 0 (period edges) to 1 (peak), is multiplied by

    * ``peak_qe`` for the main peak (k = order),
    * ``peak_qe * second_order`` for the next interference order of the same cavity
      (k = order + 1, at ``centre * order / (order + 1)``),
    * 0 for all other orders (absorbed by the sensor or blocked by a rejection filter).

    The finesse coefficient F is solved so that the main peak's FWHM measured in wavelength is
    exactly ``fwhm_nm``. The line shape is Lorentzian-like (long wings), not Gaussian. The
    higher-order lobe has the same finesse, hence a narrower width in nm, as for a real etalon
    with dispersion-free mirrors.

    Parameters
    ----------
    centres_nm : (n_bands,) float
    fwhm_nm, peak_qe, second_order : float or (n_bands,)
        FWHM in nm; peak quantum efficiency as a fraction; relative amplitude of the
        next-order lobe (0 = none).
    order : int >= 1
        Interference order of the main peak.
    wavelengths_nm : (L,) grid, default 400-1000 nm at 1 nm.
    """
    wl = as_grid(wavelengths_nm)
    c = np.asarray(centres_nm, dtype=np.float64).reshape(-1)
    n = c.size
    if n == 0 or not np.all(np.isfinite(c)) or np.any(c <= 0):
        raise ValueError("centres_nm must be a non-empty sequence of positive wavelengths (nm)")
    f = per_band(fwhm_nm, n, "fwhm_nm")
    q = per_band(peak_qe, n, "peak_qe")
    s2 = per_band(second_order, n, "second_order")
    m = int(order)
    if m != order or m < 1:
        raise ValueError(f"order must be a positive integer, got {order!r}")
    if np.any(~np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"fwhm_nm must be positive, got {fwhm_nm!r}")
    if np.any(q < 0) or np.any(s2 < 0):
        raise ValueError("peak_qe and second_order must be >= 0")

    # Half-maximum phase offset x0 giving the requested FWHM in wavelength exactly:
    # half-maximum wavelengths are pi*m*c/(pi*m +- x0), whose difference is fwhm.
    pm = np.pi * m
    x0 = pm * (np.sqrt(c * c + f * f) - c) / f
    s_sq = np.sin(x0) ** 2
    if np.any(s_sq >= 0.5):
        bad = c[s_sq >= 0.5]
        raise ValueError(f"fwhm_nm too wide for an order-{m} cavity at {bad.tolist()} nm "
                         "(it must be well below the free spectral range)")
    finesse_coef = 1.0 / s_sq - 2.0          # normalised Airy: half maximum at sin^2 = 1/(2+F)

    phi = pm * c[:, None] / wl[None, :]      # (n, L) round-trip phase / 2
    k = np.rint(phi / np.pi)                 # interference order of the period
    delta = phi - k * np.pi                  # in [-pi/2, pi/2]
    F = finesse_coef[:, None]
    floor = 1.0 / (1.0 + F)
    airy = (1.0 / (1.0 + F * np.sin(delta) ** 2) - floor) / (1.0 - floor)
    amp = np.where(k == m, 1.0, np.where(k == m + 1, s2[:, None], 0.0))
    responses = q[:, None] * amp * airy
    return BandSet(wl, responses, c, f, name)


def paper_8band(**kwargs) -> BandSet:
    """Eight bands evenly spaced from 470 to 890 nm (60 nm apart), FWHM 25 nm, peak QE 0.35.

    The paper's sensor has 8 bands whose exact centres are not given; this preset spreads them
    evenly over the visible-NIR range a silicon sensor covers. Keyword arguments override
    :func:`fabry_perot_bands` defaults (``fwhm_nm``, ``peak_qe``, ``second_order``, ...).
    """
    opts = dict(fwhm_nm=25.0, peak_qe=0.35, name="paper 8-band (470-890 nm)")
    opts.update(kwargs)
    return fabry_perot_bands(np.linspace(470.0, 890.0, 8), **opts)


def imec_4x4_visible(**kwargs) -> BandSet:
    """Sixteen bands evenly spaced from 470 to 620 nm (10 nm apart), FWHM 12 nm, peak QE 0.3,
    like IMEC's VIS 4x4 snapshot-mosaic sensor."""
    opts = dict(fwhm_nm=12.0, peak_qe=0.3, name="IMEC-like VIS 4x4 (470-620 nm)")
    opts.update(kwargs)
    return fabry_perot_bands(np.linspace(470.0, 620.0, 16), **opts)


def imec_5x5_nir(**kwargs) -> BandSet:
    """Twenty-five bands evenly spaced from 600 to 875 nm (~11.5 nm apart), FWHM 7 nm (the
    median of the real 5x5 calibration is ~6 nm), peak QE 0.3, like IMEC's NIR 5x5 sensor."""
    opts = dict(fwhm_nm=7.0, peak_qe=0.3, name="IMEC-like NIR 5x5 (600-875 nm)")
    opts.update(kwargs)
    return fabry_perot_bands(np.linspace(600.0, 875.0, 25), **opts)


# -- spectral correction ---------------------------------------------------------------------------

def gaussian_responses(centres_nm, fwhm_nm, wavelengths_nm=DEFAULT_GRID, *,
                       peak: float = 1.0) -> np.ndarray:
    """(n, L) Gaussian curves with the given centres and FWHM (nm) and peak value ``peak``."""
    wl = as_grid(wavelengths_nm)
    c = np.asarray(centres_nm, dtype=np.float64).reshape(-1)
    f = per_band(fwhm_nm, c.size, "fwhm_nm")
    if np.any(f <= 0):
        raise ValueError("fwhm_nm must be positive")
    sigma = f / np.sqrt(8.0 * np.log(2.0))
    return peak * np.exp(-0.5 * ((wl[None, :] - c[:, None]) / sigma[:, None]) ** 2)


def spectral_correction_matrix(bands: BandSet, virtual_centres_nm, fwhm_nm, *,
                               regularisation: float = 1e-3,
                               target_peak: float = 1.0) -> np.ndarray:
    """Least-squares correction matrix ``M`` (n_virtual, n_bands) from physical to virtual bands.

    ``M @ bands.responses`` approximates Gaussian virtual bands of the given centres and FWHM
    with peak ``target_peak``; apply it to band signals ordered like ``bands`` as
    ``virtual = M @ b`` (or ``b @ M.T`` for a stack of (..., n_bands) pixels).

    Solves ``min ||M R - G||^2 + lam ||M||^2`` with wavelength integrals taken by the trapezoid
    rule, i.e. ``M = G W R^T (R W R^T + lam I)^-1`` with ``W`` the quadrature weights. The
    Tikhonov parameter is relative: ``lam = regularisation * trace(R W R^T) / n_bands``, so the
    result does not depend on the units of the responses. Larger values trade fidelity of the
    virtual band shape for lower noise amplification (smaller coefficients).
    """
    if not isinstance(bands, BandSet):
        raise TypeError(f"bands must be a BandSet, got {type(bands).__name__}")
    if not np.isfinite(regularisation) or regularisation < 0:
        raise ValueError(f"regularisation must be >= 0, got {regularisation!r}")
    R = bands.responses
    G = gaussian_responses(virtual_centres_nm, fwhm_nm, bands.wavelengths_nm, peak=target_peak)
    w = trapezoid_weights(bands.wavelengths_nm)
    A = (R * w) @ R.T                       # (n_bands, n_bands) Gram matrix
    B = (G * w) @ R.T                       # (n_virtual, n_bands)
    lam = regularisation * np.trace(A) / R.shape[0]
    A = A + lam * np.eye(R.shape[0])
    # M A = B, A symmetric  ->  A M^T = B^T
    try:
        return np.linalg.solve(A, B.T).T
    except np.linalg.LinAlgError:
        return B @ np.linalg.pinv(A, hermitian=True)
