"""The simulated snapshot-mosaic sensor (see :mod:`hsiffc.simulate`)."""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np

from ..data.mosaic import Mosaic
from ..spectral import BandSet, Illumination, electron_rate, lamp
from ..data.sweep import Sweep
from .params import PAPER_LIGHT_W_M2  # noqa: F401 (the examples use it)
from .params import Capture, SensorParams, Truth, default_bands, default_mosaic

__all__ = ["MosaicSensor"]


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
            mosaic = default_mosaic(self.bands)
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
