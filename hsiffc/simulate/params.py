"""The simulated sensor's parameters, its ground truth and captures, the default 8-band
sensor and the paper's light levels (see :mod:`hsiffc.simulate`)."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..leakage import model
from ..data.mosaic import Mosaic
from ..spectral import BandSet, electron_rate, lamp, paper_8band

__all__ = ["SensorParams", "Truth", "Capture", "PAPER_LIGHT_W_M2", "DEFAULT_BAND_BALANCE",
           "default_bands", "default_mosaic"]


@dataclass(frozen=True)
class SensorParams:
    """Physical parameters of the simulated sensor (units in the names).

    The leakage amplitude is given as the leakage rate at a reference level,
    ``leak_rate_dn_per_ms`` at ``leak_ref_dn`` (the paper's Fig. 4/5: 2 DN/ms at 800 DN), so
    ``a = leak_rate * exp(-b * leak_ref)``.
    """

    bit_depth: int = 10
    pixel_pitch_um: float = 5.5  # CMV2000
    conversion_gain_dn_per_e: float = 0.075  # 13.5 ke- full well over ~1000 DN
    full_well_e: float = 13500.0
    read_noise_dn: float = 1.0
    dark_level_dn: float = 32.0
    dsnu_dn: float = 2.0
    prnu: float = 0.01  # relative std of the light sensitivity
    dark_current_dn_per_ms: float = 0.01
    dark_current_spread: float = 0.3  # relative (log-normal sigma)
    leak_b_per_dn: float = 0.0125
    leak_b_spread: float = 0.03  # relative std
    leak_rate_dn_per_ms: float = 2.0
    leak_ref_dn: float = 800.0
    leak_a_spread: float = 0.2  # log-normal sigma of a
    hot_fraction: float = 0.0
    hot_dark_current_dn_per_ms: float = 2.0
    dead_fraction: float = 0.0

    @property
    def full_scale_dn(self) -> int:
        """``2**bit_depth - 1`` (DN)."""
        return 2 ** int(self.bit_depth) - 1

    @property
    def leak_a_dn_per_ms(self) -> float:
        """Leakage amplitude a (DN/ms) implied by the reference rate and level."""
        return float(self.leak_rate_dn_per_ms * np.exp(-self.leak_b_per_dn * self.leak_ref_dn))


#: Irradiances (W/m^2 over 400-1000 nm) that reproduce the paper's light levels on the default
#: 8-band sensor: ``training`` (lamp A, 2900 K, band 1 median k 30 DN/ms: alpha near 37 % at
#: 32.25 ms as in Table I), ``fig5`` (lamp B, 2200 K, band 1 k 2 DN/ms as in Fig. 5) and ``test``
#: (lamp B, k 25 DN/ms in the brightest band: about 400 DN at the 16.125 ms test exposure of
#: Table II with every band unsaturated; the paper does not give its test level).
class LazyLevels(Mapping):
    """Read-only mapping computed on first use (keeps ``import hsiffc.simulate`` fast)."""

    def __init__(self, compute):
        self._compute = compute
        self._values = None

    def _get(self):
        if self._values is None:
            self._values = self._compute()
        return self._values

    def __getitem__(self, key):
        return self._get()[key]

    def __iter__(self):
        return iter(self._get())

    def __len__(self):
        return len(self._get())

    def __repr__(self):
        return repr(dict(self))


PAPER_LIGHT_W_M2: Mapping[str, float] = None  # type: ignore[assignment]  # set at module end


@dataclass(frozen=True, eq=False)
class Truth:
    """Per-pixel ground truth of a capture (all (H, W) float64 unless stated)."""

    k_dn_per_ms: np.ndarray  # light rate from the illumination (dark current excluded)
    dark_current_dn_per_ms: np.ndarray
    a_dn_per_ms: np.ndarray
    b_per_dn: np.ndarray
    dark_dn: np.ndarray  # level at t = 0
    hot: np.ndarray  # bool
    dead: np.ndarray  # bool
    band: np.ndarray  # int band index

    @property
    def k_total_dn_per_ms(self) -> np.ndarray:
        """Rate that drives the ODE: light plus dark current."""
        return self.k_dn_per_ms + self.dark_current_dn_per_ms

    def expected_dn(self, exposure_ms: float) -> np.ndarray:
        """Noise-free model response (DN) before full-well and ADC clipping."""
        return model.response(exposure_ms, self.k_total_dn_per_ms, self.a_dn_per_ms,
                              self.b_per_dn, self.dark_dn)


@dataclass(frozen=True, eq=False)
class Capture:
    """Raw frames of one exposure and the ground truth that produced them."""

    frames: np.ndarray  # (n, H, W) uint16 raw DN
    exposure_ms: float
    illumination: str
    truth: Truth
    expected_dn: np.ndarray  # (H, W) noise-free mean response, after full-well clipping
    mosaic: Mosaic | None = None
    bit_depth: int = 10

    def to_frames(self, kind: str | None = None) -> list:
        """The frames as :class:`hsiffc.data.frame.Frame` objects (kind "light" or "dark": by
        default "dark" when there was no light)."""
        from ..data.frame import Frame

        kind = kind or ("light" if self.illumination else "dark")
        return [Frame.from_raw(f, exposure_ms=self.exposure_ms, bit_depth=self.bit_depth,
                               mosaic=self.mosaic, kind=kind, illumination=self.illumination)
                for f in self.frames]


#: Relative light rate of the default sensor's 8 bands under lamp A (2900 K). The paper's Table I
#: shows bands 1-3 leaking at similar exposures, band 2 and 3 slightly sooner; a real filter set
#: is balanced in the same way by choosing each band's width and transmission.
DEFAULT_BAND_BALANCE = (1.00, 1.06, 1.10, 0.97, 1.03, 0.94, 1.08, 0.99)


@functools.cache
def default_bands() -> BandSet:
    """The default sensor's 8 Fabry-Perot bands (470-890 nm, FWHM 25 nm), with per-band peak QE
    (at most 0.45) chosen so that lamp A gives the light rates in :data:`DEFAULT_BAND_BALANCE`."""
    unit = paper_8band(peak_qe=1.0)
    illum = lamp("lamp A", 1.0, wavelengths_nm=unit.wavelengths_nm)
    rate = np.asarray(electron_rate(illum, unit, pixel_pitch_um=1.0))
    qe = np.asarray(DEFAULT_BAND_BALANCE) / rate
    return paper_8band(peak_qe=0.45 * qe / qe.max(), name="hsiffc default 8-band (470-890 nm)")


def default_mosaic(bands: BandSet) -> Mosaic:
    n = bands.n_bands
    rows = int(np.floor(np.sqrt(n)))
    while n % rows:
        rows -= 1
    cols = n // rows
    return Mosaic(np.arange(n).reshape(rows, cols), wavelengths_nm=tuple(bands.centres_nm),
                  name=f"{cols}x{rows}")  # width x height, as --mosaic


def paper_light_levels() -> dict:
    """Irradiances of the paper's light levels on the default sensor (see PAPER_LIGHT_W_M2).

    Light rates (DN/ms) before PRNU: fig5 2 in band 1 (lamp B), training 30 in band 1
    (lamp A), test 25 in the brightest band (lamp B; about 400 DN at 16.125 ms).
    """
    p = SensorParams()
    bands = default_bands()
    per_w = {}
    for key, name in (("lamp B", "lamp B"), ("lamp A", "lamp A")):
        illum = lamp(name, 1.0, wavelengths_nm=bands.wavelengths_nm)
        rate = np.asarray(electron_rate(illum, bands, pixel_pitch_um=p.pixel_pitch_um))
        per_w[key] = float(rate[0] * p.conversion_gain_dn_per_e)  # DN/ms per W/m^2, band 1
        per_w[key + " max"] = float(rate.max() * p.conversion_gain_dn_per_e)
    levels = {"fig5": 2.0 / per_w["lamp B"], "training": 30.0 / per_w["lamp A"],
              "test": 25.0 / per_w["lamp B max"]}
    # 12 significant digits: the spectral integrals' last bit depends on the CPU's SIMD width,
    # and files written with these levels (the sample cubes) must be identical on every machine
    return {key: float(f"{value:.12g}") for key, value in levels.items()}


PAPER_LIGHT_W_M2 = LazyLevels(paper_light_levels)
