"""A simulator of a CMOS snapshot-mosaic spectral sensor whose pixels follow the leakage model.

Light (a colour-science lamp spectrum, optionally with vignetting and target reflectances) is
turned into photo-electrons per band, into a per-pixel light rate ``k`` (DN/ms) through the
band responses, the pixel's PRNU and the conversion gain, and then into a raw response by the
closed form of ``dY/dt = k - a e^{bY}`` starting from the pixel's dark level. Temporal noise
(shot noise on the collected electrons, read noise), full-well clipping, quantisation and clipping
at full scale follow. The fixed pattern (dark level with DSNU, PRNU, leakage a and b with spread,
dark current, hot and dead pixels) is drawn once from the sensor's seed and returned as ground
truth with every capture.

Defaults reproduce the paper's sensor (Liu et al.; see ``shared/reference/README.md``): 10 bit,
k about 2 DN/ms under lamp B at the Fig. 5 light level with a dynamic saturation near 800 DN and a
leakage of 2 DN/ms at 800 DN, and under the training lamp A an alpha that grows over
6.45-32.25 ms roughly as in Table I.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace

import numpy as np

from . import model
from .mosaic import Mosaic
from .spectral import BandSet, Illumination, electron_rate, lamp, paper_8band
from .sweep import Sweep

__all__ = ["SensorParams", "Truth", "Capture", "MosaicSensor", "PAPER_LIGHT_W_M2"]


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
class _LazyLevels(Mapping):
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
        """The frames as :class:`hsiffc.frame.Frame` objects (kind "light" or "dark": by
        default "dark" when there was no light)."""
        from .frame import Frame

        kind = kind or ("light" if self.illumination else "dark")
        return [Frame.from_raw(f, exposure_ms=self.exposure_ms, bit_depth=self.bit_depth,
                               mosaic=self.mosaic, kind=kind, illumination=self.illumination)
                for f in self.frames]


class MosaicSensor:
    """A simulated snapshot-mosaic sensor with a fixed pattern drawn from ``seed``.

    Parameters
    ----------
    shape : (H, W)
    mosaic : Mosaic, optional
        Default: the paper's 8-band sensor as a 2 x 4 tile.
    bands : BandSet, optional
        Band responses, one per mosaic band. Default: :func:`hsiffc.spectral.paper_8band`.
    params : SensorParams, optional
    seed : int
        Seeds the fixed pattern and, unless a capture is given its own seed, the temporal noise.

    Examples
    --------
    >>> sensor = MosaicSensor((16, 16), seed=1)
    >>> cap = sensor.capture(10.0, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["fig5"], n_frames=2)
    >>> cap.frames.shape, cap.frames.dtype.name
    ((2, 16, 16), 'uint16')
    """

    def __init__(self, shape=(64, 64), *, mosaic: Mosaic | None = None,
                 bands: BandSet | None = None, params: SensorParams | None = None, seed: int = 0):
        self.shape = (int(shape[0]), int(shape[1]))
        if min(self.shape) < 1:
            raise ValueError(f"shape must be positive (H, W), got {shape}")
        self.bands = bands if bands is not None else default_bands()
        if mosaic is None:
            mosaic = _default_mosaic(self.bands)
        if mosaic.n_bands != self.bands.n_bands:
            raise ValueError(f"mosaic has {mosaic.n_bands} bands but the band set has "
                             f"{self.bands.n_bands}; give one band response per mosaic band")
        self.mosaic = mosaic
        self.params = params if params is not None else SensorParams()
        self.seed = int(seed)
        fp_seq, noise_seq = np.random.SeedSequence(self.seed).spawn(2)
        self._noise_rng = np.random.default_rng(noise_seq)
        self._draw_fixed_pattern(np.random.default_rng(fp_seq))

    # -- fixed pattern -------------------------------------------------------------------------
    def _draw_fixed_pattern(self, rng):
        p, shape = self.params, self.shape
        self.band_map = self.mosaic.band_map(shape)
        self.dark_dn = p.dark_level_dn + p.dsnu_dn * rng.standard_normal(shape)
        self.gain = np.clip(1.0 + p.prnu * rng.standard_normal(shape), 0.0, None)
        self.b_per_dn = p.leak_b_per_dn * np.clip(1.0 + p.leak_b_spread * rng.standard_normal(shape),
                                                  0.05, None)
        # a spreads log-normally around the value giving leak_rate at leak_ref for this pixel's b
        self.a_dn_per_ms = (p.leak_rate_dn_per_ms * np.exp(-self.b_per_dn * p.leak_ref_dn)
                            * np.exp(p.leak_a_spread * rng.standard_normal(shape)))
        self.dark_current = p.dark_current_dn_per_ms * np.exp(
            p.dark_current_spread * rng.standard_normal(shape) - 0.5 * p.dark_current_spread ** 2)
        u = rng.random(shape)
        self.hot = u < p.hot_fraction
        self.dead = (u >= p.hot_fraction) & (u < p.hot_fraction + p.dead_fraction)
        self.dark_current = np.where(self.hot, p.hot_dark_current_dn_per_ms, self.dark_current)
        self.gain = np.where(self.dead, 0.0, self.gain)

    # -- light ---------------------------------------------------------------------------------
    def illumination(self, spec, irradiance_w_m2: float, *, vignetting: float = 0.0) -> Illumination:
        """Build an :class:`Illumination` on this sensor's wavelength grid."""
        if isinstance(spec, Illumination):
            return spec
        return lamp(spec, irradiance_w_m2, wavelengths_nm=self.bands.wavelengths_nm,
                    vignetting=vignetting)

    def light_rate(self, illumination, *, irradiance_w_m2: float | None = None,
                   reflectance=None, vignetting: float = 0.0) -> np.ndarray:
        """Per-pixel light rate k (DN/ms) under an illumination, dark current excluded.

        ``reflectance`` is None (a white target), one spectrum (L,) for the whole scene, or
        ``(labels, spectra)`` with an (H, W) int label map into (M, L) spectra.
        """
        illum = self._illum(illumination, irradiance_w_m2, vignetting)
        g = self.params.conversion_gain_dn_per_e
        pitch = self.params.pixel_pitch_um
        if reflectance is None or (not isinstance(reflectance, tuple)):
            per_band = electron_rate(illum, self.bands, pixel_pitch_um=pitch,
                                     reflectance=reflectance)  # (n_bands,)
            k = np.asarray(per_band)[self.band_map]
        else:
            labels, spectra = reflectance
            labels = np.asarray(labels)
            if labels.shape != self.shape:
                raise ValueError(f"reflectance label map has shape {labels.shape}, "
                                 f"expected the sensor shape {self.shape}")
            table = np.asarray(electron_rate(illum, self.bands, pixel_pitch_um=pitch,
                                             reflectance=np.atleast_2d(spectra)))  # (M, n_bands)
            k = table[labels, self.band_map]
        return k * g * self.gain * illum.spatial_gain(self.shape)

    def _illum(self, illumination, irradiance_w_m2, vignetting):
        if isinstance(illumination, Illumination):
            return illumination
        if irradiance_w_m2 is None:
            raise ValueError("irradiance_w_m2 is required when the illumination is given by name "
                             f"({illumination!r}); e.g. PAPER_LIGHT_W_M2['fig5']")
        return self.illumination(illumination, irradiance_w_m2, vignetting=vignetting)

    def truth(self, k_dn_per_ms: np.ndarray) -> Truth:
        """Per-pixel ground truth for light rates ``k_dn_per_ms`` (H, W), DN/ms."""
        return Truth(k_dn_per_ms=k_dn_per_ms, dark_current_dn_per_ms=self.dark_current,
                     a_dn_per_ms=self.a_dn_per_ms, b_per_dn=self.b_per_dn, dark_dn=self.dark_dn,
                     hot=self.hot, dead=self.dead, band=self.band_map)

    # -- capture -------------------------------------------------------------------------------
    def capture(self, exposure_ms: float, illumination=None, *, irradiance_w_m2: float | None = None,
                n_frames: int = 1, reflectance=None, vignetting: float = 0.0,
                seed: int | None = None, label: str | None = None) -> Capture:
        """Raw integer frames at one exposure.

        ``illumination`` None (or irradiance 0) captures dark frames. Returns a :class:`Capture`
        with ``frames`` (n_frames, H, W) uint16 and the per-pixel ground truth. ``label``
        replaces the illumination's label (e.g. to tell light levels of one lamp apart).

        Parameters
        ----------
        exposure_ms : float
            Exposure time (ms).
        illumination : str or Illumination, optional
            A lamp (``"lamp A"``, ``"2200K"``, a CIE illuminant name...) or None for darks.
        irradiance_w_m2 : float, optional
            Irradiance at the sensor (W/m^2); required when ``illumination`` is a name (e.g.
            ``PAPER_LIGHT_W_M2["test"]``).
        n_frames : int
            Frames to capture (independent noise).
        reflectance : callable or array, optional
            Scene reflectance (per pixel or per wavelength) in front of the lamp.
        vignetting : float
            Relative light fall-off at the corners (0: uniform, as an integrating sphere).
        seed : int, optional
            Seeds the noise (the fixed pattern is the sensor's own).
        label : str, optional

        Returns
        -------
        Capture

        Examples
        --------
        >>> sensor = MosaicSensor((8, 8), seed=1)
        >>> cap = sensor.capture(16.125, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"],
        ...                      n_frames=2, seed=3)
        >>> cap.frames.shape, cap.frames.dtype.name
        ((2, 8, 8), 'uint16')
        """
        exposure_ms = float(exposure_ms)
        if not np.isfinite(exposure_ms) or exposure_ms < 0:
            raise ValueError(f"exposure_ms must be finite and >= 0, got {exposure_ms}")
        if int(n_frames) < 1:
            raise ValueError(f"n_frames must be >= 1, got {n_frames}")
        if illumination is None or irradiance_w_m2 == 0:
            k = np.zeros(self.shape)
            label = ""
        else:
            illum = self._illum(illumination, irradiance_w_m2, vignetting)
            k = self.light_rate(illum, reflectance=reflectance)
            label = label or illum.label
        truth = self.truth(k)
        rng = self._noise_rng if seed is None else np.random.default_rng(seed)
        frames, expected = self._expose(truth, exposure_ms, int(n_frames), rng)
        return Capture(frames=frames, exposure_ms=exposure_ms, illumination=label, truth=truth,
                       expected_dn=expected, mosaic=self.mosaic, bit_depth=self.params.bit_depth)

    def _expose(self, truth: Truth, exposure_ms: float, n: int, rng):
        p = self.params
        g = p.conversion_gain_dn_per_e
        mean = truth.expected_dn(exposure_ms)
        electrons = np.clip((mean - truth.dark_dn) / g, 0.0, p.full_well_e)
        expected = truth.dark_dn + electrons * g
        out = np.empty((n,) + self.shape, dtype=np.uint16)
        fs = p.full_scale_dn
        for i in range(n):
            e = rng.poisson(electrons).astype(np.float32)
            np.minimum(e, p.full_well_e, out=e)
            dn = truth.dark_dn.astype(np.float32) + e * np.float32(g)
            dn += np.float32(p.read_noise_dn) * rng.standard_normal(self.shape, dtype=np.float32)
            np.rint(dn, out=dn)
            np.clip(dn, 0, fs, out=dn)
            out[i] = dn
        return out, expected

    def sweep(self, exposures_ms, illumination=None, *, irradiance_w_m2: float | None = None,
              n_frames: int = 2, darks: bool = True, reflectance=None, vignetting: float = 0.0,
              seed: int | None = None, label: str | None = None) -> Sweep:
        """An exposure sweep: for every exposure, ``n_frames`` light frames then (with ``darks``)
        ``n_frames`` dark frames, in that acquisition order. With ``illumination=None`` every
        frame is a dark frame. The ground truth is in
        ``sweep.meta['truth']`` as arrays (not serialised)."""
        rng = self._noise_rng if seed is None else np.random.default_rng(seed)
        frames, exposure, kind, labels = [], [], [], []
        truth = None
        for t in np.atleast_1d(np.asarray(exposures_ms, dtype=np.float64)):
            cap = self.capture(t, illumination, irradiance_w_m2=irradiance_w_m2, n_frames=n_frames,
                               reflectance=reflectance, vignetting=vignetting,
                               seed=int(rng.integers(2 ** 63)), label=label)
            truth = cap.truth
            frames.append(cap.frames)
            exposure += [t] * n_frames
            is_dark = illumination is None or irradiance_w_m2 == 0
            kind += ["dark" if is_dark else "light"] * n_frames
            labels += [cap.illumination] * n_frames
            if darks and not is_dark:
                dcap = self.capture(t, None, n_frames=n_frames, seed=int(rng.integers(2 ** 63)))
                frames.append(dcap.frames)
                exposure += [t] * n_frames
                kind += ["dark"] * n_frames
                labels += [""] * n_frames
        return Sweep(np.concatenate(frames), exposure, kind, self.params.bit_depth,
                     illumination=labels, mosaic=self.mosaic, source="simulated",
                     meta={"simulator": self.describe(), "truth": truth})

    def sweep_varying_light(self, exposures_ms, levels, illumination, *,
                            irradiance_w_m2: float, n_frames: int = 2, darks: bool = True,
                            seed: int | None = None) -> Sweep:
        """An EMVA 1288-style sweep whose light changes from step to step.

        Step i has exposure ``exposures_ms[i]`` and irradiance ``levels[i] * irradiance_w_m2``;
        its ``photons`` field is ``levels[i] * exposure`` (a relative photon count, so that
        photons / exposure is proportional to the light rate, as in EMVA 1288 data). With
        ``darks`` a dark step follows every light step. ``meta["truth"]`` holds the truth at
        level 1 and ``meta["levels"]`` the level of every step (0 for darks).
        """
        rng = self._noise_rng if seed is None else np.random.default_rng(seed)
        exposures = np.asarray(exposures_ms, float)
        levels = np.broadcast_to(np.asarray(levels, float), exposures.shape)
        illum = self._illum(illumination, irradiance_w_m2, 0.0)
        k1 = self.light_rate(illum)
        truth = self.truth(k1)
        frames, exp, kind, photons, step_levels = [], [], [], [], []
        for t, lev in zip(exposures, levels):
            cap_truth = self.truth(k1 * lev)
            f, _ = self._expose(cap_truth, float(t), n_frames, rng)
            frames.append(f)
            exp += [t] * n_frames
            kind += ["light"] * n_frames
            photons += [lev * t] * n_frames
            step_levels.append(lev)
            if darks:
                f, _ = self._expose(self.truth(np.zeros(self.shape)), float(t), n_frames, rng)
                frames.append(f)
                exp += [t] * n_frames
                kind += ["dark"] * n_frames
                photons += [np.nan] * n_frames
                step_levels.append(0.0)
        return Sweep(np.concatenate(frames), exp, kind, self.params.bit_depth, photons=photons,
                     illumination=[illum.label if k == "light" else "" for k in kind],
                     mosaic=self.mosaic, source="simulated",
                     meta={"simulator": self.describe(), "truth": truth,
                           "levels": step_levels})

    def describe(self) -> dict:
        """JSON-safe description of the simulated sensor (for metadata and reports)."""
        return {"shape": list(self.shape), "seed": self.seed, "params": asdict(self.params),
                "mosaic": self.mosaic.to_dict(), "bands": self.bands.name}

    # -- convenience ---------------------------------------------------------------------------
    @classmethod
    def default(cls, shape=(64, 64), *, seed: int = 0, **param_overrides) -> "MosaicSensor":
        """The paper's 8-band sensor with default parameters (optionally overridden)."""
        return cls(shape, params=replace(SensorParams(), **param_overrides), seed=seed)


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


def _default_mosaic(bands: BandSet) -> Mosaic:
    n = bands.n_bands
    rows = int(np.floor(np.sqrt(n)))
    while n % rows:
        rows -= 1
    cols = n // rows
    return Mosaic(np.arange(n).reshape(rows, cols), wavelengths_nm=tuple(bands.centres_nm),
                  name=f"{rows}x{cols}")


def _calibrate_paper_light() -> dict:
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
    return {"fig5": 2.0 / per_w["lamp B"], "training": 30.0 / per_w["lamp A"],
            "test": 25.0 / per_w["lamp B max"]}


PAPER_LIGHT_W_M2 = _LazyLevels(_calibrate_paper_light)
