"""Per-pixel calibration of the leakage model from exposure sweeps.

Two methods, both vectorised over all pixels:

- ``"joint"`` (beyond the paper): one weighted least-squares fit per pixel of the responsivity
  (light rate per unit of the step's relative light rate), a, b and the dark level, using every
  valid sample of one sweep whose light may change from step to step (EMVA 1288 photons /
  exposure). Gives per-pixel residual RMS (DN) and parameter uncertainties.
- ``"paper"`` (section III.C): k per illumination from the linear part of its exposure sweep,
  a and b from the dynamic saturation levels reached under several illuminations (ln k against
  the saturated level is a straight line), the dark level (the paper's constant c) from the
  shortest exposure.

Both leave out and count clipped samples (any frame of the step at full scale) and samples at or
above the full-well level.
"""

from __future__ import annotations

import logging

import numpy as np

from .. import model
from ..dq import DQ
from ..errors import DataFormatError
from ..sweep import Sweep
from .joint import (B_GRID, JointFit, dark_current_from_darks, fit_pixels, initial_guess,
                    merge_dark_samples, model_and_jacobian, predict, residuals)
from .product import Calibration
from .samples import PhotonTransfer, Samples, collect_samples, photon_transfer

__all__ = ["calibrate", "calibrate_joint", "calibrate_paper", "Calibration", "photon_transfer",
           "PhotonTransfer", "collect_samples", "Samples", "fit_pixels", "initial_guess",
           "model_and_jacobian", "predict", "residuals", "JointFit"]

log = logging.getLogger(__name__)
METHODS = ("joint", "paper")


def calibrate(sweep: Sweep, *, method: str = "joint", **kwargs) -> Calibration:
    """Calibrate every pixel of ``sweep``; ``method`` is ``"joint"`` or ``"paper"``."""
    if method == "joint":
        return calibrate_joint(sweep, **kwargs)
    if method == "paper":
        return calibrate_paper(sweep, **kwargs)
    raise ValueError(f"unknown calibration method {method!r}; choose one of {METHODS}")


def _sample_weights(samples: Samples, ptc: PhotonTransfer | None, dark0: np.ndarray):
    """1 / variance of each step mean (S, P) from the photon transfer curve."""
    n = samples.n_frames[:, None].astype(np.float64)
    if ptc is None:
        return np.broadcast_to(n, samples.y.shape).astype(np.float64)
    return n / ptc.variance(samples.y.astype(np.float64) - dark0[None, :])


def fit_inputs(smp: Samples, ptc: PhotonTransfer | None, dark_current: bool | str = "auto"):
    """The joint fit's inputs for a set of samples, exactly as :func:`calibrate_joint` builds them.

    Returns a dict: ``y, t, r, valid, wgt`` (pixels x samples, dark samples merged), ``dc``
    (fixed per-pixel dark current or None) and the unmerged ``y_all, valid_all`` (residual RMS
    and sample counts are taken over these).
    """
    valid = smp.valid.T
    y = smp.y.T.astype(np.float64)
    dark_steps = smp.kind == "dark"
    dark0 = (np.median(smp.y[dark_steps], axis=0) if dark_steps.any()
             else np.min(smp.y, axis=0)).astype(np.float64)
    wgt = _sample_weights(smp, ptc, dark0).T
    n_dark_exposures = len(np.unique(smp.exposure_ms[dark_steps & smp.usable_step]))
    dc = None
    if dark_current is True or (dark_current == "auto" and n_dark_exposures >= 2):
        dc = dark_current_from_darks(y, smp.exposure_ms, smp.rate, valid, wgt)
        # keep it only when the pixels as a whole show a dark current above the noise
        # (a negative dark current is not physical: clip at zero)
        med = np.median(dc)
        se = 1.4826 * np.median(np.abs(dc - med)) / np.sqrt(dc.size)
        dc = np.clip(dc, 0.0, None) if (dark_current is True or med > 3 * se) else None
    y_m, t_m, r_m, v_m, w_m = merge_dark_samples(y, smp.exposure_ms, smp.rate, valid, wgt, dc)
    return {"y": y_m, "t": np.asarray(t_m, np.float64), "r": np.asarray(r_m, np.float64),
            "valid": v_m, "wgt": w_m, "dc": dc, "y_all": y, "valid_all": valid}


def calibrate_joint(sweep: Sweep, *, full_well_dn: float | None = None, light_rate=None,
                    dark_current: bool | str = "auto", rows_per_chunk: int | None = None,
                    progress=None) -> Calibration:
    """Joint per-pixel fit of responsivity, a, b and dark level from one sweep.

    Parameters
    ----------
    sweep : Sweep
        Light and (ideally) dark steps. The light rate of a step is photons / exposure when
        photon counts are present (EMVA 1288), else 1 for every light step (single illumination),
        or ``light_rate`` (one value per step).
    full_well_dn : float, optional
        Samples at or above this level are left out as full-well saturated.
    dark_current : "auto", True or False
        Estimate a per-pixel dark current from dark steps at two or more exposures and add it
        to the light rate ("auto": when such dark steps exist).
    rows_per_chunk : int, optional
        Rows processed at once (memory is bounded by rows x width x steps); default: chunks of
        about 32k pixels.
    progress : callable, optional
        Called with (rows_done, rows_total) after each chunk.
    """
    h, w = sweep.frame_shape
    if not sweep.is_light.any():
        raise DataFormatError("the sweep has no light frames to calibrate from",
                              path=sweep.source or None)
    ptc = photon_transfer(sweep)
    n_steps = len(sweep.steps())
    rows_per_chunk = rows_per_chunk or max(1, 262144 // (w * n_steps))
    out = {name: np.zeros((h, w), np.float32) for name in (
        "responsivity", "a_dn_per_ms", "b_per_dn", "dark_dn", "dark_current_dn_per_ms",
        "sigma_ln_g", "sigma_ln_a", "sigma_ln_b", "sigma_dark_dn", "rms_dn", "chi2_red",
        "saturation_ref_dn")}
    counts = {name: np.zeros((h, w), np.int32) for name in ("n_valid", "n_clipped", "n_full_well")}
    flags = np.zeros((h, w), np.uint32)
    info = None
    b_grid = None  # set by a pilot fit on the first chunk
    for r0 in range(0, h, rows_per_chunk):
        rows = slice(r0, min(h, r0 + rows_per_chunk))
        smp = collect_samples(sweep, full_well_dn=full_well_dn, light_rate=light_rate, rows=rows)
        info = info or smp
        fi = fit_inputs(smp, ptc, dark_current)
        y, t_s, r_s, valid, wgt, dc = (fi[k] for k in ("y", "t", "r", "valid", "wgt", "dc"))
        y_all, valid_all = fi["y_all"], fi["valid_all"]
        if b_grid is None:
            b_grid = _pilot_b_grid(y, t_s, r_s, valid, wgt, dc)
        theta0 = initial_guess(y, t_s, r_s, valid, wgt, dc, b_grid=b_grid)
        fit = fit_pixels(y, t_s, r_s, valid, wgt, theta0, dark_current=dc)
        rr = slice(rows.start, rows.stop)
        nr = rows.stop - rows.start
        shape = (nr, w)
        out["responsivity"][rr] = fit.g.reshape(shape)
        out["a_dn_per_ms"][rr] = fit.a.reshape(shape)
        out["b_per_dn"][rr] = fit.b.reshape(shape)
        out["dark_dn"][rr] = fit.dark.reshape(shape)
        out["dark_current_dn_per_ms"][rr] = (0 if dc is None else dc.reshape(shape))
        for i, name in enumerate(("sigma_ln_g", "sigma_ln_a", "sigma_ln_b", "sigma_dark_dn")):
            out[name][rr] = fit.sigma[:, i].reshape(shape)
        res = residuals(fit, y_all, smp.exposure_ms, smp.rate, valid_all, dc)
        n_all = valid_all.sum(axis=1)
        out["rms_dn"][rr] = np.sqrt((res ** 2).sum(axis=1) / np.maximum(n_all, 1)).reshape(shape)
        out["chi2_red"][rr] = fit.chi2_red.reshape(shape)
        rmax = np.where(valid, r_s[None, :], 0).max(axis=1)
        out["saturation_ref_dn"][rr] = model.dynamic_saturation_level(
            np.maximum(fit.g * rmax, 1e-300), fit.a, fit.b).reshape(shape)
        counts["n_valid"][rr] = n_all.reshape(shape)
        usable = smp.usable_step[:, None]
        counts["n_clipped"][rr] = (smp.clipped & usable).sum(axis=0).reshape(shape)
        counts["n_full_well"][rr] = (smp.full_well & ~smp.clipped & usable).sum(axis=0).reshape(shape)
        f = np.zeros(fit.g.shape, np.uint32)
        f[~fit.converged] |= np.uint32(DQ.NOT_CONVERGED)
        f[~fit.leak_constrained] |= np.uint32(DQ.LEAK_UNCONSTRAINED)
        f[fit.n_valid < 5] |= np.uint32(DQ.DO_NOT_USE)
        flags[rr] = f.reshape(shape)
        if progress:
            progress(rows.stop, h)
    light_ok = info.usable_step & (info.kind == "light")
    rates = info.rate[light_ok]
    arrays = {**out, **counts, "flags": flags}
    single = info.rate_unit.startswith("1 =")
    if single:
        arrays["k_ref_dn_per_ms"] = out["responsivity"]
    return Calibration(arrays=arrays, domain=_domain(sweep, info, rates), method="joint",
                       fitted_on=_fitted_on(sweep, info, ptc, full_well_dn))


def _pilot_b_grid(y, t, r, valid, wgt, dc, n_pilot: int = 512):
    """Start value of b for a whole sensor: fit up to ``n_pilot`` pixels from the full grid of
    start values and keep the median fitted b (pixels of one sensor share their leakage
    physics; the fit then moves each pixel from there). Falls back to the full grid."""
    p = y.shape[0]
    rng = np.random.default_rng(0)
    idx = np.sort(rng.choice(p, size=min(p, n_pilot), replace=False))
    sub = (y[idx], t, r, valid[idx], wgt[idx])
    dcs = None if dc is None else dc[idx]
    fit = fit_pixels(*sub, initial_guess(*sub, dcs), dark_current=dcs)
    good = fit.leak_constrained & fit.converged
    if good.sum() < 10:
        return B_GRID
    return (float(np.median(fit.b[good])),)


def _domain(sweep: Sweep, info: Samples, rates) -> dict:
    usable = info.usable_step
    return {"exposure_ms": [float(info.exposure_ms[usable].min()),
                            float(info.exposure_ms[usable].max())],
            "light_rate": [float(np.min(rates)), float(np.max(rates))] if len(rates) else [0, 0],
            "light_rate_unit": info.rate_unit, "bit_depth": sweep.bit_depth,
            "full_scale_dn": sweep.full_scale_dn, "frame_shape": list(sweep.frame_shape),
            "mosaic": sweep.mosaic.to_dict() if sweep.mosaic else None}


def _fitted_on(sweep: Sweep, info: Samples, ptc, full_well_dn) -> dict:
    return {"source": sweep.source or "in-memory sweep", "n_frames": sweep.n_frames,
            "n_steps": int(len(info.step)), "n_unusable_steps": int((~info.usable_step).sum()),
            "illuminations": sorted(set(info.illumination[info.kind == "light"].tolist())),
            "photon_transfer": None if ptc is None else {
                "gain_dn_per_e": ptc.gain_dn_per_e, "read_var_dn2": ptc.read_var_dn2},
            "full_well_dn": full_well_dn}


def calibrate_paper(sweep: Sweep, *, reference: str | None = None, alpha_limit: float = 5.0,
                    full_well_dn: float | None = None, plateau_tolerance_dn: float | None = None
                    ) -> Calibration:
    """The paper's calibration (section III.C) from exposure sweeps under several illuminations.

    Light steps are grouped by illumination label; each group is an exposure sweep into dynamic
    saturation. Per pixel and illumination: k is the slope of the response against exposure over
    the linear samples (not clipped, below half of the plateau above dark in a first pass, then
    with model alpha under ``alpha_limit`` percent); the saturated level is the mean of the two
    longest exposures, used only if they agree within ``plateau_tolerance_dn`` (default: 4 noise
    sigmas). Then ln k = ln a + b * Y_sat is fitted across illuminations per pixel (weighted
    least squares, vectorised). The dark level at t = 0 (the paper's c) is the mean response at
    the shortest exposure of dark steps if any, else of the shortest light exposure.

    ``reference`` names the illumination whose k is stored as ``k_ref_dn_per_ms`` (default: the
    first in acquisition order).
    """
    means = sweep.step_means()
    h, w = sweep.frame_shape
    fs = sweep.full_scale_dn
    light = means["kind"] == "light"
    labels = list(dict.fromkeys(means["illumination"][light].tolist()))
    groups = [lab for lab in labels
              if len(np.unique(means["exposure_ms"][light & (means["illumination"] == lab)])) >= 3]
    if len(groups) < 2:
        raise DataFormatError(
            f"the paper's method needs exposure sweeps (>= 3 exposures) under at least two "
            f"illuminations to fit a and b; found {len(groups)} ({groups}). Record sweeps under "
            "more light levels or use method='joint'", path=sweep.source or None)
    ptc = photon_transfer(sweep)
    dark_steps = means["kind"] == "dark"
    if dark_steps.any():
        tmin = means["exposure_ms"][dark_steps].min()
        dark = means["data"][dark_steps & (means["exposure_ms"] == tmin)].mean(axis=0)
    else:
        tmin = means["exposure_ms"][light].min()
        dark = means["data"][light & (means["exposure_ms"] == tmin)].mean(axis=0)
    ks, sats, sat_ok = [], [], []
    n_clipped = np.zeros((h, w), np.int32)
    for lab in groups:
        sel = light & (means["illumination"] == lab)
        order = np.argsort(means["exposure_ms"][sel])
        t = means["exposure_ms"][sel][order]
        y = means["data"][sel][order]  # (n, H, W)
        nfr = means["n_frames"][sel][order]
        clipped = _clipped_steps(sweep, means["step"][sel][order], fs)
        if full_well_dn is not None:
            clipped |= y >= full_well_dn
        n_clipped += clipped.sum(axis=0)
        plateau = y[-2:].mean(axis=0)
        noise = np.sqrt((ptc.variance(plateau - dark) if ptc else 1.0) / nfr[-2:].min())
        tol = plateau_tolerance_dn if plateau_tolerance_dn is not None else 4 * np.sqrt(2) * noise
        flat = (np.abs(y[-1] - y[-2]) <= tol) & ~clipped[-2:].any(axis=0)
        use = ~clipped & ((y - dark) < 0.5 * (plateau - dark)) & (t[:, None, None] > 0)
        ks.append(_slope_through(t, y - dark, use))
        sats.append(plateau)
        sat_ok.append(flat)
    ks, sats, sat_ok = np.stack(ks), np.stack(sats), np.stack(sat_ok)
    a, b = _exp_fit(ks, sats, sat_ok)
    # second pass: recompute k from samples with model alpha below the limit
    ks2 = []
    for i, lab in enumerate(groups):
        sel = light & (means["illumination"] == lab)
        order = np.argsort(means["exposure_ms"][sel])
        t = means["exposure_ms"][sel][order]
        y = means["data"][sel][order]
        clipped = _clipped_steps(sweep, means["step"][sel][order], fs)
        alpha = model.leakage_percentage(y, np.maximum(ks[i], 1e-9), a, b)
        use = ~clipped & (alpha < alpha_limit) & (t[:, None, None] > 0)
        use_ok = use.sum(axis=0) >= 2
        ks2.append(np.where(use_ok, _slope_through(t, y - dark, use), ks[i]))
    ks = np.stack(ks2)
    a, b = _exp_fit(ks, sats, sat_ok)
    ref = groups.index(reference) if reference in groups else 0
    k_ref = ks[ref]
    flags = np.zeros((h, w), np.uint32)
    n_pairs = sat_ok.sum(axis=0)
    flags[n_pairs < 2] |= np.uint32(DQ.LEAK_UNCONSTRAINED)
    arrays = {"a_dn_per_ms": a, "b_per_dn": b, "dark_dn": dark, "k_ref_dn_per_ms": k_ref,
              "responsivity": k_ref, "c_ms": model.c_from_dark(np.maximum(k_ref, 1e-9), a, b, dark),
              "saturation_ref_dn": model.dynamic_saturation_level(np.maximum(k_ref, 1e-9), a, b),
              "n_saturation_pairs": n_pairs.astype(np.int32), "n_clipped": n_clipped,
              "flags": flags}
    for i, lab in enumerate(groups):
        arrays[f"k_illum{i}_dn_per_ms"] = ks[i]
    arrays = {k: (v.astype(np.float32) if v.dtype == np.float64 else v) for k, v in arrays.items()}
    usable = means["exposure_ms"] > 0
    domain = {"exposure_ms": [float(means["exposure_ms"][usable].min()),
                              float(means["exposure_ms"][usable].max())],
              "light_rate": [float(np.median(ks.min(axis=0))), float(np.median(ks.max(axis=0)))],
              "light_rate_unit": "DN/ms (median k of the dimmest and brightest illumination)", "bit_depth": sweep.bit_depth,
              "full_scale_dn": fs, "frame_shape": [h, w],
              "mosaic": sweep.mosaic.to_dict() if sweep.mosaic else None}
    fitted = {"source": sweep.source or "in-memory sweep", "n_frames": sweep.n_frames,
              "n_steps": int(len(means["step"])), "illuminations": groups,
              "reference_illumination": groups[ref], "alpha_limit_percent": alpha_limit,
              "full_well_dn": full_well_dn}
    return Calibration(arrays=arrays, domain=domain, method="paper", fitted_on=fitted)


def _clipped_steps(sweep: Sweep, steps, fs) -> np.ndarray:
    return np.stack([(sweep.data[sweep.step == s] >= fs).any(axis=0) for s in steps])


def _slope_through(t, signal, use):
    """Per-pixel least-squares slope of ``signal`` against ``t`` through the origin."""
    tt = t[:, None, None]
    num = np.where(use, tt * signal, 0).sum(axis=0)
    den = np.where(use, tt * tt, 0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, 0.0)


def _exp_fit(ks, sats, ok):
    """Per pixel, fit ln k = ln a + b * Y_sat over the illuminations where ``ok`` (Fig. 4)."""
    lk = np.log(np.maximum(ks, 1e-12))
    wgt = ok.astype(np.float64)
    sw = wgt.sum(axis=0)
    sx, sy = (wgt * sats).sum(axis=0), (wgt * lk).sum(axis=0)
    sxx, sxy = (wgt * sats * sats).sum(axis=0), (wgt * sats * lk).sum(axis=0)
    den = sw * sxx - sx ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        b = (sw * sxy - sx * sy) / den
        ln_a = (sy - b * sx) / sw
    good = (sw >= 2) & np.isfinite(b) & (b > 0)
    b_fill = np.nanmedian(np.where(good, b, np.nan)) if good.any() else 0.01
    a_fill = np.nanmedian(np.where(good, ln_a, np.nan)) if good.any() else -10.0
    return np.exp(np.where(good, ln_a, a_fill)), np.where(good, b, b_fill)
