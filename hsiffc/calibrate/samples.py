"""From a sweep to fit samples: step means, validity, relative light rates, noise weights.

A *sample* is the mean of the frames of one acquisition step at one pixel. A sample is left out
of a fit (and counted) when any of its frames is clipped at full scale (its mean is biased),
when it is at or above the full-well level, or when its exposure is zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DataFormatError
from ..sweep import Sweep


@dataclass(frozen=True, eq=False)
class Samples:
    """Step-mean samples of a sweep, pixels flattened: arrays (S, P) unless stated."""

    y: np.ndarray  # float32 step means, DN
    clipped: np.ndarray  # bool: some frame at full scale
    full_well: np.ndarray  # bool: at or above the full-well level
    exposure_ms: np.ndarray  # (S,)
    rate: np.ndarray  # (S,) relative light rate (0 for darks)
    rate_unit: str
    n_frames: np.ndarray  # (S,)
    kind: np.ndarray  # (S,)
    illumination: np.ndarray  # (S,)
    step: np.ndarray  # (S,) step ids
    usable_step: np.ndarray  # (S,) bool: exposure > 0 and a known rate
    frame_shape: tuple
    full_scale_dn: int

    @property
    def valid(self) -> np.ndarray:
        return (~self.clipped) & (~self.full_well) & self.usable_step[:, None]


def relative_light_rate(sweep_steps: dict, *, light_rate=None) -> tuple[np.ndarray, str]:
    """Relative light rate of every step and its unit.

    Priority: ``light_rate`` given by the user (one value per step); photons / exposure where the
    sweep has photon counts (EMVA 1288); otherwise 1 for every light step when all light steps
    share one illumination label. Dark steps get 0.
    """
    kind = sweep_steps["kind"]
    dark = kind == "dark"
    n = len(kind)
    if light_rate is not None:
        rate = np.asarray(light_rate, np.float64)
        if rate.shape != (n,):
            raise ValueError(f"light_rate must have one value per step ({n}), got {rate.shape}")
        return np.where(dark, 0.0, rate), "user"
    photons = sweep_steps["photons"]
    t = sweep_steps["exposure_ms"]
    light = ~dark
    if light.any() and np.all(np.isfinite(photons[light])):
        with np.errstate(divide="ignore", invalid="ignore"):
            rate = np.where(light, photons / t, 0.0)
        rate[~np.isfinite(rate)] = np.nan  # zero exposure: unusable
        return rate, "photons/ms"
    labels = set(sweep_steps["illumination"][light].tolist())
    if len(labels) > 1:
        raise DataFormatError(
            f"the sweep mixes illuminations {sorted(labels)} without photon counts, so the light "
            "rate of each step is unknown; calibrate each illumination separately, use "
            "method='paper' (several illuminations), or pass light_rate=[...] per step")
    return np.where(dark, 0.0, 1.0), "1 = the sweep's illumination"


def collect_samples(sweep: Sweep, *, full_well_dn: float | None = None, light_rate=None,
                    rows: slice | None = None) -> Samples:
    """Step means and validity of every pixel (optionally of a band of ``rows`` only)."""
    steps = sweep.steps()
    data = sweep.data if rows is None else sweep.data[:, rows]
    shape = data.shape[1:]
    fs = sweep.full_scale_dn
    means = np.empty((len(steps), shape[0] * shape[1]), np.float32)
    clipped = np.empty(means.shape, bool)
    exposure = np.empty(len(steps))
    n_frames = np.empty(len(steps), np.int64)
    kind = np.empty(len(steps), "U5")
    photons = np.empty(len(steps))
    illum = np.empty(len(steps), object)
    for i, s in enumerate(steps):
        sel = np.flatnonzero(sweep.step == s)
        frames = data[sel].reshape(sel.size, -1)
        means[i] = frames.mean(axis=0, dtype=np.float64)
        clipped[i] = (frames >= fs).any(axis=0)
        exposure[i] = sweep.exposure_ms[sel[0]]
        n_frames[i] = sel.size
        kind[i] = sweep.kind[sel[0]]
        photons[i] = sweep.photons[sel[0]]
        illum[i] = sweep.illumination[sel[0]]
    info = {"kind": kind, "photons": photons, "exposure_ms": exposure,
            "illumination": illum.astype(str)}
    rate, unit = relative_light_rate(info, light_rate=light_rate)
    full_well = (means >= full_well_dn) if full_well_dn is not None else np.zeros_like(clipped)
    usable = (exposure > 0) & np.isfinite(rate)
    return Samples(y=means, clipped=clipped, full_well=full_well, exposure_ms=exposure, rate=rate,
                   rate_unit=unit, n_frames=n_frames, kind=kind, illumination=info["illumination"],
                   step=steps, usable_step=usable, frame_shape=tuple(shape), full_scale_dn=fs)


@dataclass(frozen=True)
class PhotonTransfer:
    """Temporal noise model of step means: ``var = gain * (mean - dark) + read_var`` (DN^2)."""

    gain_dn_per_e: float  # system gain K of EMVA 1288 (DN per electron)
    read_var_dn2: float  # temporal dark variance incl. quantisation
    n_steps_used: int

    def variance(self, signal_dn):
        return self.gain_dn_per_e * np.maximum(signal_dn, 0.0) + self.read_var_dn2


def photon_transfer(sweep: Sweep, *, max_fraction_of_full_scale: float = 0.7) -> PhotonTransfer | None:
    """Fit the photon transfer curve from steps with two or more frames (EMVA 1288 method).

    Per step, the temporal variance is the mean over pixels of the frame-to-frame variance
    (pixels clipped in any frame of the step are left out). A straight line through variance
    against the mean signal above dark, over unclipped steps below ``max_fraction_of_full_scale``,
    gives the system gain K and the dark variance. Returns None when no step has two frames.
    """
    fs = sweep.full_scale_dn
    rows = []
    dark_means = []
    for s in sweep.steps():
        sel = np.flatnonzero(sweep.step == s)
        if sel.size < 2:
            continue
        frames = sweep.data[sel[:2]].astype(np.float64)
        ok = (frames < fs).all(axis=0)
        if ok.mean() < 0.5:
            continue
        mean = frames.mean(axis=0)[ok].mean()
        var = 0.5 * ((frames[0] - frames[1])[ok] ** 2).mean()
        rows.append((sweep.kind[sel[0]], mean, var))
        if sweep.kind[sel[0]] == "dark":
            dark_means.append(mean)
    if not rows:
        return None
    kinds = np.array([r[0] for r in rows])
    means = np.array([r[1] for r in rows])
    vars_ = np.array([r[2] for r in rows])
    dark = float(np.median(dark_means)) if dark_means else float(means.min())
    light = (kinds == "light") & (means < max_fraction_of_full_scale * fs)
    read_var = float(np.median(vars_[kinds == "dark"])) if (kinds == "dark").any() else None
    if light.sum() >= 3:
        slope, intercept = np.polyfit(means[light] - dark, vars_[light], 1)
        gain = float(max(slope, 1e-6))
        if read_var is None:
            read_var = float(max(intercept, 1 / 12))
    else:
        gain = 0.0
        read_var = read_var if read_var is not None else float(vars_.min())
    return PhotonTransfer(gain_dn_per_e=gain, read_var_dn2=max(read_var, 1 / 12),
                          n_steps_used=int(light.sum()))
