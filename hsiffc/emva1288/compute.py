"""EMVA 1288 Release 4.0 figures of a sweep, computed the way the standard's reference
implementation (``emva1288`` on PyPI/GitHub) computes them: the numbers only.

What is computed, in the order of the computation (``u_`` is a mean, ``s2_`` a variance):

*Step statistics.* For every sweep step (two frames in the standard) the mean ``u_y`` over the
pixels and the temporal variance ``s2_y = 1/(2 N) sum ((A - B) - mean(A - B))^2`` of the
difference of its two frames A and B with the difference of their means taken out (Release 4.0;
with L frames: the per-pixel variance over the frames, each frame less its own spatial mean,
averaged over the pixels). Light steps are ordered by exposure, then photons; each gets the
statistics of the dark step at its exposure (``u_ydark``, ``s2_ydark``); with one exposure the
one dark step serves every light step.

*Saturation.* ``index_u_ysat``: the light step where the temporal variance peaks, searched from
the brightest step down (the first peak met from above, as the reference does, so that noise
spikes at low signal are skipped). ``u_p_sat`` is its photon count, ``u_e_sat = QE u_p_sat``.

*Sensitivity fit range.* From the first light step up to the last whose dark-subtracted mean
is at most 70 % of the one at saturation. ``R`` is the slope of ``u_y - u_ydark`` against
``u_p`` and ``K`` the slope of ``s2_y - s2_ydark`` against ``u_y - u_ydark``, both lines
through the origin (least squares). ``QE = R / K``.

*Temporal dark noise.* ``s2_ydark`` of the first dark step when the sweep has at most two
exposures, else the intercept of a line through ``s2_ydark`` against exposure; at least
0.24 DN^2 (below it quantisation dominates; the standard then uses 0.49 DN).
``sigma_d = sqrt(sigma_y_dark^2 - 1/12) / K``.
Sensitivity threshold ``u_p_min = (sigma_y_dark / K + 1/2) / QE``; ``DR = u_p_sat / u_p_min``;
``SNR_max = sqrt(u_e_sat)``.

*Linearity.* Fit range from the first light step at or above 5 % of the saturation signal to
the last at or below 95 %; a line ``a u_p + b`` fitted with relative weights (minimising
``sum ((Y - a u_p - b) / Y)^2``, ``Y = u_y - u_ydark``); the linearity error is the relative
deviation ``100 (Y - fit) / fit`` in percent, ``LE_min``/``LE_max`` its extremes over the range.

*Dark current* (only with more than two exposures): slope of ``u_ydark`` against exposure over K
(``u_I_mean``, e-/s) and slope of ``s2_ydark`` over K^2 (``u_I_var``; NaN if the slope is
negative). Exposures are converted to seconds from the sweep's milliseconds, which the EMVA 1288
reader converted from the descriptor's nanoseconds.

*Spatial nonuniformity* from the stacks of many frames (one light, one dark step at one
exposure): ``s2 = var(mean image, ddof=1) - mean(per-pixel temporal variance) / L``;
``DSNU1288_DN = sqrt(s2_dark)``, ``DSNU1288 = DSNU1288_DN / K``,
``PRNU1288 = 100 sqrt(s2_light - s2_dark) / (u_light - u_dark)``.

Standard errors: the regression standard error (1 sigma) of each fitted slope or intercept
(``K``, ``R``, ``sigma_y_dark`` when it is an intercept, the dark currents); ``QE`` and the
figures derived from them by first-order propagation. The reference implementation reports none.
"""

from __future__ import annotations

import math

import numpy as np

from ..data.mosaic import wavelength_order
from ..errors import DataFormatError, ParameterError

__all__ = ["FIGURES", "SPLIT_FIGURES", "QUANTISATION_VARIANCE", "characterise",
           "step_statistics", "figures_from_statistics", "saturation_index"]

QUANTISATION_VARIANCE = 1.0 / 12.0  # DN^2
MIN_DARK_VARIANCE = 0.24  # DN^2: the standard's floor of s2_ydark (quantisation dominates below)
SENSITIVITY_FRACTION = 0.70
LINEARITY_RANGE = (0.05, 0.95)

#: name -> unit, in the order of the reference implementation's report
FIGURES = {
    "K": "DN/e-", "R": "DN/p", "QE": "%", "sigma_y_dark": "DN", "sigma_d": "e-",
    "DSNU1288_DN": "DN", "DSNU1288": "e-", "PRNU1288": "%", "LE_min": "%", "LE_max": "%",
    "u_p_sat": "p", "u_e_sat": "e-", "SNR_max": "1", "SNR_max_dB": "dB", "DR": "1",
    "DR_dB": "dB", "u_p_min": "p", "u_e_min": "e-", "u_I_mean": "e-/s", "u_I_var": "e-/s",
}
#: Release 4.0 figures beyond the reference's classic set: the mean linearity error and the
#: split of DSNU and PRNU into row, column and pixel parts (:mod:`.spatial`)
SPLIT_FIGURES = {
    "LE_mean": "%", "DSNU1288_row": "e-", "DSNU1288_col": "e-", "DSNU1288_pixel": "e-",
    "DSNU1288_row_DN": "DN", "DSNU1288_col_DN": "DN", "DSNU1288_pixel_DN": "DN",
    "PRNU1288_row": "%", "PRNU1288_col": "%", "PRNU1288_pixel": "%", "PRNU1288_highpass": "%",
}
#: figures per unit area, given the pixel area
AREA_FIGURES = {"u_p_sat_area": ("u_p_sat", "p/um^2"), "u_e_sat_area": ("u_e_sat", "e-/um^2"),
                "u_p_min_area": ("u_p_min", "p/um^2"), "u_e_min_area": ("u_e_min", "e-/um^2")}
PLANCK_J_S = 6.62607015e-34
LIGHT_M_S = 299792458.0


# -- step statistics ---------------------------------------------------------------------------
def step_statistics(source, *, mosaic_bands: bool = True, keep_step_means=False) -> dict:
    """Mean and temporal variance of every step, over the whole frame and per band, and the
    spatial statistics of the stacks, read one frame at a time (:mod:`.stream`).

    Parameters
    ----------
    source : Sweep or FrameSource
        An EMVA 1288 measurement (:func:`hsiffc.io.read_emva1288`, or
        :func:`hsiffc.io.open_source` on its descriptor to stream it): light steps with photon
        counts, dark steps, optionally a spatial stack (one light and one dark step with many
        frames, listed in ``meta["spatial_steps"]`` or found as steps with more than twice the
        median frames per step).
    mosaic_bands : bool
        Also per band when the measurement has a mosaic.
    keep_step_means : bool or array of int
        Keep the per-pixel step means (for the leakage calibration); given pixels (flat
        indices), their means only.

    Returns
    -------
    dict
        :func:`~hsiffc.emva1288.stream.reduce_frames`, each group with its ``spatial``
        statistics of the light and dark stack (or None) and ``spatial_note`` saying why
        they are missing.
    """
    from .spatial import spatial_group
    from .stream import reduce_frames

    stats = reduce_frames(source, mosaic_bands=mosaic_bands, keep_step_means=keep_step_means)
    info, images = stats["steps"], stats["images"]
    stats["spatial_note"] = None
    if images is None:
        n_light, n_dark = stats["spatial_counts"]
        stats["spatial_note"] = (f"no spatial stack (one light and one dark step with many "
                                 f"frames): found {n_light} light and {n_dark}; DSNU and PRNU "
                                 "not computed")
    bmap = None if stats["band_map"] is None else stats["band_map"].ravel()
    for g in stats["groups"]:
        g["spatial"] = None
        if images is None:
            continue
        mask = None if g["band"] is None else bmap == g["band"]
        il = int(np.flatnonzero(info["step"] == images["light"]["step"])[0])
        gi = 0 if g["band"] is None else g["band"] + 1
        g["spatial"] = {"light": spatial_group(images["light"], mask, gi),
                        "dark": spatial_group(images["dark"], mask, gi),
                        "step_light": int(images["light"]["step"]),
                        "step_dark": int(images["dark"]["step"]),
                        "exposure_ms": float(info["exposure_ms"][il]),
                        "photons": float(info["photons"][il])}
    return stats


# -- fits --------------------------------------------------------------------------------------
def _slope0(x, y) -> tuple[float, float]:
    """Least-squares slope of a line through the origin and its standard error."""
    sxx = float((x * x).sum())
    if not sxx > 0:  # every x is 0: no slope (the caller says why in one line)
        return float("nan"), float("nan")
    m = float((x * y).sum()) / sxx
    n = len(x)
    se = math.sqrt(float(((y - m * x) ** 2).sum()) / (n - 1) / sxx) if n > 1 else float("nan")
    return m, se


def _line(x, y) -> tuple[float, float, float, float]:
    """Least-squares line ``y = m x + c``: m, c and their standard errors."""
    n = len(x)
    xm, ym = float(x.mean()), float(y.mean())
    sxx = float(((x - xm) ** 2).sum())
    m = float(((x - xm) * (y - ym)).sum()) / sxx
    c = ym - m * xm
    if n > 2:
        s2 = float(((y - m * x - c) ** 2).sum()) / (n - 2)
        return m, c, math.sqrt(s2 / sxx), math.sqrt(s2 * (1.0 / n + xm * xm / sxx))
    return m, c, float("nan"), float("nan")


def saturation_index(s2_y) -> int:
    """Index of the saturation point: the temporal-variance peak met first from the brightest
    step down. Walking down, the candidate moves while the variance of the step or of the one
    below it is at least the current candidate's; it stops where both are below it."""
    s2_y = np.asarray(s2_y, np.float64)
    best, best_i = 0.0, 0
    for i in range(len(s2_y) - 1, -1, -1):
        below = s2_y[abs(i - 1)]
        if s2_y[i] >= best or below >= best:
            best, best_i = float(s2_y[i]), i
        else:
            break
    return best_i


def relative_fit(x, y) -> tuple[float, float]:
    """Line ``y = a x + b`` minimising ``sum(((y - a x - b) / y)^2)`` (relative deviations)."""
    w = 1.0 / y
    sw2 = float((w * w).sum())
    sxw2 = float((x * w * w).sum())
    sx2w2 = float((x * x * w * w).sum())
    syw2 = float((y * w * w).sum())  # = sum(w)
    sxyw2 = float((x * y * w * w).sum())
    det = sx2w2 * sw2 - sxw2 * sxw2
    a = (sxyw2 * sw2 - syw2 * sxw2) / det
    b = (sx2w2 * syw2 - sxw2 * sxyw2) / det
    return a, b


def _temporal_arrays(info: dict, mean, var, where: str) -> dict:
    """Light steps in the reference order with the dark statistics at their exposures."""
    sweep_steps = ~info["spatial"]
    light = np.flatnonzero(sweep_steps & (info["kind"] == "light"))
    dark = np.flatnonzero(sweep_steps & (info["kind"] == "dark"))
    if light.size < 3:
        raise DataFormatError(f"{light.size} light sweep steps; EMVA 1288 needs a sweep of light "
                              "steps (50 or more in the standard) with dark steps", path=where)
    photons = info["photons"][light]
    if not np.all(np.isfinite(photons)):
        raise DataFormatError("light steps without photon counts; EMVA 1288 figures need the "
                              "mean photons per pixel of every light step ('b EXPOSURE PHOTONS' "
                              "lines)", path=where)
    if np.any(photons < 0) or not np.any(photons > 0):
        raise DataFormatError("the light steps' photon counts are all 0 or some are negative; "
                              "give the mean photons per pixel of every light step "
                              "('b EXPOSURE PHOTONS' lines), > 0 for a lit step", path=where)
    if dark.size == 0:
        raise DataFormatError("no dark sweep step; EMVA 1288 needs a dark step at every exposure "
                              "of the light steps", path=where)
    order = light[np.lexsort((photons, info["exposure_ms"][light]))]
    texp = np.unique(info["exposure_ms"][dark])
    u_ydark = np.array([mean[dark][info["exposure_ms"][dark] == t].mean() for t in texp])
    s2_ydark = np.array([var[dark][info["exposure_ms"][dark] == t].mean() for t in texp])
    t_light = info["exposure_ms"][order]
    if len(texp) == 1:
        at = np.zeros(len(order), int)
    else:
        missing = sorted(set(t_light.tolist()) - set(texp.tolist()))
        if missing:
            raise DataFormatError(f"no dark step at exposure(s) {missing[:5]} ms of light steps; "
                                  "EMVA 1288 subtracts the dark step of the same exposure: "
                                  "record one for each", path=where)
        at = np.searchsorted(texp, t_light)
    return {"order": order, "step": info["step"][order], "u_p": info["photons"][order],
            "texp_ms": t_light, "u_y": mean[order], "s2_y": var[order],
            "u_ydark": u_ydark[at], "s2_ydark": s2_ydark[at],
            "dark_texp_ms": texp, "dark_u_y": u_ydark, "dark_s2_y": s2_ydark}


def figures_from_statistics(info: dict, group: dict, *, where: str = "",
                            pixel_area_um2: float | None = None,
                            wavelength_nm: float | None = None, images: dict | None = None
                            ) -> dict:
    """The EMVA 1288 figures of one pixel group from its step statistics.

    Parameters
    ----------
    info : dict
        ``steps`` of :func:`step_statistics`.
    group : dict
        One entry of its ``groups``.
    where : str
        Names the data in error messages.
    pixel_area_um2, wavelength_nm : float, optional
        See :func:`characterise`.
    images : dict, optional
        The stacks' images (``images`` of :func:`step_statistics`): adds the row, column and
        pixel parts of DSNU and PRNU and the high-pass PRNU (whole frame only).

    Returns
    -------
    dict
        ``figures`` (name -> ``{"value", "unit", "se"}``), ``fit_ranges``, ``curves`` (the
        arrays the plots need), ``notes`` and, with ``images``, ``nonuniformity`` (the
        variances of the split, DN^2).
    """
    ta = _temporal_arrays(info, group["mean_dn"], group["var_dn2"], where)
    u_p, u_y, s2_y = ta["u_p"], ta["u_y"], ta["s2_y"]
    y = u_y - ta["u_ydark"]
    v = s2_y - ta["s2_ydark"]
    notes = []
    isat = saturation_index(s2_y)
    ysat = y[isat]
    top = int(np.argmax(s2_y))
    if s2_y[top] > s2_y[isat]:
        notes.append(f"the temporal variance peaks higher at light step {top} ({s2_y[top]:.4g} "
                     f"DN^2) than at the saturation point the standard's search finds from the "
                     f"brightest step down (step {isat}, {s2_y[isat]:.4g} DN^2): a plateau or "
                     "noise near the top stopped it early (a pixel that levels off without "
                     "clipping keeps a variance); the figures use step "
                     f"{isat}, as the reference implementation does")
    if not np.any(s2_y > 0):
        raise DataFormatError("every light step has a temporal variance of 0 DN^2: the frames "
                              "of each step are identical (copies of one frame?) or all clipped "
                              "(every step saturated); EMVA 1288 needs two independent frames "
                              "per step, from dark to saturation", path=where)
    below = np.flatnonzero(y <= SENSITIVITY_FRACTION * ysat)
    if not ysat > 0 or below.size == 0:
        raise DataFormatError(f"no light step lies below {SENSITIVITY_FRACTION:.0%} of the "
                              f"saturation signal ({ysat:.4g} DN above dark): every step is "
                              "saturated, or none is above the dark level; record steps from "
                              "dark to saturation", path=where)
    isens = int(below.max())
    sl = slice(0, isens + 1)
    R, R_se = _slope0(u_p[sl], y[sl])
    K, K_se = _slope0(y[sl], v[sl])
    if not (R > 0 and K > 0):
        raise DataFormatError(f"the photon transfer gives responsivity R = {R:.4g} DN/p and "
                              f"gain K = {K:.4g} DN/e-: the signal or its variance does not rise "
                              "with the light below saturation; check the photon counts and "
                              "that the steps span dark to saturation", path=where)
    qe = R / K
    qe_se = abs(qe) * math.hypot(R_se / R, K_se / K)

    texp_s = ta["dark_texp_ms"] / 1e3
    many = len(texp_s) > 2
    if many:
        m_v, c_v, m_v_se, c_v_se = _line(texp_s, ta["dark_s2_y"])
        s2_dark, s2_dark_se = c_v, c_v_se
    else:
        s2_dark, s2_dark_se = float(ta["dark_s2_y"][0]), float("nan")
    clamped = s2_dark < MIN_DARK_VARIANCE
    if clamped:
        notes.append(f"temporal dark variance {s2_dark:.4g} DN^2 is below the standard's floor "
                     f"{MIN_DARK_VARIANCE} DN^2 (quantisation dominates): sigma_y_dark = "
                     f"sqrt({MIN_DARK_VARIANCE}) DN")
        s2_dark, s2_dark_se = MIN_DARK_VARIANCE, float("nan")
    sy = math.sqrt(s2_dark)
    sy_se = s2_dark_se / (2 * sy)
    sigma_d = math.sqrt(s2_dark - QUANTISATION_VARIANCE) / K
    sigma_d_se = sigma_d * math.hypot(s2_dark_se / (2 * (s2_dark - QUANTISATION_VARIANCE)),
                                      K_se / K)
    u_p_min = (sy / K + 0.5) / qe
    u_p_sat = float(u_p[isat])
    u_e_sat = qe * u_p_sat
    u_e_min = qe * u_p_min
    snr_max = math.sqrt(u_e_sat)
    dr = u_p_sat / u_p_min

    lo = int(np.flatnonzero(y >= LINEARITY_RANGE[0] * ysat).min())
    hi = int(np.flatnonzero(y <= LINEARITY_RANGE[1] * ysat).max())
    if hi <= lo:
        raise DataFormatError(f"fewer than 2 light steps between {LINEARITY_RANGE[0]:.0%} and "
                              f"{LINEARITY_RANGE[1]:.0%} of saturation: no linearity fit; "
                              "record more steps below saturation", path=where)
    ll = slice(lo, hi + 1)
    a_lin, b_lin = relative_fit(u_p[ll], y[ll])
    fit = a_lin * u_p + b_lin
    dev = 100.0 * (y - fit) / fit

    def fig(name, value, se=None):
        return {"value": float(value), "unit": FIGURES.get(name, ""),
                "se": None if se is None or not np.isfinite(se) else float(se)}

    figs = {
        "K": fig("K", K, K_se), "R": fig("R", R, R_se), "QE": fig("QE", 100 * qe, 100 * qe_se),
        "sigma_y_dark": fig("sigma_y_dark", sy, sy_se), "sigma_d": fig("sigma_d", sigma_d,
                                                                       sigma_d_se),
        "LE_min": fig("LE_min", dev[ll].min()), "LE_max": fig("LE_max", dev[ll].max()),
        "LE_mean": {"value": float(np.abs(dev[ll]).mean()), "unit": "%", "se": None},
        "u_p_sat": fig("u_p_sat", u_p_sat), "u_e_sat": fig("u_e_sat", u_e_sat, u_e_sat * qe_se / qe),
        "SNR_max": fig("SNR_max", snr_max, snr_max * qe_se / qe / 2),
        "SNR_max_dB": fig("SNR_max_dB", 20 * math.log10(snr_max)),
        "DR": fig("DR", dr), "DR_dB": fig("DR_dB", 20 * math.log10(dr)),
        "u_p_min": fig("u_p_min", u_p_min), "u_e_min": fig("u_e_min", u_e_min),
    }
    if many:
        m_u, _, m_u_se, _ = _line(texp_s, ta["dark_u_y"])
        figs["u_I_mean"] = fig("u_I_mean", m_u / K, abs(m_u / K) * math.hypot(m_u_se / m_u,
                                                                               K_se / K))
        if m_u < 0:
            notes.append(f"the dark mean falls with exposure ({m_u:.4g} DN/s): u_I_mean is "
                         "negative, which no dark current is (an offset drifting along the "
                         "sweep, or a clamped dark level); check the dark steps and the "
                         "descriptor's exposure unit")
        if m_v >= 0:
            figs["u_I_var"] = fig("u_I_var", m_v / K ** 2,
                                  abs(m_v / K ** 2) * math.hypot(m_v_se / m_v, 2 * K_se / K))
        else:
            figs["u_I_var"] = {"value": None, "unit": FIGURES["u_I_var"], "se": None}
            notes.append("the dark variance falls with exposure (slope "
                         f"{m_v:.4g} DN^2/s): u_I_var undefined")
    else:
        for name in ("u_I_mean", "u_I_var"):
            figs[name] = {"value": None, "unit": FIGURES[name], "se": None}
        notes.append(f"dark steps at {len(texp_s)} exposure(s): dark current needs more than two")

    sp = group.get("spatial")
    if sp is not None:
        s2d, s2l = sp["dark"]["s2"], sp["light"]["s2"]
        figs["DSNU1288_DN"] = fig("DSNU1288_DN", math.sqrt(s2d)) if s2d >= 0 else \
            {"value": None, "unit": "DN", "se": None}
        figs["DSNU1288"] = fig("DSNU1288", math.sqrt(s2d) / K) if s2d >= 0 else \
            {"value": None, "unit": "e-", "se": None}
        dy = sp["light"]["avg_mean"] - sp["dark"]["avg_mean"]
        figs["PRNU1288"] = (fig("PRNU1288", 100 * math.sqrt(s2l - s2d) / dy) if s2l >= s2d else
                            {"value": None, "unit": "%", "se": None})
    else:
        for name in ("DSNU1288_DN", "DSNU1288", "PRNU1288"):
            figs[name] = {"value": None, "unit": FIGURES[name], "se": None}
    parts = None
    if images is not None:
        from .spatial import nonuniformity_parts

        split, parts = nonuniformity_parts(images, K)
        for name, value in split.items():
            figs[name] = {"value": value, "unit": SPLIT_FIGURES[name], "se": None}
    if pixel_area_um2 is not None:
        for name, (base, unit) in AREA_FIGURES.items():
            figs[name] = {"value": figs[base]["value"] / pixel_area_um2, "unit": unit, "se": None}
    if wavelength_nm is not None:
        energy_j = PLANCK_J_S * LIGHT_M_S / (wavelength_nm * 1e-9)
        figs["photon_energy"] = {"value": energy_j, "unit": "J", "se": None}
        if pixel_area_um2 is not None:
            # irradiation: photons per pixel x photon energy / pixel area, in uJ/m^2 (1 um^2 =
            # 1e-12 m^2; J -> uJ: 1e6)
            for name, base in (("H_sat", "u_p_sat"), ("H_min", "u_p_min")):
                figs[name] = {"value": figs[base]["value"] * energy_j / (pixel_area_um2 * 1e-12)
                              * 1e6, "unit": "uJ/m^2", "se": None}
    ordered = {k: figs[k] for k in FIGURES}
    ordered.update({k: v for k, v in figs.items() if k not in FIGURES})

    fit_ranges = {
        "index_u_ysat": isat,
        "saturation": {"step": int(ta["step"][isat]), "u_p": u_p_sat,
                       "signal_dn": float(ysat), "s2_y_dn2": float(s2_y[isat]),
                       "highest_variance_index": top},
        "sensitivity": {"index": [0, isens], "u_p": [float(u_p[0]), float(u_p[isens])],
                        "signal_dn": [float(y[0]), float(y[isens])],
                        "rule": f"light steps up to {SENSITIVITY_FRACTION:.0%} of the "
                                "saturation signal"},
        "linearity": {"index": [lo, hi], "u_p": [float(u_p[lo]), float(u_p[hi])],
                      "signal_dn": [float(y[lo]), float(y[hi])],
                      "rule": f"light steps from {LINEARITY_RANGE[0]:.0%} to "
                              f"{LINEARITY_RANGE[1]:.0%} of the saturation signal",
                      "fit_slope_dn_per_p": a_lin, "fit_offset_dn": b_lin},
        "sigma_y_dark": ("intercept of s2_ydark against exposure" if many else
                         "s2_ydark of the first dark step") + (", floored" if clamped else ""),
    }
    curves = {"u_p": u_p, "u_y": u_y, "s2_y": s2_y, "u_ydark": ta["u_ydark"],
              "s2_ydark": ta["s2_ydark"], "texp_ms": ta["texp_ms"], "step": ta["step"],
              "linearity_deviation_percent": dev, "dark_texp_ms": ta["dark_texp_ms"],
              "dark_u_y": ta["dark_u_y"], "dark_s2_y": ta["dark_s2_y"]}
    out = {"figures": ordered, "fit_ranges": fit_ranges, "curves": curves, "notes": notes}
    if parts is not None:
        out["nonuniformity"] = parts
    return out


def characterise(sweep, *, pixel_area_um2: float | None = None,
                 wavelength_nm: float | None = None, mosaic_bands: bool = True,
                 statistics: dict | None = None) -> dict:
    """EMVA 1288 Release 4.0 figures of a sweep under the reference implementation's names.

    Parameters
    ----------
    sweep : Sweep or FrameSource
        An EMVA 1288 measurement (:func:`hsiffc.io.read_emva1288`; or
        :func:`hsiffc.io.open_source` on its descriptor, read one frame at a time): light steps
        with photon counts (mean photons per pixel), a dark step at every exposure of the
        light steps and, for DSNU and PRNU, a spatial stack (one light and one dark step of
        many frames).
    pixel_area_um2 : float, optional
        Pixel area in um^2: adds the saturation capacity and sensitivity threshold per area
        (``u_p_sat_area`` ... in p/um^2 and e-/um^2). The descriptor gives photons per pixel,
        so QE needs neither this nor the wavelength.
    wavelength_nm : float, optional
        Wavelength of the light in nm: adds the photon energy and, with the pixel area, the
        saturation and threshold irradiation ``H_sat``, ``H_min`` (uJ/m^2).
    mosaic_bands : bool
        With a mosaic, also the figures of each band (its pixels only).
    statistics : dict, optional
        :func:`step_statistics` of ``sweep``, when already computed (the frames are not read
        again).

    Returns
    -------
    dict
        ``figures`` (name -> value, unit and standard error; None where undefined; the
        classic set, ``LE_mean`` and, with a spatial stack, the row, column and pixel parts of
        DSNU and PRNU and the high-pass PRNU), ``fit_ranges``, ``curves``, ``spatial``
        statistics, ``nonuniformity`` (variances of the split), ``spectrograms`` and
        ``defect_pixels`` (histograms; :mod:`.spatial`), ``general`` (Release 4.0 General,
        :func:`hsiffc.emva1288.general.general_figures`), ``notes``; ``bands`` (the same per
        band) when the sweep has a mosaic; ``steps`` per-step statistics.

    Raises
    ------
    DataFormatError
        Too few light steps, light steps without photons, or no dark step at an exposure of
        the light steps.
    ParameterError
        A non-positive pixel area or wavelength.
    """
    from .spatial import defect_histograms, spectrograms

    for name, value in (("pixel_area_um2", pixel_area_um2), ("wavelength_nm", wavelength_nm)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ParameterError(f"{name} must be a positive number, got {value!r}")
    source = getattr(sweep, "source", None) or getattr(sweep, "label", None) or None
    where = source
    stats = statistics or step_statistics(sweep, mosaic_bands=mosaic_bands)
    images = stats["images"]
    out = []
    for g in stats["groups"]:
        res = figures_from_statistics(stats["steps"], g, where=where,
                                      pixel_area_um2=pixel_area_um2, wavelength_nm=wavelength_nm,
                                      images=images if g["band"] is None else None)
        res.update({"label": g["label"], "band": g["band"], "spatial": g["spatial"]})
        out.append(res)
    main = out[0]
    if stats["spatial_note"]:
        main["notes"].append(stats["spatial_note"])
    meta = getattr(sweep, "meta", {}) or {}
    result = {
        "source": source or "", "frame_shape": stats["frame_shape"],
        "n_pixels": stats["n_pixels"], "bit_depth": stats["bit_depth"],
        "exposure_unit_in_descriptor": meta.get("exposure_unit_in_descriptor"),
        "pixel_area_um2": pixel_area_um2, "wavelength_nm": wavelength_nm,
        "figures": main["figures"], "fit_ranges": main["fit_ranges"], "curves": main["curves"],
        "spatial": main["spatial"], "notes": main["notes"],
        "steps": {k: v for k, v in stats["steps"].items()},
    }
    from .general import general_figures

    result["general"] = general_figures(result)
    if images is not None:
        result["nonuniformity"] = main["nonuniformity"]
        result["spectrograms"] = spectrograms(images, {k: v["value"] for k, v in
                                                       main["figures"].items()})
        result["defect_pixels"] = defect_histograms(images)
    if len(out) > 1:
        wl = sweep.mosaic.wavelengths_nm  # bands by wavelength, labelled as everywhere
        rank = {b: k for k, b in enumerate(wavelength_order(len(out) - 1, wl))}
        rows = sorted(out[1:], key=lambda r: rank[r["band"]])
        result["bands"] = [{"band": r["band"], "label": r["label"], "wavelength_nm": None
                            if wl is None else wl[r["band"]], "figures": r["figures"],
                            "fit_ranges": r["fit_ranges"], "notes": r["notes"]} for r in rows]
    return result
