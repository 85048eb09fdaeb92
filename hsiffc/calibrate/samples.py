"""From a sweep to fit samples: step means, validity, relative light rates, noise weights.

A *sample* is the mean of the frames of one acquisition step at one pixel. A sample is left out
of a fit (and counted) when any of its frames is clipped at full scale (its mean is biased),
when it is at or above the full-well level, or when its exposure is zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ..data.sweep import Sweep
from ..errors import DataFormatError
from ..kernels.sweepstats import pair_stats, step_means


@dataclass(frozen=True, eq=False)
class Samples:
    """Step-mean samples of a sweep, pixels flattened: arrays (S, P) unless stated.

    Made by :func:`collect_samples`; S steps, P pixels.

    Attributes
    ----------
    y : ndarray of float32, (S, P), DN
        Step means.
    clipped, full_well : ndarray of bool, (S, P)
        Some frame of the step at full scale; the mean at or above the full-well level.
    exposure_ms, rate, n_frames, kind, illumination, step, usable_step : (S,) arrays
        Exposure (ms), relative light rate (0 for darks; unit ``rate_unit``), frames per step,
        "light"/"dark", illumination label, step id, and whether the step can be fitted.
    frame_shape : (int, int)
        (H, W) of the pixels sampled.
    full_scale_dn : int
        ``2**bit_depth - 1``.
    """

    y: np.ndarray  # step means, DN (float32 unless asked otherwise)
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
        """(S, P) bool: samples a fit may use (not clipped, below full well, usable step)."""
        ok = ~(self.clipped | self.full_well)
        ok &= self.usable_step[:, None]
        return ok


def relative_light_rate(sweep_steps: dict, *, light_rate=None) -> tuple[np.ndarray, str]:
    """Relative light rate of every step and its unit.

    Priority: ``light_rate`` given by the user (one value per step); photons / exposure where the
    sweep has photon counts (EMVA 1288); otherwise 1 for every light step when all light steps
    share one illumination label. Dark steps get 0.

    Parameters
    ----------
    sweep_steps : dict
        Per-step arrays ``kind``, ``photons``, ``exposure_ms`` (ms) and ``illumination``.
    light_rate : array_like, optional
        One relative light rate per step.

    Returns
    -------
    rate : ndarray of float64, (S,)
        Relative light rate per step (0 for darks, NaN where unusable).
    unit : str
        ``"user"``, ``"photons/ms"`` or ``"1 = the sweep's illumination"``.

    Raises
    ------
    DataFormatError
        Several illuminations without photon counts or ``light_rate``.
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
                    rows: slice | None = None, dtype=np.float32,
                    clip_dn: float | None = None, floor_dn: float | None = None) -> Samples:
    """Step means and validity of every pixel (optionally of a band of ``rows`` only).

    Parameters
    ----------
    sweep : Sweep
        Raw frames (N, H, W) in DN with their steps.
    full_well_dn : float, optional, DN
        Step means at or above this level are not valid samples.
    light_rate : array_like, optional
        One relative light rate per step (see :func:`relative_light_rate`).
    rows : slice, optional
        Rows of the frame to sample (default: all).
    dtype : numpy dtype
        Of the step means: float32, or float64 for a fit that computes in float64.
    clip_dn : float, optional, DN
        Frame values at or above it are clipped (default: the ADC's full scale; lower where
        the data clip first, e.g. a full well that fills before the ADC).
    floor_dn : float, optional, DN
        Frame values at or below it are clipped too (the ADC's lowest code, 0 DN, where a low
        black level or a negative offset drift cuts the noise off; default: no floor).

    Returns
    -------
    Samples
        Arrays (S, P) over the S steps and the P pixels of the rows.
    """
    steps = sweep.steps()
    rows = rows or slice(0, sweep.frame_shape[0])
    r0, r1, _ = rows.indices(sweep.frame_shape[0])
    shape = (r1 - r0, sweep.frame_shape[1])
    fs = sweep.full_scale_dn
    means = np.empty((len(steps), shape[0] * shape[1]), dtype)
    clipped = np.empty(means.shape, bool)
    exposure = np.empty(len(steps))
    n_frames = np.empty(len(steps), np.int64)
    kind = np.empty(len(steps), "U5")
    photons = np.empty(len(steps))
    illum = np.empty(len(steps), object)
    frames_of = [np.flatnonzero(sweep.step == s) for s in steps]
    sel = np.zeros((len(steps), max(f.size for f in frames_of)), np.int64)
    for i, f in enumerate(frames_of):
        sel[i, :f.size] = f
    step_means(sweep.data, sel, np.array([f.size for f in frames_of]), r0, r1,
                float(fs if clip_dn is None else clip_dn),
                float(-np.inf if floor_dn is None else floor_dn), means, clipped)
    averaged = sweep.meta.get("frames_averaged")  # frames that are means of several
    for i, f in enumerate(frames_of):
        n_frames[i] = f.size if averaged is None else int(np.asarray(averaged)[f].sum())
        exposure[i] = sweep.exposure_ms[f[0]]
        kind[i] = sweep.kind[f[0]]
        photons[i] = sweep.photons[f[0]]
        illum[i] = sweep.illumination[f[0]]
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
    """Temporal noise model of step means: ``var = gain * (mean - dark) + read_var`` (DN^2).

    Attributes
    ----------
    gain_dn_per_e : float, DN/e-
        System gain K of EMVA 1288.
    read_var_dn2 : float, DN^2
        Temporal dark variance, quantisation included.
    n_steps_used : int
        Steps the line was fitted on.
    """

    gain_dn_per_e: float  # system gain K of EMVA 1288 (DN per electron)
    read_var_dn2: float  # temporal dark variance incl. quantisation
    n_steps_used: int

    def variance(self, signal_dn):
        """Temporal variance (DN^2) of one frame at ``signal_dn`` (DN above dark, array_like);
        negative signals count as 0."""
        return self.gain_dn_per_e * np.maximum(signal_dn, 0.0) + self.read_var_dn2


def photon_transfer(sweep: Sweep, *, max_fraction_of_full_scale: float = 0.7) -> PhotonTransfer | None:
    """Fit the photon transfer curve from steps with two or more frames (EMVA 1288 method).

    Per step, the temporal variance is the mean over pixels of the frame-to-frame variance
    (pixels clipped in any frame of the step are left out). A straight line through variance
    against the mean signal above dark, over unclipped steps below ``max_fraction_of_full_scale``,
    gives the system gain K and the dark variance.

    Parameters
    ----------
    sweep : Sweep
        Raw frames with at least two frames in some steps.
    max_fraction_of_full_scale : float
        Light steps whose mean exceeds this fraction of full scale are left out of the line.

    Returns
    -------
    PhotonTransfer or None
        None when no step has two frames.
    """
    fs = sweep.full_scale_dn
    pairs = []
    for s in sweep.steps():
        sel = np.flatnonzero(sweep.step == s)
        if sel.size >= 2:
            pairs.append((sweep.kind[sel[0]],
                          *pair_stats(sweep.data[sel[0]], sweep.data[sel[1]], float(fs))))
    return photon_transfer_from_pairs(pairs, sweep.data[0].size, fs,
                                      max_fraction_of_full_scale=max_fraction_of_full_scale)


def photon_transfer_from_pairs(pairs, n_pixels: int, full_scale_dn: float, *,
                               max_fraction_of_full_scale: float = 0.7
                               ) -> PhotonTransfer | None:
    """:func:`photon_transfer` from the first two frames of every step, reduced: ``pairs`` holds
    per step (kind, pixels below full scale in both frames, their mean level in DN, half
    their mean squared frame-to-frame difference in DN^2), e.g. accumulated while the frames
    were streamed (:mod:`hsiffc.emva1288.stream`); ``n_pixels`` the frame's pixels."""
    fs = full_scale_dn
    rows = []
    dark_means = []
    for kind, n_ok, mean, var in pairs:
        if n_ok < 0.5 * n_pixels:
            continue
        rows.append((kind, mean, var))
        if kind == "dark":
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


def kernel_samples(smp: Samples, ptc: PhotonTransfer | None, *,
                   exposure_offset_ms: float = 0.0) -> dict:
    """Arguments of :func:`hsiffc.calibrate.joint.run_kernel` for a chunk of samples: (S, P)
    step means and validity, the per-step arrays and the photon-transfer noise model.

    Parameters
    ----------
    smp : Samples
        Step means of a chunk of pixels (:func:`hsiffc.calibrate.collect_samples`).
    ptc : PhotonTransfer or None
        Noise model for the weights (None: unit read variance).
    exposure_offset_ms : float, ms
        Added to the exposure of every light sample: the light is collected for ``t + t0``
        (a shutter or transfer offset, :func:`exposure_offset`). A light step whose
        ``t + t0`` is not positive is left out.

    Returns
    -------
    dict
        ``y``, ``valid`` (S, P); ``t`` (ms), ``r``, ``light``, ``dark``, ``n_frames`` (S,);
        ``noise`` (gain DN/e-, read variance DN^2) or None.
    """
    usable = smp.usable_step
    r = np.where(usable, np.nan_to_num(smp.rate), 0.0)
    light = usable & (smp.kind == "light") & (r > 0)
    t_light = smp.exposure_ms + exposure_offset_ms
    light &= t_light > 0
    t = np.where(light, t_light, np.where(usable, smp.exposure_ms, 0.0))
    dark = usable & (smp.kind == "dark")
    return {"y": smp.y, "valid": smp.valid, "t": t, "r": np.where(light | dark, r, 0.0),
            "light": light, "dark": dark, "n_frames": smp.n_frames,
            "noise": None if ptc is None else (ptc.gain_dn_per_e, ptc.read_var_dn2)}


def exposure_offset(ks: dict, *, max_fraction: float = 0.5, min_sigmas: float = 3.0) -> dict:
    """The sensor's exposure offset ``t0`` (ms): light collected for ``t + t0``.

    CCDs, global and mechanical shutters collect light for a time that differs from the
    nominal exposure by a fixed amount, so the light response does not start at the dark
    level: ``Y - D(t) = G r (t + t0)``. Per light step, the mean signal above each pixel's
    dark line (its dark frames) over the pixels; a weighted least-squares fit of
    ``G r t + H r`` through the steps below ``max_fraction`` of the highest signal (relative
    errors: weights ``1 / S^2``; a term in the dose squared takes up a response that starts to
    bend, from leakage or a compression, so that a bend is not read as an offset) gives
    ``t0 = H / G``. It is kept where the sweep has four or
    more exposures there and ``|t0|`` exceeds ``min_sigmas`` standard errors; otherwise 0 (a
    light sweep at one exposure cannot tell an offset from the responsivity, and needs
    none).

    Parameters
    ----------
    ks : dict
        :func:`kernel_samples` of a sample of pixels (with dark samples).

    Returns
    -------
    dict
        ``exposure_offset_ms`` (0 where not measurable), ``sigma_ms``, ``n_steps``, ``used``
        (bool) and ``reason``.
    """
    out = {"exposure_offset_ms": 0.0, "sigma_ms": float("nan"), "n_steps": 0, "used": False}
    y, valid, t, r = ks["y"], ks["valid"], ks["t"], ks["r"]
    dark, light = ks["dark"], ks["light"]
    if not dark.any():
        return {**out, "reason": "no dark frames: the offset cannot be told from the dark"}
    tm, ym, slope = dark_lines(ks)
    slope = np.nan_to_num(slope)  # one dark exposure: a constant dark

    def dark_line(ti):
        return ym + slope * (ti - tm)
    signal = []
    for s in np.flatnonzero(light):
        ok = valid[s]
        if ok.mean() < 0.9:
            continue
        signal.append((s, float(np.mean(y[s, ok] - dark_line(t[s])[ok]))))
    if len(signal) < 3:
        return {**out, "reason": "fewer than 3 unclipped light steps"}
    idx, level = (np.array(v) for v in zip(*signal))
    keep = (level > 0) & (level <= max_fraction * level.max())
    idx, level = idx[keep], level[keep]
    if np.unique(np.round(t[idx], 9)).size < 4:
        return {**out, "reason": "fewer than 4 exposures in the lower half of the sweep"}
    dose = r[idx] * t[idx]
    x = np.column_stack([dose, r[idx], (dose / dose.max()) ** 2])
    w = 1.0 / level ** 2
    xtw = x.T * w
    try:
        cov = np.linalg.inv(xtw @ x)
    except np.linalg.LinAlgError:
        return {**out, "reason": "exposure and light rate not separable"}
    coef = cov @ (xtw @ level)
    res = level - x @ coef
    s2 = float((w * res ** 2).sum() / max(idx.size - 3, 1))
    cov = cov[:2, :2]
    g, h = (float(v) for v in coef[:2])
    if not g > 0:
        return {**out, "reason": "no positive response"}
    t0 = h / g
    # standard error of H / G by the delta method
    jac = np.array([-h / g ** 2, 1.0 / g])
    se = float(np.sqrt(max(jac @ (cov * s2) @ jac, 0.0)))
    out.update(sigma_ms=se, n_steps=int(idx.size))
    if abs(t0) > min_sigmas * se and abs(t0) < 0.5 * float(t[idx].max()):
        return {**out, "exposure_offset_ms": t0, "used": True,
                "reason": f"measured at {abs(t0) / se:.1f} standard errors"}
    return {**out, "reason": f"not significant ({t0:.3g} +- {se:.2g} ms)"}


def dark_lines(ks: dict) -> tuple:
    """Per pixel, the unweighted least-squares line through its valid dark samples.

    Parameters
    ----------
    ks : dict
        :func:`kernel_samples` of the pixels.

    Returns
    -------
    t_mean, y_mean, slope : (P,) float64
        Mean exposure (ms), mean level (DN) and slope (DN/ms; NaN where the samples do not
        span two exposures, or there are none), so the level at ``t`` is ``y_mean + slope *
        (t - t_mean)``.
    """
    use = ks["valid"] & ks["dark"][:, None]
    n = use.sum(axis=0)
    tt = np.where(use, ks["t"][:, None], 0.0)
    yy = np.where(use, ks["y"], 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tm, ym = tt.sum(0) / n, yy.sum(0) / n
        slope = (np.where(use, (tt - tm) * (yy - ym), 0).sum(0)
                 / np.where(use, (tt - tm) ** 2, 0).sum(0))
    return tm, ym, slope


def dark_level(ks: dict, dark_current) -> np.ndarray:
    """Per pixel, its dark frames' level at zero exposure (DN): the weighted mean of its dark
    samples (step means weighted by their frames) less ``dark_current`` times their weighted
    mean exposure; NaN without a dark sample.

    Parameters
    ----------
    ks : dict
        :func:`kernel_samples` of the pixels.
    dark_current : (P,) array_like, DN/ms
    """
    rows = np.flatnonzero(ks["dark"])  # the dark steps' rows only: weights by matrix products
    use = ks["valid"][rows].astype(np.float64)
    n = np.asarray(ks["n_frames"], np.float64)[rows]
    sw = n @ use
    with np.errstate(divide="ignore", invalid="ignore"):
        mt = (n * ks["t"][rows]) @ use / sw
        my = (n[:, None] * use * ks["y"][rows]).sum(axis=0) / sw
    return np.where(sw > 0, my - np.asarray(dark_current, np.float64) * mt, np.nan)


def dark_sigma(ks: dict, *, dark_current: bool) -> np.ndarray:
    """Per pixel, the 1-sigma error (DN) of the dark level measured by its dark frames: the
    intercept of the weighted line through the dark samples (or their weighted mean without a
    dark current), each step mean weighted by its frames over the read variance.

    Parameters
    ----------
    ks : dict
        :func:`kernel_samples` of the pixels.
    dark_current : bool
        Whether the dark line has a slope (the dark current).

    Returns
    -------
    (P,) float64 (inf without a dark sample)
    """
    read_var = ks["noise"][1] if ks["noise"] is not None else 1.0
    rows = np.flatnonzero(ks["dark"])
    use = ks["valid"][rows].astype(np.float64)
    w = np.asarray(ks["n_frames"], np.float64)[rows] / read_var
    t = ks["t"][rows]
    sw, swt, swtt = w @ use, (w * t) @ use, (w * t * t) @ use
    with np.errstate(divide="ignore", invalid="ignore"):
        if dark_current:
            den = sw * swtt - swt ** 2
            var = np.where(den > 1e-12 * sw * swtt, swtt / den, 1.0 / sw)
        else:
            var = 1.0 / sw
    return np.where(sw > 0, np.sqrt(var), np.inf)


def linear_fit(ks: dict, dark, dark_current, *, exposure_offset_ms: float = 0.0) -> tuple:
    """Per pixel, the linear response through the pixel's dark line: ``Y - (d + dc t) =
    g r (t + t0)``, weighted least squares over its valid light samples (weights from the
    photon-transfer noise model, as the joint fit's).

    Parameters
    ----------
    ks : dict
        :func:`kernel_samples` of the pixels (light exposures already ``t + t0``).
    dark, dark_current : (P,) array_like
        The dark line (DN, DN/ms) at the nominal exposure.
    exposure_offset_ms : float
        The ``t0`` in ``ks``'s light exposures (taken off for the dark line).

    Returns
    -------
    g : (P,) float64
        Responsivity, DN/ms per unit of relative light rate (NaN without a light sample).
    sigma_ln_g : (P,) float64
        Its 1-sigma relative error (scaled by the fit's reduced chi-square where above 1).
    """
    sel = ks["valid"] & ks["light"][:, None]
    t_eff = ks["t"][:, None]
    u = ks["r"][:, None] * t_eff
    z = ks["y"] - (np.asarray(dark, np.float64)[None, :]
                   + np.asarray(dark_current, np.float64)[None, :] * (t_eff - exposure_offset_ms))
    gain, read_var = ks["noise"] if ks["noise"] is not None else (0.0, 1.0)
    w = np.where(sel, ks["n_frames"][:, None] / (gain * np.maximum(z, 0.0) + read_var), 0.0)
    wuu = (w * u * u).sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = (w * u * z).sum(axis=0) / wuu
        chi2 = (w * (z - g * u) ** 2).sum(axis=0)
        over = np.maximum(chi2 / np.maximum(sel.sum(axis=0) - 1, 1), 1.0)
        sigma = np.sqrt(over / wuu) / g
    ok = (wuu > 0) & (g > 0)
    return np.where(ok, g, np.nan), np.where(ok & np.isfinite(sigma), sigma, np.inf)
