"""Linear model against leakage model on a real EMVA 1288 sweep: the analysis (numbers only).

See :mod:`hsiffc.reports.emva_leakage` for the definitions."""


from __future__ import annotations


import numpy as np

from ...files.jsonsafe import json_safe
from ... import __version__
from ...leakage import model
from ...calibrate import (LEAKAGE_ACCOUNT, Calibration, calibrate, collect_samples,
                         photon_transfer)
from ...errors import CalibrationMismatchError, DataFormatError

__all__ = ["BIN_WIDTH_DN", "analyse_emva_leakage", "fit_linear", "sweep_steps_only"]

N_TOP_STEPS = 10  # brightest light steps of the roll-off test
# observed / linear rise over those steps below this: levels off. A linear pixel has a ratio of
# 1 with a noise of about 0.07 on this sweep, so 0.75 is more than 3 sigma away from it
ROLL_OFF_RATIO = 0.75
FULL_SCALE_MARGIN_DN = 1.0
PLATEAU_STEPS = 5  # brightest light steps averaged into the plateau
SIGNAL_EDGES_DN = (20.0, 100.0, 200.0)  # light samples split by signal above dark
BIN_WIDTH_DN = 5.0  # residual-against-signal curves
PCTS = (5, 25, 50, 75, 95)
ROLES = ("levels off (low plateau)", "levels off (median plateau)", "typical, clips at 255",
         "median pixel")


def sweep_steps_only(sweep):
    """The sweep steps of an EMVA 1288 sweep (its spatial flat/dark stacks left out).

    Sweeps without ``meta["sweep_steps"]`` are returned unchanged.
    """
    steps = sweep.meta.get("sweep_steps")
    return sweep if steps is None else sweep.select(np.isin(sweep.step, steps))


def fit_linear(photons, y, weight):
    """Weighted least-squares line ``y = d + g * photons`` for every pixel at once.

    Closed-form normal equations on centred photon counts; no loop over pixels.

    Parameters
    ----------
    photons : (S,) or (S, P) array
        Photons per pixel of each sample (0 for dark samples).
    y : (S, P) array
        Responses (DN).
    weight : (S, P) array
        Weight of each sample; 0 leaves it out.

    Returns
    -------
    d, g : (P,) arrays
        Offset (DN) and gain (DN per photon); NaN where the weighted samples span fewer than two
        photon values.

    Examples
    --------
    >>> x = np.array([0.0, 10.0, 20.0, 30.0])
    >>> d, g = fit_linear(x, np.column_stack([2 + 0.5 * x, 1 - x]), np.ones((4, 2)))
    >>> np.round(d, 6).tolist(), np.round(g, 6).tolist()
    ([2.0, 1.0], [0.5, -1.0])
    """
    y = np.asarray(y, np.float64)
    x = np.broadcast_to(np.asarray(photons, np.float64).reshape(len(y), -1), y.shape)
    ok = np.isfinite(x) & np.isfinite(y)
    w = np.where(ok, np.asarray(weight, np.float64), 0.0)
    x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sw = w.sum(axis=0)
        xm = (w * x).sum(axis=0) / sw
        ym = (w * y).sum(axis=0) / sw
        xc = x - xm
        sxx = (w * xc * xc).sum(axis=0)
        g = (w * xc * (y - ym)).sum(axis=0) / sxx
        g = np.where(sxx > 1e-12 * np.maximum(sw * xm * xm, 1e-300), g, np.nan)
    return ym - g * xm, g


def _stats(v) -> dict:
    v = np.asarray(v, np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"n": 0}
    p = np.percentile(v, PCTS)
    return {"n": int(v.size), "mean": float(v.mean()), "median_abs": float(np.median(np.abs(v))),
            "min": float(v.min()), "max": float(v.max()),
            **{f"p{q}": float(x) for q, x in zip(PCTS, p)}}


def _rms(res, mask) -> float | None:
    r = res[mask]
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else None


def _binned(x, v, edges, min_count=50) -> dict:
    """Median and quartiles of ``v`` in bins of ``x`` (one radix sort by bin, no sample loop)."""
    b = np.digitize(x, edges) - 1
    keep = (b >= 0) & (b < len(edges) - 1) & np.isfinite(v)
    b, v = b[keep].astype(np.int16), v[keep]
    v = v[np.argsort(b, kind="stable")]
    counts = np.bincount(b, minlength=len(edges) - 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = {"center": [], "median": [], "q25": [], "q75": [], "n": []}
    for i, (s, n) in enumerate(zip(starts, counts)):
        if n < min_count:
            continue
        q25, q50, q75 = np.percentile(v[s:s + n], [25, 50, 75])
        out["center"].append(float(0.5 * (edges[i] + edges[i + 1])))
        out["q25"].append(float(q25))
        out["median"].append(float(q50))
        out["q75"].append(float(q75))
        out["n"].append(int(n))
    return out


def _step_median(v, valid):
    """Median over pixels of each step's valid samples, (S, 1); NaN for steps without any."""
    out = np.full((len(v), 1), np.nan)
    rows = valid.any(axis=1)
    out[rows, 0] = np.nanmedian(np.where(valid[rows], v[rows], np.nan), axis=1)
    return out


def _most_typical(mask, *features) -> int:
    """Index of the pixel in ``mask`` closest to the medians of ``features`` (robust z)."""
    idx = np.flatnonzero(mask)
    score = np.zeros(idx.size)
    for f in features:
        f = np.asarray(f, np.float64)[idx]
        med = np.nanmedian(f)
        mad = 1.4826 * np.nanmedian(np.abs(f - med)) or 1.0
        score += np.nan_to_num((f - med) / mad, nan=1e9) ** 2
    return int(idx[np.argmin(score)])


def analyse_emva_leakage(sweep, calibration: Calibration | None = None, *,
                         n_example_pixels: int = 4) -> dict:
    """Compare the linear model (eq. 1) with the leakage model on an EMVA 1288 sweep.

    Parameters
    ----------
    sweep : Sweep
        An EMVA 1288 sweep with photon counts; only its sweep steps are used.
    calibration : Calibration, optional
        Leakage-model calibration of the same sensor region; default: ``calibrate(sweep,
        method="joint")`` on the sweep steps.
    n_example_pixels : int
        Example pixels to keep (1 to 4, in the order of ``ROLES``).

    Returns
    -------
    dict
        JSON-safe figures: sample and pixel counts, RMS errors (pooled over samples and median
        of per-pixel values) overall, for the pixels that level off below full scale, and by
        signal range; fitted saturation levels against plateaus; binned residuals against
        signal; the example pixels' data and model curves.

    Raises
    ------
    DataFormatError
        The sweep has no photon counts for its light steps.
    CalibrationMismatchError
        The calibration is for another frame size.
    """
    if not 1 <= n_example_pixels <= len(ROLES):
        raise ValueError(f"n_example_pixels must be 1 to {len(ROLES)}, got {n_example_pixels}")
    sweep = sweep_steps_only(sweep)
    if calibration is None:
        # what the leakage model explains: each pixel's, wherever its samples earn it (no
        # held-out choice of a simpler model, which a correction would make)
        calibration = calibrate(sweep, method="joint", **LEAKAGE_ACCOUNT)
    if tuple(calibration.domain.get("frame_shape", ())) != tuple(sweep.frame_shape):
        raise CalibrationMismatchError(
            f"the calibration is for frames {calibration.domain.get('frame_shape')}, the sweep "
            f"has {list(sweep.frame_shape)}")
    smp = collect_samples(sweep, full_well_dn=calibration.fitted_on.get("full_well_dn"))
    usable, light = smp.usable_step, smp.kind == "light"
    if smp.rate_unit != "photons/ms":
        raise DataFormatError("the linear model of photons needs photon counts per light step "
                              "(an EMVA 1288 sweep)", path=sweep.source or None)
    t = np.where(usable, smp.exposure_ms, 1.0)
    rate = np.where(usable, smp.rate, 0.0)
    photons = rate * t
    fs = smp.full_scale_dn
    y = smp.y.astype(np.float64)
    valid = smp.valid
    h, w = smp.frame_shape

    # weights of the leakage fit: frames per step / photon-transfer variance of the step mean
    ptc = calibration.fitted_on.get("photon_transfer")
    if ptc is None:
        p = photon_transfer(sweep)
        ptc = None if p is None else {"gain_dn_per_e": p.gain_dn_per_e,
                                      "read_var_dn2": p.read_var_dn2}
    dark_steps = (smp.kind == "dark") & usable
    dark0 = np.median(y[dark_steps], axis=0) if dark_steps.any() else y.min(axis=0)
    var = (ptc["gain_dn_per_e"] * np.maximum(y - dark0, 0.0) + ptc["read_var_dn2"]
           if ptc else np.ones_like(y))
    weight = np.where(valid, smp.n_frames[:, None] / var, 0.0)
    d_lin, g_lin = fit_linear(photons, y, weight)
    y_lin = d_lin + g_lin * photons[:, None]

    arr = {k: np.asarray(calibration.arrays[k], np.float64).ravel()
           for k in ("responsivity", "a_dn_per_ms", "b_per_dn", "dark_dn", "saturation_ref_dn")}
    dc = np.asarray(calibration.arrays.get("dark_current_dn_per_ms", np.zeros((h, w))),
                    np.float64).ravel()
    k = arr["responsivity"] * rate[:, None] + dc
    y_leak = model.response(t[:, None], k, arr["a_dn_per_ms"], arr["b_per_dn"], arr["dark_dn"])
    res_lin = np.where(valid, y_lin - y, np.nan)
    res_leak = np.where(valid, y_leak - y, np.nan)

    # pixels that level off below full scale
    never_clipped = ~(smp.clipped & usable[:, None]).any(axis=0)
    y_max = np.where(valid, y, -np.inf).max(axis=0)
    below = y_max < fs - FULL_SCALE_MARGIN_DN
    by_photons = np.flatnonzero(light & usable)[np.argsort(photons[light & usable])]
    top = by_photons[-N_TOP_STEPS:]
    span = photons[top].max() - photons[top].min()
    _, slope_top = fit_linear(photons[top], y[top], valid[top])
    rise_ratio = slope_top / g_lin
    xt = photons[top] - photons[top].mean()
    noise_var = var / smp.n_frames[:, None]  # expected temporal variance of a step mean
    rise_ratio_sigma = np.sqrt(noise_var[top].mean(axis=0) / (xt * xt).sum()) / g_lin
    levels_off = never_clipped & below & (rise_ratio < ROLL_OFF_RATIO)
    clips = ~never_clipped

    # saturation levels against plateaus
    plat = by_photons[-PLATEAU_STEPS:]
    plateau = np.where(valid[plat].all(axis=0), y[plat].mean(axis=0), np.nan)
    k_plat = arr["responsivity"] * rate[plat].mean() + dc
    sat_plat = model.dynamic_saturation_level(np.maximum(k_plat, 1e-300), arr["a_dn_per_ms"],
                                              arr["b_per_dn"])
    lo = levels_off
    saturation = {
        "plateau_steps": [int(s) for s in smp.step[plat]],
        "plateau_dn": _stats(plateau[lo]), "max_step_mean_dn": _stats(y_max[lo]),
        "ref_minus_plateau_dn": _stats(arr["saturation_ref_dn"][lo] - plateau[lo]),
        "ref_minus_max_step_mean_dn": _stats(arr["saturation_ref_dn"][lo] - y_max[lo]),
        "at_plateau_rate_minus_plateau_dn": _stats(sat_plat[lo] - plateau[lo]),
        "model_minus_plateau_dn": _stats(y_leak[plat][:, lo].mean(axis=0) - plateau[lo]),
        "linear_minus_plateau_dn": _stats(y_lin[plat][:, lo].mean(axis=0) - plateau[lo]),
        # near saturation dY/dt = k (1 - exp(-b (Ys - Y))): a pixel still rising at a fraction f
        # of its linear slope lies -ln(1 - f) / b below saturation (model-light cross-check)
        "gap_from_remaining_slope_dn": _stats(
            -np.log1p(-np.clip(rise_ratio[lo], 0.0, 0.999)) / arr["b_per_dn"][lo]),
        "clipping_pixels_saturation_ref_dn": _stats(arr["saturation_ref_dn"][clips]),
        "brightest_rate_photons_per_ms": float(rate[usable].max()),
        "plateau_rate_photons_per_ms": float(rate[plat].mean()),
    }

    # RMS: pooled over samples and median of per-pixel values
    pix = {"all": np.ones(h * w, bool), "levels_off": lo, "not_levels_off": ~lo,
           "clipping": clips}
    rms = {}
    for name, pm in pix.items():
        m = valid & pm[None, :]
        per_lin = np.sqrt(np.nanmean(res_lin[:, pm] ** 2, axis=0))
        per_leak = np.sqrt(np.nanmean(res_leak[:, pm] ** 2, axis=0))
        rms[name] = {"n_pixels": int(pm.sum()), "n_samples": int(m.sum()),
                     "linear_dn": _rms(res_lin, m), "leakage_dn": _rms(res_leak, m),
                     "linear_median_pixel_dn": float(np.median(per_lin)) if pm.any() else None,
                     "leakage_median_pixel_dn": float(np.median(per_leak)) if pm.any() else None}
    signal = y - arr["dark_dn"]
    edges = (-np.inf, *SIGNAL_EDGES_DN, np.inf)
    ranges = [("dark steps", dark_steps[:, None] & valid)]
    for lo_e, hi_e in zip(edges[:-1], edges[1:]):
        lab = (f"light, < {hi_e:g} DN" if lo_e == -np.inf else
               f"light, >= {lo_e:g} DN" if hi_e == np.inf else f"light, {lo_e:g}-{hi_e:g} DN")
        ranges.append((lab, valid & (light & usable)[:, None] & (signal >= lo_e) & (signal < hi_e)))
    # residual common to all pixels in a step (median over pixels): illumination / photon-count
    # errors or a sensor-wide non-linearity, as opposed to pixel-to-pixel differences
    cm_lin, cm_leak = _step_median(res_lin, valid), _step_median(res_leak, valid)
    by_range = []
    for lab, m in ranges:
        for pname, pm in (("all", pix["all"]), ("levels_off", lo)):
            mm = m & pm[None, :]
            by_range.append({
                "range": lab, "pixels": pname, "n_samples": int(mm.sum()),
                "linear_rms_dn": _rms(res_lin, mm), "leakage_rms_dn": _rms(res_leak, mm),
                "noise_rms_dn": float(np.sqrt(np.mean(noise_var[mm]))) if mm.any() else None,
                "linear_bias_dn": float(np.nanmean(res_lin[mm])) if mm.any() else None,
                "leakage_bias_dn": float(np.nanmean(res_leak[mm])) if mm.any() else None,
                "linear_rms_without_step_common_dn": _rms(res_lin - cm_lin, mm),
                "leakage_rms_without_step_common_dn": _rms(res_leak - cm_leak, mm)})

    bins = np.arange(-BIN_WIDTH_DN, fs + BIN_WIDTH_DN, BIN_WIDTH_DN)
    binned = {}
    for pname, pm in (("all", pix["all"]), ("levels_off", lo)):
        m = valid & pm[None, :]
        binned[pname] = {"linear": _binned(signal[m], res_lin[m], bins),
                         "leakage": _binned(signal[m], res_leak[m], bins)}
    step_common = {"photons": photons[usable], "kind": smp.kind[usable].tolist(),
                   "signal_dn": _step_median(signal, valid)[usable, 0],
                   "linear_dn": cm_lin[usable, 0], "leakage_dn": cm_leak[usable, 0]}

    # example pixels
    plateau_lo = np.where(lo, plateau, np.nan)
    picks = []
    if lo.any():
        q10 = np.nanpercentile(plateau_lo, 10)
        picks.append(int(np.nanargmin(np.abs(plateau_lo - q10))))
        picks.append(_most_typical(lo, plateau, rise_ratio))
    else:
        picks += [None, None]
    picks.append(_most_typical(clips, g_lin, (smp.clipped & usable[:, None]).sum(axis=0))
                 if clips.any() else None)
    rms_lin_px = np.sqrt(np.nanmean(res_lin ** 2, axis=0))
    rms_leak_px = np.sqrt(np.nanmean(res_leak ** 2, axis=0))
    picks.append(_most_typical(np.ones(h * w, bool), g_lin, rms_lin_px, rms_leak_px))
    curve = light & usable
    order = np.flatnonzero(curve)[np.argsort(photons[curve])]
    examples = []
    for role, p in list(zip(ROLES, picks))[:n_example_pixels]:
        if p is None:
            continue
        v = valid[order, p]
        examples.append({
            "role": role, "row": p // w, "col": p % w, "photons": photons[order].round(2),
            "y_dn": np.where(v, y[order, p], np.nan).round(3),
            "clipped": smp.clipped[order, p], "linear_dn": y_lin[order, p].round(3),
            "leakage_dn": y_leak[order, p].round(3), "dark_dn": arr["dark_dn"][p],
            "linear_rms_dn": rms_lin_px[p], "leakage_rms_dn": rms_leak_px[p],
            "saturation_ref_dn": arr["saturation_ref_dn"][p], "plateau_dn": plateau[p],
            "levels_off": bool(lo[p]), "rise_ratio": rise_ratio[p]})

    criterion = {
        "text": (f"never clipped in any usable step, highest step mean < "
                 f"{fs - FULL_SCALE_MARGIN_DN:g} DN, and over the {N_TOP_STEPS} brightest light "
                 f"steps a rise (LS slope x photon span) < {ROLL_OFF_RATIO:g} x the pixel's own "
                 "linear-fit rise"),
        "n_top_steps": N_TOP_STEPS, "photon_span_top_steps": float(span),
        "roll_off_ratio": ROLL_OFF_RATIO, "full_scale_margin_dn": FULL_SCALE_MARGIN_DN,
        "n_never_clipped": int(never_clipped.sum()),
        "n_never_clipped_below_margin": int((never_clipped & below).sum()),
        "n_levels_off": int(lo.sum()),
        "n_never_clipped_below_margin_but_linear": int((never_clipped & below & ~lo).sum()),
        "rise_ratio_levels_off": _stats(rise_ratio[lo]),
        "rise_ratio_noise_sigma": _stats(rise_ratio_sigma[never_clipped & below]),
        "rise_ratio_never_clipped_below_margin": _stats(rise_ratio[never_clipped & below]),
    }
    return json_safe({
        "source": sweep.source, "hsiffc_version": __version__,
        "frame_shape": [h, w], "n_pixels": h * w, "full_scale_dn": fs,
        "n_steps": int(usable.sum()), "n_light_steps": int((light & usable).sum()),
        "n_dark_steps": int(dark_steps.sum()), "n_valid_samples": int(valid.sum()),
        "calibration_method": calibration.method,
        "residual": "model - data (DN), on step means",
        "linear_model": "Y = d + g * photons (paper eq. 1), weighted LS per pixel, closed form",
        "weights": ("same as the leakage fit: frames per step / (K * max(Y - dark, 0) + read "
                    "variance), K and read variance from the photon transfer curve"),
        "photon_transfer": ptc,
        "linear_gain_dn_per_photon": _stats(g_lin), "linear_offset_dn": _stats(d_lin),
        "leakage_b_per_dn": _stats(arr["b_per_dn"]), "leakage_dark_dn": _stats(arr["dark_dn"]),
        "criterion": criterion, "rms": rms, "rms_by_signal": by_range,
        "saturation": saturation, "binned_residual": binned, "step_common_residual": step_common,
        "examples": examples,
    })


