"""EMVA 1288 Release 4.0 General: the application figures of a camera whose response is not
linear, from the same measurement and without the photon transfer curve; numbers only.

Release 4.0 Linear reads K, QE and the noise off the photon transfer line, which a leaky pixel
bends (its variance is damped before its mean bends, so the line and the saturation point it
gives no longer mean what they say). Release 4.0 General asks only what an application needs:
how much light a camera detects, from where, up to where and how well. Following its reasoning,
with ``Y = u_y - u_y.dark`` the characteristic curve (DN) and ``s2 = s2_y`` the temporal
variance of each light step (DN^2, dark noise included):

- the differential responsivity ``R(u_p) = dY/du_p`` (DN/p): the slope at each step of a
  quadratic fitted to the characteristic curve over the ``DERIVATIVE_WINDOW`` steps around it
  (fewer at the ends), so that no line is assumed and the noise of the step means is not
  differentiated as it is (a plain difference of neighbouring steps varies by about 10 % on
  the shared CMOS set);
- the input-referred temporal noise ``sigma_p = sigma_y / R`` (photons) and the signal-to-noise
  ratio ``SNR(u_p) = u_p / sigma_p = u_p R / sigma_y``; for a linear camera this is the
  standard's ``(u_y - u_y.dark) / sigma_y``;
- ``u_p_sat_general``: the photons of the light step with the largest SNR among those where
  the camera still responds (``R`` at least ``RESPONDING_FRACTION`` of its median over the
  lower half of the steps), up to which more light gives a better image; ``SNR_max_general``
  that SNR. (Where pixels clip, their temporal variance vanishes faster than the mean curve
  flattens, and the ratio would rise again on an output that no longer responds.)
- ``u_p_min_general``: the photons where the SNR reaches 1, interpolated linearly in
  ``log SNR`` against ``log u_p`` between the steps around it (the lowest step when even it is
  above 1; undefined when no step reaches 1 below saturation and none is below);
- ``DR_general = u_p_sat_general / u_p_min_general`` and its dB;
- ``QE_general``: ``max SNR^2 / u_p`` over the steps up to saturation (%): the photon noise
  limit ``SNR^2 = eta u_p`` is approached from below wherever other noise adds, so the largest
  ratio is the closest estimate of the quantum efficiency the SNR curve allows, without K.

*What the leakage model adds.* With hsiffc's per-pixel leakage calibration the same quantities
follow from the model's characteristic curve and its predicted temporal variance
(:func:`hsiffc.emva1288.leakage.leakage_effects`), plus the measured dark variance: the model's
General SNR curve, its saturation and its maximum, beside the measured ones. Where the linear
model misdescribes the sensor (a leaky CMOS), this says whether the leakage model describes
what the General figures measure.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["general_figures", "general_curves", "GENERAL_FIGURES", "DERIVATIVE_WINDOW",
           "RESPONDING_FRACTION"]

DERIVATIVE_WINDOW = 5  # light steps in each local quadratic fit of the characteristic curve
RESPONDING_FRACTION = 0.5  # a step "responds" with R at least this x the low-signal median

#: name -> unit
GENERAL_FIGURES = {"u_p_sat_general": "p", "SNR_max_general": "1", "SNR_max_general_dB": "dB",
                   "u_p_min_general": "p", "DR_general": "1", "DR_general_dB": "dB",
                   "QE_general": "%"}


def general_curves(u_p, signal_dn, var_dn2) -> dict:
    """Differential responsivity, input-referred noise and SNR of each light step.

    Parameters
    ----------
    u_p : (S,) array, photons per pixel
        The light steps, in increasing order.
    signal_dn : (S,) array, DN
        Characteristic curve above dark.
    var_dn2 : (S,) array, DN^2
        Temporal variance of each step (dark noise included).

    Returns
    -------
    dict
        ``u_p``, ``R_diff`` (DN/p), ``sigma_p`` (p), ``SNR`` (S,) arrays.

    Examples
    --------
    >>> c = general_curves(np.array([100.0, 200.0, 400.0]), np.array([10.0, 20.0, 40.0]),
    ...                    np.array([1.0, 2.0, 4.0]))
    >>> [round(float(v), 3) for v in c["SNR"]]   # a linear camera: signal / noise
    [10.0, 14.142, 20.0]
    """
    u_p = np.asarray(u_p, np.float64)
    y = np.asarray(signal_dn, np.float64)
    r = _slopes(u_p, y)
    sigma_y = np.sqrt(np.maximum(np.asarray(var_dn2, np.float64), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma_p = np.where(r > 0, sigma_y / r, np.inf)
        snr = np.where(r > 0, u_p * r / sigma_y, 0.0)
    return {"u_p": u_p, "R_diff": r, "sigma_p": sigma_p, "SNR": snr}


def _slopes(x, y, window: int = DERIVATIVE_WINDOW) -> np.ndarray:
    """dy/dx at every x from a local quadratic (a line with 2 points) over ``window`` points."""
    n = len(x)
    out = np.full(n, np.nan)
    h = window // 2
    for i in range(n):
        lo, hi = max(0, i - h), min(n, i + h + 1)
        xs = x[lo:hi] - x[i]
        if xs.size < 2:
            continue
        deg = 2 if xs.size >= 3 else 1
        scale = float(np.abs(xs).max()) or 1.0
        coef = np.polynomial.polynomial.polyfit(xs / scale, y[lo:hi], deg)
        out[i] = coef[1] / scale
    return out


def _threshold(u_p, snr, top) -> float | None:
    """Photons where the SNR reaches 1 below ``top`` (log-log interpolation)."""
    ok = np.flatnonzero((snr[:top + 1] > 0) & (u_p[:top + 1] > 0))
    if ok.size == 0:
        return None
    above = ok[snr[ok] >= 1.0]
    if above.size == 0:
        return None
    j = int(above[0])
    below = ok[ok < j]
    if below.size == 0:
        return float(u_p[j])  # already above 1 at the lowest usable step
    i = int(below[-1])
    x0, x1 = math.log(u_p[i]), math.log(u_p[j])
    s0, s1 = math.log(snr[i]), math.log(snr[j])
    if s1 == s0:
        return float(u_p[j])
    return float(math.exp(x0 + (0.0 - s0) * (x1 - x0) / (s1 - s0)))


def _figures(c: dict) -> dict:
    u_p, snr, r = c["u_p"], c["SNR"], c["R_diff"]
    low = r[: max(1, len(r) // 2)]
    ref = float(np.nanmedian(low)) if np.any(np.isfinite(low)) else float("nan")
    responds = np.nan_to_num(r) >= RESPONDING_FRACTION * ref
    top = int(np.argmax(np.where(responds, snr, -np.inf))) if responds.any() else \
        int(np.argmax(snr))
    fmin = _threshold(u_p, snr, top)
    sat = float(u_p[top])
    smax = float(snr[top])
    with np.errstate(divide="ignore", invalid="ignore"):
        qe = np.where(u_p[:top + 1] > 0, snr[:top + 1] ** 2 / u_p[:top + 1], 0.0)
    dr = sat / fmin if fmin else None
    return {"u_p_sat_general": sat, "SNR_max_general": smax,
            "SNR_max_general_dB": 20 * math.log10(smax) if smax > 0 else None,
            "u_p_min_general": fmin, "DR_general": dr,
            "DR_general_dB": 20 * math.log10(dr) if dr else None,
            "QE_general": 100 * float(qe.max()) if qe.size else None,
            "index_sat_general": top}


def general_figures(res: dict, leak: dict | None = None) -> dict:
    """The Release 4.0 General figures of a characterisation, measured and (with ``leak``)
    as the leakage model predicts them.

    Parameters
    ----------
    res : dict
        :func:`hsiffc.emva1288.characterise` (its light-step curves are used).
    leak : dict, optional
        :func:`hsiffc.emva1288.leakage.leakage_effects` of the same measurement.

    Returns
    -------
    dict
        ``figures`` (name -> ``{"value", "unit", "se"}``, :data:`GENERAL_FIGURES`),
        ``index_sat`` (light-step index of the saturation), ``curves`` (:func:`general_curves`)
        and, with ``leak``, ``model`` (the same from the leakage model's curve and variance).
    """
    c = res["curves"]
    u_p = np.asarray(c["u_p"], np.float64)
    y = np.asarray(c["u_y"], np.float64) - np.asarray(c["u_ydark"], np.float64)
    var = np.asarray(c["s2_y"], np.float64)
    curves = general_curves(u_p, y, var)
    f = _figures(curves)

    def table(d):
        return {k: {"value": None if d[k] is None else float(d[k]), "unit": u, "se": None}
                for k, u in GENERAL_FIGURES.items()}

    out = {"figures": table(f), "index_sat": f["index_sat_general"], "curves": curves}
    if leak is not None:
        lc = leak["curves"]
        dark_var = np.asarray(c["s2_ydark"], np.float64)
        mc = general_curves(u_p, np.asarray(lc["signal_model_dn"], np.float64),
                            np.asarray(lc["variance_model_dn2"], np.float64) + dark_var)
        mf = _figures(mc)
        out["model"] = {"figures": table(mf), "index_sat": mf["index_sat_general"],
                        "curves": mc}
    return out
