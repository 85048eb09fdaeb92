"""The paper's calibration (section III.C) from exposure sweeps under several illuminations."""

from __future__ import annotations

import numpy as np

from ..leakage import model
from ..data.dq import DQ
from ..errors import DataFormatError
from ..data.sweep import Sweep
from .product import Calibration
from .samples import photon_transfer


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

    Parameters
    ----------
    sweep : Sweep
        Exposure sweeps (>= 3 exposures each) into dynamic saturation under at least two
        illuminations (``sweep.illumination`` labels), ideally with dark steps.
    reference : str, optional
        The illumination whose k is stored as ``k_ref_dn_per_ms`` (default: the first in
        acquisition order).
    alpha_limit : float, percent
        Samples with model alpha above it are left out of the slope (second pass).
    full_well_dn : float, optional, DN
        Step means at or above it are not used.
    plateau_tolerance_dn : float, optional, DN
        Largest difference between the two longest exposures for a saturated level (default:
        4 noise sigmas from the photon transfer curve).

    Returns
    -------
    Calibration
        ``method="paper"``; per-pixel (H, W) ``dark_dn``, ``a_dn_per_ms``, ``b_per_dn``,
        ``k_ref_dn_per_ms``, ``saturation_ref_dn`` and flags.

    Raises
    ------
    DataFormatError
        Fewer than two illuminations with an exposure sweep (the message says what to record).
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
              "n_steps": len(means["step"]), "illuminations": groups,
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
