"""What the leakage model says about the EMVA 1288 figures (beyond the standard): numbers only.

The standard sees a leaky pixel only through its mean curve: leakage bends the response below
the line (a linearity error) and makes it level off below full scale (a variance peak, hence a
saturation point, set by the leakage rather than the well or the ADC). With a per-pixel
calibration of the leakage model (:func:`hsiffc.calibrate.calibrate`; ``k = responsivity x
photons/exposure + dark current``, ``dY/dt = k - a exp(b Y)``) every light step of the sweep is
predicted pixel by pixel and the standard's computations are repeated on the predictions:

*Linearity error explained.* The model's mean curve (mean over the pixels of the predicted
response, clipped at full scale as the ADC clips, less the predicted dark at that exposure)
goes through the standard's linearity computation (same fit range, same relative fit). The
share of the linearity error explained is ``1 - sum((dev - dev_model)^2) / sum(dev^2)`` over the
fit range, ``dev`` the measured relative deviation (percent). The same with leakage switched
off (``a = 0``, the same responsivity, dark and clipping) is the control: what clipping and the
light rates alone explain. The difference is the leakage's share.

*Dynamic saturation against light rate.* The level ``ln(k/a)/b`` where leakage balances the
light, per pixel at the light rate of each light step (median and 10th-90th percentiles over the
pixels), and the share of pixels for which it lies below full scale (they level off before they
can clip).

*Alpha at the standard's points.* The model leakage percentage ``100 a exp(b Y) / k`` (the
share of the light rate that leaks at the predicted response) per pixel at the end of the
sensitivity fit range (70 %: K and R are fitted up to there), at the end of the linearity
range (95 %) and at the saturation point.

*Temporal variance and the saturation point.* Leakage damps the temporal noise before it bends
the mean: a pixel a little above its mean path leaks faster and relaxes back. With shot noise
(``K`` DN^2 per DN of signal, for the light and for the leaked charge) and the linearised
damping ``2 b a exp(b Y)``, the variance of a pixel's response obeys
``dV/dt = K (k + a e^{bY}) - 2 b a e^{bY} V`` along the model's mean path; it is integrated
exactly over ``VARIANCE_SUBSTEPS`` pieces of every exposure (the leakage held at each piece's
middle), for ``VARIANCE_PIXELS`` pixels drawn with a fixed seed, a pixel at or above full scale
counting 0 (clipped). The standard's saturation search run on the predicted mean variance gives
the saturation point the leakage model predicts; without leakage (``V = K k t`` up to full
scale) the variance only peaks where the pixels clip.

*Saturation capacity: leakage or well.* At the saturation step, per pixel: the generated signal
``k t`` (what the standard's ``u_e_sat = QE u_p_sat`` counts, in DN), the part lost to leakage
(``k t`` minus the predicted response above dark), the part lost to clipping at full scale, and
the stored part; means over the pixels in DN and in electrons (over the standard's K). Also the
photon count at which the median pixel would reach full scale without leakage, against the
standard's ``u_p_sat``.
"""

from __future__ import annotations

import numpy as np

from ..leakage import model
from ..errors import CalibrationMismatchError
from .compute import LINEARITY_RANGE, relative_fit, saturation_index

__all__ = ["ALPHA_LEVELS", "NOISE_Z", "chi2_limit", "deviation_chi2", "leakage_effects",
           "leakage_evidence", "predicted_temporal_variance"]

ALPHA_LEVELS = (5.0, 12.0, 50.0)  # percent: shares of pixels above these alphas
PCTS = (10, 50, 90)
#: Pixels whose temporal variance is predicted (fixed seed). Against 4096 on the shared CMOS set
#: the saturation points are the same (predicted, measured, without leakage), the predicted
#: variance at saturation 4.0981 against 4.0956 DN^2 and the share damped by leakage 8.12
#: against 8.16 %, at a quarter of the time (the integration was a third of the account's).
VARIANCE_PIXELS = 1024
CHUNK_VALUES = 1 << 19  # model values per call: few kernel launches, arrays that stay in cache
VARIANCE_CHUNK = 1 << 16  # values per piece in the variance integration (arrays in cache)
VARIANCE_SUBSTEPS = 16  # pieces of each exposure in the variance integration (16 against 40:
# 0.15 % on the CMOS set's predicted variance at saturation, same saturation point)


def _pcts(v) -> dict:
    v = np.asarray(v, np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return {f"p{p}": None for p in PCTS}
    return {f"p{p}": float(x) for p, x in zip(PCTS, np.percentile(v, PCTS))}


def _linearity_deviation(u_p, y, lo, hi) -> np.ndarray:
    a, b = relative_fit(u_p[lo:hi + 1], y[lo:hi + 1])
    fit = a * u_p + b
    return 100.0 * (y - fit) / fit


def _deviation_noise(emva: dict, u_p, y, lo, hi) -> np.ndarray:
    """Standard error (percent) of each light step's linearity deviation from the temporal
    noise of its means: ``sigma_y^2 / (pixels x frames)`` of the light step and of its dark,
    relative to the fitted line. A lower bound of the random error (row noise and the light
    source's own noise add to it)."""
    c, steps = emva["curves"], emva["steps"]
    n_pix = float(emva["n_pixels"])
    frames = dict(zip(np.asarray(steps["step"]).tolist(), np.asarray(steps["n_frames"]).tolist()))
    dark_frames = {}
    for kind, t, f in zip(steps["kind"], steps["exposure_ms"], steps["n_frames"]):
        if str(kind) == "dark":
            dark_frames.setdefault(round(float(t), 9), int(f))
    t = np.asarray(c["texp_ms"], np.float64)
    f_light = np.array([frames.get(int(st), 1) for st in c["step"]], np.float64)
    f_dark = np.array([dark_frames.get(round(float(x), 9), fl) for x, fl in zip(t, f_light)],
                      np.float64)
    var = (np.asarray(c["s2_y"], np.float64) / (n_pix * f_light)
           + np.asarray(c["s2_ydark"], np.float64) / (n_pix * f_dark))
    a, b = relative_fit(u_p[lo:hi + 1], y[lo:hi + 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return 100.0 * np.sqrt(np.maximum(var, 0.0)) / np.abs(a * u_p + b)


#: The measured linearity error is "at the noise level" while the sum of its squares over the
#: fit range, in units of each step's noise, stays below the chi-square quantile that pure noise
#: exceeds with probability 0.001 (one-sided normal z = 3.09)
NOISE_Z = 3.09


def chi2_limit(dof: int, z: float = NOISE_Z) -> float:
    """The chi-square value that ``dof`` degrees of freedom of pure noise exceed with the
    one-sided normal probability of ``z`` (Wilson-Hilferty: ``(chi2 / dof)^(1/3)`` is about
    normal with mean ``1 - 2 / (9 dof)`` and variance ``2 / (9 dof)``; within 0.6 % of the
    exact quantile from 10 degrees of freedom up, 1.2 % at 5).

    >>> round(chi2_limit(26), 1)  # exact 0.999 quantile: 54.05
    54.2
    """
    v = 2.0 / (9.0 * dof)
    return dof * (1.0 - v + z * v ** 0.5) ** 3


def deviation_chi2(dev, se) -> tuple[float, int]:
    """(chi-square, degrees of freedom) of linearity deviations ``dev`` against their standard
    errors ``se`` (the same unit): the sum of ``(dev / se)^2`` over the steps, less the fitted
    line's two parameters. A step without noise (``se`` 0: noise-free frames) that deviates
    makes it infinite (a deviation without noise is systematic); one that does not deviate
    adds nothing.

    >>> deviation_chi2([0.1, -0.1, 0.2, 0.0], [0.1, 0.1, 0.1, 0.1])
    (6.0, 2)
    >>> deviation_chi2([0.1, 0.0, 0.0], [0.0, 0.0, 0.0])[0]
    inf
    """
    dev = np.asarray(dev, np.float64)
    se = np.asarray(se, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(se > 0, (dev / se) ** 2, np.where(dev != 0, np.inf, 0.0))
    return float(np.sum(terms)), max(int(np.count_nonzero(se > 0)) - 2, 1)


def leakage_evidence(linearity: dict) -> dict:
    """Whether the measurement shows leakage, from the account's linearity figures:
    ``verdict`` ``"noise"`` (the linearity error is what the temporal noise of the step means
    gives: its chi-square over the fit range below :func:`chi2_limit`, so there is nothing
    systematic for leakage to explain), ``"not_explained"`` (a systematic linearity error the
    leakage model does not reduce beyond the control) or ``"explained"`` (the model reduces it:
    consistent with leakage, which the mean curve alone cannot tell from other compressive
    effects), with a sentence (``text``) that says it with the numbers. Where the verdict is not
    ``"explained"`` the account's alpha, saturation and budget figures are what the model
    fitted, not evidence of leakage.

    The noise is a lower bound (row noise and the light source's own noise add to it): a
    sensor whose light flickers between steps can show a "systematic" error the model does not
    explain, never a false "noise".

    On the shared sets: the two linear reference simulations (no leakage) are ``"noise"``
    (chi-square 23.4 on 24 and 30.6 on 32 degrees of freedom), the CMOS set ``"explained"``
    (53 times the noise, 14.2 % explained)."""
    rms, noise = linearity["rms_measured_percent"], linearity["noise_rms_percent"]
    share = linearity["share_explained_by_leakage"]
    times = rms / noise if noise > 0 else np.inf
    chi2, dof, limit = (linearity["noise_chi2"], linearity["noise_dof"],
                        linearity["noise_chi2_limit"])
    stat = (f"RMS {rms:.3g} %, {times:.3g} times what the temporal noise of the step means "
            f"gives; chi-square {chi2:.3g} on {dof} degrees of freedom, noise exceeds "
            f"{limit:.3g} with probability 0.001")
    if chi2 <= limit:
        verdict = "noise"
        text = (f"no evidence of leakage: the linearity error is at the noise level ({stat}), "
                "so there is nothing systematic for leakage to explain; the alpha, saturation "
                "and budget figures are what the model fitted, not findings")
    elif share is None or share <= 0:
        verdict = "not_explained"
        text = (f"no evidence of leakage: the leakage model does not explain the linearity "
                f"error ({stat}; {linearity['rms_left_percent']:.3g} % left after the model); "
                "the alpha, saturation and budget figures are what the model fitted, not "
                "findings")
    else:
        verdict = "explained"
        text = (f"the leakage model explains {100 * share:.1f} % of the linearity error's sum "
                f"of squares ({stat}; {linearity['rms_left_percent']:.3g} % left after the "
                "model): consistent with leakage, not proof of it (a compression common to "
                "every pixel, in the readout or the well, and an exposure offset bend the mean "
                "curve too; `hsiffc diagnose` tests them against each other)")
    return {"verdict": verdict, "text": text, "measured_over_noise": float(times)}


def predicted_temporal_variance(t_ms, k, a, b, dark, gain_dn_per_e, full_scale,
                                n_pieces: int = VARIANCE_SUBSTEPS) -> np.ndarray:
    """Temporal variance (DN^2, above the dark's) of the leakage model's response after
    ``t_ms`` at light rate ``k``, per pixel (all arguments broadcast: several exposures at
    once): ``dV/dt = K (k + L) - 2 b L V``, ``L = a e^{bY}``
    along the mean path, integrated exactly piece by piece with L at each piece's middle; 0
    where the mean path is at or above ``full_scale`` (clipped).

    Examples
    --------
    >>> v = predicted_temporal_variance(10.0, np.array([5.0]), np.array([0.0]), np.array([0.01]),
    ...                                 np.array([0.0]), 0.5, 4095)
    >>> float(v[0])  # no leakage: shot noise K k t
    25.0
    """
    out_shape = np.broadcast_shapes(*(np.shape(v) for v in (t_ms, k, a, b, dark)))
    t, k, a, b, dark = (np.ravel(v).astype(np.float64)
                        for v in np.broadcast_arrays(t_ms, k, a, b, dark))
    var = np.zeros(k.shape)
    lit = t > 0  # no exposure: no variance (a zero piece gives none either)
    h = np.where(lit, t, 0.0) / n_pieces
    no_leak = a == 0  # a pixel without leakage leaks 0 (not 0 x an overflowed exponential)
    for j in range(n_pieces):  # one piece at a time: flat arrays, no broadcast copies
        y = model.response((j + 0.5) * h, k, a, b, dark)
        with np.errstate(over="ignore", invalid="ignore"):
            leak = a * np.exp(b * y)
        leak[no_leak] = 0.0
        x = 2.0 * b * leak * h
        decay = np.expm1(-x)  # e^-x - 1: the damping over the piece and its mean, one pass
        with np.errstate(invalid="ignore", divide="ignore"):
            phi = np.where(x > 1e-12, -decay / x, 1.0)
        decay += 1.0
        var *= decay
        var += gain_dn_per_e * (k + leak) * h * phi
    end = model.response(np.where(lit, t, 0.0), k, a, b, dark)
    var = np.where(lit, var, 0.0)
    return np.where(end >= full_scale, 0.0, var).reshape(out_shape)


def leakage_effects(sweep, emva: dict, calibration) -> dict:
    """The leakage model's account of the EMVA 1288 figures of ``sweep``.

    Parameters
    ----------
    sweep : Sweep
        The measurement :func:`~hsiffc.emva1288.characterise` characterised.
    emva : dict
        Its result (the curves and fit ranges of the whole frame are used).
    calibration : Calibration
        Per-pixel leakage-model calibration of the same frames (photons / exposure as the light
        rate: what :func:`hsiffc.calibrate.calibrate` fits on an EMVA 1288 sweep).

    Returns
    -------
    dict
        ``linearity`` (measured and model deviations, shares explained), ``dynamic_saturation``
        (per light step), ``alpha`` (at the sensitivity end, linearity end and saturation
        point), ``saturation_budget`` (generated, leaked, clipped, stored at the saturation
        step) and the calibration's fit status.

    Raises
    ------
    CalibrationMismatchError
        The calibration is for another frame size or another light-rate unit.
    """
    h, w = sweep.frame_shape
    if tuple(calibration.domain.get("frame_shape", ())) != (h, w):
        raise CalibrationMismatchError(
            f"the calibration is for frames {calibration.domain.get('frame_shape')}, the sweep "
            f"has {[h, w]}: calibrate this measurement")
    unit = calibration.domain.get("light_rate_unit")
    if unit not in (None, "photons/ms"):
        raise CalibrationMismatchError(
            f"the calibration's light rate is in {unit!r}; the EMVA 1288 figures need one "
            "calibrated with photons / exposure (calibrate the EMVA 1288 sweep itself)")
    c = emva["curves"]
    fr = emva["fit_ranges"]
    fs = float(sweep.full_scale_dn)
    arr = {k: np.asarray(calibration.arrays[k], np.float64).ravel()
           for k in ("responsivity", "a_dn_per_ms", "b_per_dn", "dark_dn")}
    g, a, b, dark = arr["responsivity"], arr["a_dn_per_ms"], arr["b_per_dn"], arr["dark_dn"]
    dc = np.asarray(calibration.dark_current, np.float64).ravel()
    u_p = np.asarray(c["u_p"], np.float64)
    t = np.asarray(c["texp_ms"], np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.where(t > 0, u_p / t, 0.0)  # photons / ms; a step at t = 0 holds no light
    y_meas = np.asarray(c["u_y"]) - np.asarray(c["u_ydark"])
    n = len(u_p)
    y_model = np.empty(n)
    y_noleak = np.empty(n)
    sat_med = np.empty(n)
    sat_lo = np.empty(n)
    sat_hi = np.empty(n)
    below_fs = np.empty(n)
    isat = fr["index_u_ysat"]
    isens = fr["sensitivity"]["index"][1]
    lo, hi = fr["linearity"]["index"]
    points = {"sensitivity_end": isens, "linearity_end": hi, "saturation": isat}
    alpha, budget = {}, None
    K = emva["figures"]["K"]["value"]
    pick = np.sort(np.random.default_rng(0).choice(h * w, min(VARIANCE_PIXELS, h * w),
                                                   replace=False))
    # the model evaluated for many steps per call (a kernel launch per step cost more than the
    # evaluation itself on the shared CMOS set), in chunks of about CHUNK_VALUES values
    kp = g[pick][None, :] * rate[:, None] + dc[pick][None, :]
    var_leak = np.empty(n)
    vchunk = max(1, VARIANCE_CHUNK // len(pick))
    for i in range(0, n, vchunk):
        var_leak[i:i + vchunk] = predicted_temporal_variance(
            t[i:i + vchunk, None], kp[i:i + vchunk], a[pick], b[pick], dark[pick], K, fs,
            VARIANCE_SUBSTEPS).mean(axis=1)
    var_noleak = np.where(dark[pick] + kp * t[:, None] >= fs, 0.0,
                          K * kp * t[:, None]).mean(axis=1)
    step_chunk = max(1, CHUNK_VALUES // max(1, g.size))
    for i in range(n):
        if i % step_chunk == 0:
            ck = g[None, :] * rate[i:i + step_chunk, None] + dc[None, :]
            ct = t[i:i + step_chunk, None]
            c_resp = model.response(ct, ck, a, b, dark)
            c_dark = model.response(ct, dc, a, b, dark)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                c_sat = model.dynamic_saturation_level(np.maximum(ck, 1e-300), a, b)
        k, resp, d_resp = ck[i % step_chunk], c_resp[i % step_chunk], c_dark[i % step_chunk]
        y_model[i] = np.minimum(resp, fs).mean() - np.minimum(d_resp, fs).mean()
        y_noleak[i] = (np.minimum(dark + k * t[i], fs).mean()
                       - np.minimum(dark + dc * t[i], fs).mean())
        if rate[i] > 0:
            ysat = c_sat[i % step_chunk]  # +inf where a pixel does not leak (a = 0)
            big = np.finfo(np.float64).max
            q = np.percentile(np.minimum(ysat, big), PCTS)
            sat_lo[i], sat_med[i], sat_hi[i] = np.where(q >= big, np.inf, q)
            below_fs[i] = float((ysat < fs).mean())
        else:  # no light in the step: no dynamic saturation to speak of
            sat_lo[i] = sat_med[i] = sat_hi[i] = below_fs[i] = np.nan
        for name, j in points.items():
            if i == j:
                al = model.leakage_percentage(resp, np.maximum(k, 1e-300), a, b)
                alpha[name] = {"index": int(j), "u_p": float(u_p[j]),
                               "signal_dn": float(y_meas[j]),
                               "mean_percent": float(np.mean(al)), **_pcts(al),
                               "max_percent": float(np.max(al)),
                               **{f"share_above_{lv:g}_percent": float((al > lv).mean())
                                  for lv in ALPHA_LEVELS}}
        if i == isat:
            gen = k * t[i] + 0.0
            stored_model = resp - dark
            stored_adc = np.minimum(resp, fs) - dark
            share = emva.get("steps", {}).get("clipped_share")
            if share is not None:  # measured while the frames were read
                clipped_meas = float(np.asarray(share)[
                    np.asarray(emva["steps"]["step"]) == int(c["step"][i])][0])
            else:
                data = sweep.data[sweep.step == int(c["step"][i])]
                clipped_meas = float((data >= sweep.full_scale_dn).any(axis=0).mean())
            budget = {
                "index": int(i), "u_p": float(u_p[i]), "exposure_ms": float(t[i]),
                "light_rate_photons_per_ms": float(rate[i]),
                "generated_dn": float(gen.mean()), "leaked_dn": float((gen - stored_model).mean()),
                "clipped_dn": float((stored_model - stored_adc).mean()),
                "stored_dn": float(stored_adc.mean()),
                "measured_signal_dn": float(y_meas[i]),
                "generated_e": float(gen.mean() / K),
                "leaked_e": float((gen - stored_model).mean() / K),
                "clipped_e": float((stored_model - stored_adc).mean() / K),
                "stored_e": float(stored_adc.mean() / K),
                "u_e_sat_standard": emva["figures"]["u_e_sat"]["value"],
                "share_pixels_leakage_limited": float(below_fs[i]),
                "share_pixels_clipped_model": float((resp >= fs).mean()),
                "share_pixels_clipped_measured": clipped_meas,
            }
    gen_share = budget["generated_dn"]
    for key in ("leaked", "clipped", "stored"):
        budget[f"{key}_share"] = budget[f"{key}_dn"] / gen_share if gen_share > 0 else None
    # photons at which a pixel would reach full scale without leakage (light only, t-free)
    with np.errstate(divide="ignore", invalid="ignore"):
        per_photon = g  # k t = g * photons (+ dark current x t, small): DN per photon
        u_p_fs = (fs - dark) / per_photon
    budget["u_p_full_scale_without_leakage"] = _pcts(u_p_fs[np.isfinite(u_p_fs)
                                                            & (u_p_fs > 0)])
    budget["u_p_sat_over_median_u_p_full_scale"] = (
        float(u_p[isat] / budget["u_p_full_scale_without_leakage"]["p50"])
        if budget["u_p_full_scale_without_leakage"]["p50"] else None)

    dev = np.asarray(c["linearity_deviation_percent"], np.float64)
    dev_model = _linearity_deviation(u_p, y_model, lo, hi)
    dev_noleak = _linearity_deviation(u_p, y_noleak, lo, hi)
    r = slice(lo, hi + 1)
    ss = float((dev[r] ** 2).sum())
    explained = 1.0 - float(((dev[r] - dev_model[r]) ** 2).sum()) / ss if ss > 0 else None
    explained_noleak = (1.0 - float(((dev[r] - dev_noleak[r]) ** 2).sum()) / ss
                        if ss > 0 else None)
    linearity = {
        "range_index": [lo, hi], "rule": f"{LINEARITY_RANGE[0]:.0%}-{LINEARITY_RANGE[1]:.0%}",
        "LE_min_measured": float(dev[r].min()), "LE_max_measured": float(dev[r].max()),
        "LE_min_model": float(dev_model[r].min()), "LE_max_model": float(dev_model[r].max()),
        "LE_min_without_leakage": float(dev_noleak[r].min()),
        "LE_max_without_leakage": float(dev_noleak[r].max()),
        "LE_min_left": float((dev - dev_model)[r].min()),
        "LE_max_left": float((dev - dev_model)[r].max()),
        "share_explained_model": explained,
        "share_explained_without_leakage": explained_noleak,
        "share_explained_by_leakage": (None if explained is None else
                                       explained - explained_noleak),
        "rms_measured_percent": float(np.sqrt(np.mean(dev[r] ** 2))),
        "rms_left_percent": float(np.sqrt(np.mean((dev[r] - dev_model[r]) ** 2))),
    }
    se = _deviation_noise(emva, u_p, y_meas, lo, hi)[r]
    chi2, dof = deviation_chi2(dev[r], se)
    linearity.update(noise_rms_percent=float(np.sqrt(np.mean(se ** 2))), noise_chi2=chi2,
                     noise_dof=dof, noise_chi2_limit=chi2_limit(dof, NOISE_Z))
    evidence = leakage_evidence(linearity)
    var_meas = np.asarray(c["s2_y"], np.float64) - np.asarray(c["s2_ydark"], np.float64)
    isat_pred = saturation_index(var_leak)
    isat_noleak = saturation_index(var_noleak)
    variance = {
        "pixels": int(len(pick)), "seed": 0, "pieces_per_exposure": VARIANCE_SUBSTEPS,
        "saturation_index_measured": int(isat), "saturation_index_predicted": int(isat_pred),
        "saturation_index_without_leakage": int(isat_noleak),
        "u_p_sat_measured": float(u_p[isat]), "u_p_sat_predicted": float(u_p[isat_pred]),
        "u_p_sat_without_leakage": float(u_p[isat_noleak]),
        "at_saturation_dn2": {"measured": float(var_meas[isat]),
                              "predicted": float(var_leak[isat]),
                              "without_leakage": float(var_noleak[isat])},
        "share_damped_by_leakage_at_saturation": (
            float(1.0 - var_leak[isat] / var_noleak[isat]) if var_noleak[isat] > 0 else None),
    }
    status = calibration.fitted_on.get("fit_status")
    return {
        "calibration": {"method": calibration.method, "fit_status": status,
                        "n_pixels": int(h * w)},
        "evidence": evidence,
        "linearity": linearity,
        "curves": {"u_p": u_p, "light_rate_photons_per_ms": rate, "signal_measured_dn": y_meas,
                   "signal_model_dn": y_model, "signal_without_leakage_dn": y_noleak,
                   "deviation_measured_percent": dev, "deviation_model_percent": dev_model,
                   "deviation_without_leakage_percent": dev_noleak,
                   "variance_measured_dn2": var_meas, "variance_model_dn2": var_leak,
                   "variance_without_leakage_dn2": var_noleak},
        "temporal_variance": variance,
        "dynamic_saturation": {"light_rate_photons_per_ms": rate, "u_p": u_p,
                               "p10_dn": sat_lo, "p50_dn": sat_med, "p90_dn": sat_hi,
                               "share_below_full_scale": below_fs, "full_scale_dn": fs},
        "alpha": alpha,
        "saturation_budget": budget,
    }
