"""Illumination spectra (blackbody lamps, CIE illuminants) scaled to an absolute irradiance.

colour-science is imported lazily: ``import hsiffc`` stays fast.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .grid import DEFAULT_GRID, as_grid, readonly, trapezoid_weights, uniform_step

#: The paper's lamps: "lamp A" (training) and "lamp B" (test) as blackbody colour temperatures.
PAPER_LAMPS_K = {"lamp A": 2900.0, "lamp B": 2200.0}


@dataclass(frozen=True, eq=False)
class Illumination:
    """Light falling on the scene (or on the sensor, for a flat field).

    Parameters
    ----------
    label : str
    wavelengths_nm : (L,) float
    spectral_irradiance : (L,) float
        Spectral irradiance in W m^-2 nm^-1 at the centre of the field.
    vignetting : float in [0, 1)
        Fraction of irradiance lost at the corners of the field (0 = uniform); see
        :meth:`spatial_gain`.
    """

    label: str
    wavelengths_nm: np.ndarray
    spectral_irradiance: np.ndarray
    vignetting: float = 0.0

    def __post_init__(self):
        wl = as_grid(self.wavelengths_nm)
        e = np.asarray(self.spectral_irradiance, dtype=np.float64)
        if e.shape != wl.shape:
            raise ValueError(f"spectral_irradiance must have shape {wl.shape} like "
                             f"wavelengths_nm, got {e.shape}")
        if not np.all(np.isfinite(e)) or np.any(e < 0):
            raise ValueError("spectral_irradiance must be finite and >= 0 (W m^-2 nm^-1)")
        v = float(self.vignetting)
        if not (0.0 <= v < 1.0):
            raise ValueError(
                f"vignetting must be in [0, 1) (fraction lost at the corners), got {v}")
        object.__setattr__(self, "label", str(self.label))
        object.__setattr__(self, "wavelengths_nm", readonly(wl))
        object.__setattr__(self, "spectral_irradiance", readonly(e))
        object.__setattr__(self, "vignetting", v)

    def __eq__(self, other):
        if not isinstance(other, Illumination):
            return NotImplemented
        return (self.label == other.label and self.vignetting == other.vignetting
                and np.array_equal(self.wavelengths_nm, other.wavelengths_nm)
                and np.array_equal(self.spectral_irradiance, other.spectral_irradiance))

    __hash__ = None

    @property
    def irradiance_w_m2(self) -> float:
        """Total irradiance over the grid (W m^-2): trapezoid integral of the spectrum."""
        return float(trapezoid_weights(self.wavelengths_nm) @ self.spectral_irradiance)

    def scaled(self, irradiance_w_m2: float) -> "Illumination":
        """The same spectrum scaled so that its integral over the grid is ``irradiance_w_m2``."""
        return Illumination(self.label, self.wavelengths_nm,
                            _scale_to(self.spectral_irradiance, self.wavelengths_nm,
                                      irradiance_w_m2, self.label),
                            self.vignetting)

    def resample(self, wavelengths_nm) -> "Illumination":
        """Linear interpolation onto another grid (zero outside); the absolute level is kept,
        so the integral changes if the range changes."""
        wl = as_grid(wavelengths_nm)
        e = np.interp(wl, self.wavelengths_nm, self.spectral_irradiance, left=0.0, right=0.0)
        return Illumination(self.label, wl, e, self.vignetting)

    def spatial_gain(self, shape) -> np.ndarray:
        """(H, W) relative irradiance across the field: a cos^4 law, 1 at the centre.

        With ``r`` the distance from the field centre normalised to 1 at the corners, the gain is
        ``cos^4(theta) = 1 / (1 + (t r)^2)^2`` with ``tan(theta) = t r``, and ``t`` chosen so the
        corners receive ``1 - vignetting``. The map is normalised to a maximum of exactly 1.
        """
        h, w = int(shape[0]), int(shape[1])
        if h < 1 or w < 1:
            raise ValueError(f"shape must be (H, W) with H, W >= 1, got {shape!r}")
        if self.vignetting == 0.0:
            return np.ones((h, w))
        y = np.arange(h) - (h - 1) / 2.0
        x = np.arange(w) - (w - 1) / 2.0
        half_diag = np.hypot((h - 1) / 2.0, (w - 1) / 2.0)
        if half_diag == 0:
            return np.ones((h, w))
        r2 = (y[:, None] ** 2 + x[None, :] ** 2) / half_diag ** 2
        t2 = (1.0 - self.vignetting) ** -0.5 - 1.0
        g = 1.0 / (1.0 + t2 * r2) ** 2
        return g / g.max()

    def to_dict(self) -> dict:
        """JSON-safe description; :meth:`from_dict` inverts it."""
        return {"label": self.label, "wavelengths_nm": self.wavelengths_nm.tolist(),
                "spectral_irradiance": self.spectral_irradiance.tolist(),
                "vignetting": self.vignetting}

    @classmethod
    def from_dict(cls, d: dict) -> "Illumination":
        """The Illumination described by :meth:`to_dict`'s output."""
        try:
            return cls(d["label"], np.asarray(d["wavelengths_nm"], dtype=np.float64),
                       np.asarray(d["spectral_irradiance"], dtype=np.float64),
                       float(d.get("vignetting", 0.0)))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"illumination description is missing or has a bad field: {exc!r}; "
                             "expected keys label, wavelengths_nm, spectral_irradiance") from exc


def _scale_to(spectrum, wl, irradiance_w_m2, label) -> np.ndarray:
    target = float(irradiance_w_m2)
    if not np.isfinite(target) or target < 0:
        raise ValueError(f"irradiance_w_m2 must be finite and >= 0, got {irradiance_w_m2!r}")
    total = float(trapezoid_weights(wl) @ spectrum)
    if total <= 0:
        raise ValueError(f"{label}: the spectrum has no power on {wl[0]:g}-{wl[-1]:g} nm, "
                         "cannot scale it to an irradiance")
    return np.asarray(spectrum, dtype=np.float64) * (target / total)


def _planck_relative(wl_nm: np.ndarray, cct_k: float) -> np.ndarray:
    """Planck spectral radiance (arbitrary units) via colour-science, on any grid."""
    import colour

    step = uniform_step(wl_nm)
    if step is not None:
        shape = colour.SpectralShape(float(wl_nm[0]), float(wl_nm[-1]), step)
        sd = colour.sd_blackbody(float(cct_k), shape)
        values = np.asarray(sd.values, dtype=np.float64)
        if values.shape == wl_nm.shape:
            return values
    return np.asarray(colour.colorimetry.planck_law(wl_nm * 1e-9, float(cct_k)), dtype=np.float64)


def blackbody(cct_k: float, irradiance_w_m2: float, *, wavelengths_nm=DEFAULT_GRID,
              vignetting: float = 0.0, label: str | None = None) -> Illumination:
    """A blackbody (incandescent / halogen lamp) of colour temperature ``cct_k``.

    Shape from ``colour.sd_blackbody`` (Planck's law); scaled so that its integral over
    ``wavelengths_nm`` (default 400-1000 nm) is ``irradiance_w_m2`` W m^-2.
    """
    t = float(cct_k)
    if not np.isfinite(t) or t <= 0:
        raise ValueError(f"cct_k must be a positive temperature in kelvin, got {cct_k!r}")
    wl = as_grid(wavelengths_nm)
    label = label if label is not None else f"blackbody {t:g} K"
    spectrum = _planck_relative(wl, t)
    return Illumination(label, wl, _scale_to(spectrum, wl, irradiance_w_m2, label), vignetting)


# -- CIE illuminants -------------------------------------------------------------------------------

def cie_illuminant_names() -> tuple[str, ...]:
    """Names accepted by :func:`cie_illuminant` (colour-science's ``SDS_ILLUMINANTS``)."""
    import colour

    return tuple(colour.SDS_ILLUMINANTS.keys())


def _resolve_cie_name(name: str) -> str:
    names = cie_illuminant_names()
    key = str(name).strip()
    m = re.fullmatch(r"[Ff](\d+(?:\.\d+)?)", key)      # "F2" -> "FL2" (older CIE spelling)
    if m:
        key = "FL" + m.group(1)
    for n in names:
        if n.lower() == key.lower():
            return n
    raise ValueError(f"unknown CIE illuminant {name!r}; valid names: {', '.join(names)}")


@lru_cache(maxsize=64)
def _illuminant_cct(name: str) -> float:
    import colour

    ccs = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]
    if name in ccs:
        xy = np.asarray(ccs[name], dtype=np.float64)
    else:
        sd = colour.SDS_ILLUMINANTS[name]
        xy = colour.XYZ_to_xy(colour.sd_to_XYZ(sd))
    cct = float(colour.xy_to_CCT(xy, method="McCamy 1992"))
    return float(np.clip(cct, 1000.0, 25000.0))


def _cie_relative(name: str, wl: np.ndarray) -> np.ndarray:
    """Relative spectral power of a CIE illuminant on ``wl``, extrapolated outside its table."""
    import colour

    if name == "A":      # defined by formula at every wavelength
        shape = colour.SpectralShape(float(np.floor(wl[0])), float(np.ceil(wl[-1])), 1.0)
        sd = colour.colorimetry.sd_CIE_standard_illuminant_A(shape)
        return np.interp(wl, sd.wavelengths, sd.values)
    sd = colour.SDS_ILLUMINANTS[name]
    lo, hi = float(sd.wavelengths[0]), float(sd.wavelengths[-1])
    out = np.empty_like(wl)
    inside = (wl >= lo) & (wl <= hi)
    if inside.any():
        out[inside] = np.asarray(sd[wl[inside]], dtype=np.float64)   # colour's interpolator
    outside = ~inside
    if outside.any():
        if name == "E":
            out[outside] = float(sd.values[0])
        else:
            # Blackbody tail at the illuminant's correlated colour temperature, joined to the
            # mean of the 3 table samples at each end (a smooth, physically plausible continuation).
            cct = _illuminant_cct(name)
            tw, tv = np.asarray(sd.wavelengths, float), np.asarray(sd.values, float)
            tail = np.asarray(colour.colorimetry.planck_law(wl[outside] * 1e-9, cct), float)
            ends_lo = colour.colorimetry.planck_law(tw[:3] * 1e-9, cct)
            ends_hi = colour.colorimetry.planck_law(tw[-3:] * 1e-9, cct)
            k_lo = tv[:3].mean() / np.mean(ends_lo)
            k_hi = tv[-3:].mean() / np.mean(ends_hi)
            out[outside] = np.where(wl[outside] < lo, k_lo, k_hi) * tail
    return np.clip(out, 0.0, None)


def cie_illuminant(name: str, irradiance_w_m2: float, *, wavelengths_nm=DEFAULT_GRID,
                   vignetting: float = 0.0, label: str | None = None) -> Illumination:
    """A CIE illuminant from ``colour.SDS_ILLUMINANTS`` (A, D65, FL2, LED-B1, ...).

    Names are case-insensitive; ``F<n>`` is accepted for ``FL<n>``. Inside the tabulated range
    the table is interpolated with colour-science's interpolator. The tables stop at 780-830 nm
    (300-380 nm at the blue end); outside them:

    * A is computed from its defining formula (a 2856 K Planckian) at every wavelength;
    * E stays constant;
    * every other illuminant is continued with a blackbody of its correlated colour temperature
      (McCamy's approximation from its CIE 1931 chromaticity), scaled to the mean of the last
      three table samples. For fluorescent and LED sources the tail is therefore near zero, as
      it should be; emission lines beyond the table (e.g. sodium at 819 nm) are not modelled.

    Scaled so that the integral over ``wavelengths_nm`` (default 400-1000 nm) is
    ``irradiance_w_m2`` W m^-2.
    """
    key = _resolve_cie_name(name)
    wl = as_grid(wavelengths_nm)
    label = label if label is not None else f"CIE {key}"
    return Illumination(label, wl, _scale_to(_cie_relative(key, wl), wl, irradiance_w_m2, label),
                        vignetting)


# -- lamp specifications ---------------------------------------------------------------------------

_KELVIN = re.compile(r"\s*(\d+(?:\.\d*)?)\s*[kK]\s*")
_PAPER = re.compile(r"\s*lamp\s*([abAB])\s*", re.IGNORECASE)


def lamp(spec: str, irradiance_w_m2: float, *, wavelengths_nm=DEFAULT_GRID,
         vignetting: float = 0.0, label: str | None = None) -> Illumination:
    """An illumination from a short text specification.

    * ``"2200K"``, ``"2900 K"``: a blackbody of that colour temperature;
    * ``"lamp A"``: the paper's training lamp, a 2900 K blackbody;
    * ``"lamp B"``: the paper's test lamp, a 2200 K blackbody;
    * a CIE illuminant name (``"A"``, ``"D65"``, ``"FL2"``, ...): see :func:`cie_illuminant`.
      Note that ``"A"`` (CIE illuminant A, 2856 K) is not ``"lamp A"`` (2900 K).

    Scaled so that the integral over ``wavelengths_nm`` (default 400-1000 nm) is
    ``irradiance_w_m2`` W m^-2.
    """
    if not isinstance(spec, str):
        raise TypeError(f"lamp spec must be a string such as '2900K', 'lamp A' or 'D65', "
                        f"got {type(spec).__name__}")
    opts = dict(wavelengths_nm=wavelengths_nm, vignetting=vignetting)
    m = _KELVIN.fullmatch(spec)
    if m:
        t = float(m.group(1))
        return blackbody(t, irradiance_w_m2, label=label or f"{t:g} K blackbody", **opts)
    m = _PAPER.fullmatch(spec)
    if m:
        key = f"lamp {m.group(1).upper()}"
        t = PAPER_LAMPS_K[key]
        return blackbody(t, irradiance_w_m2, label=label or f"{key} ({t:g} K blackbody)", **opts)
    try:
        key = _resolve_cie_name(spec)
    except ValueError:
        raise ValueError(
            f"unknown lamp {spec!r}; valid lamps: a colour temperature such as '2200K' or "
            f"'2900 K', 'lamp A' (2900 K), 'lamp B' (2200 K), or a CIE illuminant: "
            f"{', '.join(cie_illuminant_names())}") from None
    return cie_illuminant(key, irradiance_w_m2, label=label, **opts)


def lamp_names() -> tuple[str, ...]:
    """Named lamps accepted by :func:`lamp` (besides any ``'<T>K'`` colour temperature)."""
    return tuple(PAPER_LAMPS_K) + cie_illuminant_names()
