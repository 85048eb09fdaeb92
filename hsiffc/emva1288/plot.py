"""The EMVA 1288 plots of a characterisation (matplotlib figures; writing is in
:mod:`hsiffc.emva1288.render`).

Photon transfer, sensitivity, SNR, linearity and its error, dark current (when the exposure
varies), DSNU and PRNU histograms and spectrograms, and the leakage figure (beyond the
standard). Each function takes the result of :func:`hsiffc.emva1288.characterise` (and the
spatial images or the leakage result where it needs them) and returns a Figure.
"""

from __future__ import annotations

import numpy as np

from ..reports.figures import new_figure
from .compute import QUANTISATION_VARIANCE

__all__ = ["photon_transfer_figure", "sensitivity_figure", "snr_figure", "linearity_figure",
           "dark_current_figure", "histogram_figure", "spectrogram_figure", "general_figure",
           "leakage_figure"]


def _ranges(ax, x, fr, key, label):
    i0, i1 = fr[key]["index"]
    ax.axvspan(x[i0], x[i1], color="0.9", zorder=0, label=label)


def photon_transfer_figure(res: dict):
    """Temporal variance against mean signal (both dark-subtracted), with the K fit."""
    c, fr, f = res["curves"], res["fit_ranges"], res["figures"]
    x = c["u_y"] - c["u_ydark"]
    y = c["s2_y"] - c["s2_ydark"]
    fig, ax = new_figure((6.4, 4.2))
    _ranges(ax, x, fr, "sensitivity", "fit range")
    ax.plot(x, y, "o", ms=3, label="data")
    i1 = fr["sensitivity"]["index"][1]
    xx = np.array([0.0, x[i1]])
    ax.plot(xx, f["K"]["value"] * xx, "-", color="C3", label=f"K = {f['K']['value']:.4g} DN/e-")
    i = fr["index_u_ysat"]
    ax.plot(x[i], y[i], "s", mfc="none", ms=9, color="k", label="saturation point")
    ax.set(xlabel="u_y - u_y.dark (DN)", ylabel="s2_y - s2_y.dark (DN^2)",
           title="Photon transfer")
    ax.legend(fontsize=8)
    return fig


def sensitivity_figure(res: dict):
    """Mean signal against photons, with the responsivity fit."""
    c, fr, f = res["curves"], res["fit_ranges"], res["figures"]
    y = c["u_y"] - c["u_ydark"]
    fig, ax = new_figure((6.4, 4.2))
    _ranges(ax, c["u_p"], fr, "sensitivity", "fit range")
    ax.plot(c["u_p"], y, "o", ms=3, label="data")
    xx = np.array([0.0, c["u_p"][fr["sensitivity"]["index"][1]]])
    ax.plot(xx, f["R"]["value"] * xx, "-", color="C3", label=f"R = {f['R']['value']:.4g} DN/p")
    ax.set(xlabel="u_p (photons per pixel)", ylabel="u_y - u_y.dark (DN)", title="Sensitivity")
    ax.legend(fontsize=8)
    return fig


def snr_figure(res: dict):
    """SNR against photons: measured, the standard's model and the ideal sqrt(u_p)."""
    c, f = res["curves"], res["figures"]
    y = c["u_y"] - c["u_ydark"]
    ok = (y > 0) & (c["u_p"] > 0)
    snr = np.where(ok, y / np.sqrt(c["s2_y"]), np.nan)
    fig, ax = new_figure((6.4, 4.2))
    ax.loglog(c["u_p"][ok], snr[ok], "o", ms=3, label="data")
    qe, K = f["QE"]["value"] / 100, f["K"]["value"]
    up = np.geomspace(max(c["u_p"][ok].min() / 3, 1e-3), f["u_p_sat"]["value"], 200)
    sd = f["sigma_d"]["value"]
    model = qe * up / np.sqrt(sd ** 2 + QUANTISATION_VARIANCE / K ** 2 + qe * up)
    ax.loglog(up, model, "-", color="C3", label="model (QE, sigma_d, K)")
    ax.loglog(up, np.sqrt(up), ":", color="0.4", label="ideal sqrt(u_p)")
    ax.axvline(f["u_p_min"]["value"], color="0.5", lw=0.8, ls="--")
    ax.axvline(f["u_p_sat"]["value"], color="0.5", lw=0.8, ls="--")
    ax.set(xlabel="u_p (photons per pixel)", ylabel="SNR", title="Signal-to-noise ratio "
           "(dashed: u_p.min, u_p.sat)")
    ax.legend(fontsize=8)
    return fig


def linearity_figure(res: dict):
    """Signal against photons with the linearity fit, and the relative deviation (percent)."""
    c, fr = res["curves"], res["fit_ranges"]
    y = c["u_y"] - c["u_ydark"]
    lin = fr["linearity"]
    fig, (ax, ax2) = new_figure((6.4, 6.0), nrows=2, sharex=True)
    _ranges(ax, c["u_p"], fr, "linearity", "fit range")
    ax.plot(c["u_p"], y, "o", ms=3, label="data")
    ax.plot(c["u_p"], lin["fit_slope_dn_per_p"] * c["u_p"] + lin["fit_offset_dn"], "-",
            color="C3", label="fit")
    ax.set(ylabel="u_y - u_y.dark (DN)", title="Linearity")
    ax.legend(fontsize=8)
    _ranges(ax2, c["u_p"], fr, "linearity", None)
    dev = c["linearity_deviation_percent"]
    i0, i1 = lin["index"]
    ax2.plot(c["u_p"][i0:i1 + 1], dev[i0:i1 + 1], "o-", ms=3)
    ax2.axhline(0, color="0.5", lw=0.8)
    ax2.set(xlabel="u_p (photons per pixel)", ylabel="linearity error (%)")
    return fig


def dark_current_figure(res: dict):
    """Dark mean and dark variance against exposure, with their lines (None with <= 2
    exposures)."""
    c, f = res["curves"], res["figures"]
    t = np.asarray(c["dark_texp_ms"], np.float64) / 1e3
    if len(t) <= 2:
        return None
    fig, (ax, ax2) = new_figure((6.4, 6.0), nrows=2, sharex=True)
    K = f["K"]["value"]
    for a, v, key, lab, scale in ((ax, c["dark_u_y"], "u_I_mean", "u_y.dark (DN)", K),
                                  (ax2, c["dark_s2_y"], "s2_y.dark", "s2_y.dark (DN^2)", K * K)):
        a.plot(t, v, "o", ms=3)
        m, b = np.polyfit(t, v, 1)
        a.plot(t, m * t + b, "-", color="C3")
        a.set(ylabel=lab)
    ui, uv = f["u_I_mean"]["value"], f["u_I_var"]["value"]
    ax.set_title(f"Dark current: u_I.mean = {ui:.4g} e-/s, u_I.var = "
                 f"{'n/a' if uv is None else format(uv, '.4g')} e-/s", fontsize=9)
    ax2.set(xlabel="exposure (s)")
    return fig


def histogram_figure(res: dict):
    """The defect-pixel histograms of Release 4.0: DSNU and PRNU (pixels per bin, logarithmic,
    with the normal curve of the same mean and deviation) and their accumulated histograms
    (percent of pixels deviating by at least each value, logarithmic)."""
    h = res["defect_pixels"]
    fig, axes = new_figure((9.0, 6.0), nrows=2, ncols=2)
    for r, name in enumerate(("DSNU", "PRNU")):
        d = h[name]
        ax = axes[r, 0]
        ax.step(d["bins"], np.maximum(d["values"], 0.5), where="post", lw=0.8, label="data")
        ok = d["model"] >= 0.5
        ax.plot(np.asarray(d["bins"])[ok], np.asarray(d["model"])[ok], "--", color="C3",
                lw=0.8, label="normal")
        ax.set_yscale("log")
        ax.set(title=f"{name} histogram", ylabel="pixels per bin",
               xlabel="deviation from the mean (DN)" if name == "DSNU" else
               "high-pass filtered signal (DN)")
        ax.legend(fontsize=7)
        a = h[f"{name}_accumulated"]
        ax = axes[r, 1]
        ax.step(a["bins"], np.maximum(a["values"], 1e-4), where="post", lw=0.8)
        ax.set_yscale("log")
        ax.set(title=f"{name} accumulated histogram", ylabel="pixels (%)",
               xlabel="absolute deviation from the mean (DN)")
    return fig


def spectrogram_figure(res: dict):
    """Horizontal and vertical spectrograms of DSNU (DN) and PRNU (percent), with the figure's
    level (DSNU1288.DN, PRNU1288) and the temporal noise left in the mean image."""
    sp = res["spectrograms"]
    fig, axes = new_figure((9.0, 6.0), nrows=2, ncols=2)
    for r, name in enumerate(("DSNU", "PRNU")):
        d = sp[name]
        for cidx, lab in enumerate(("horizontal", "vertical")):
            ax = axes[r, cidx]
            s = d[lab]
            ax.semilogy(s["frequency"][1:], s["amplitude"][1:], lw=0.8, label="data")
            if d["figure_level"] is not None:
                ax.axhline(d["figure_level"], color="C3", lw=0.8, ls="--",
                           label=f"{name}1288" + (" (DN)" if name == "DSNU" else ""))
            ax.axhline(d["temporal_level"], color="C2", lw=0.8, ls="-.",
                       label="temporal noise of the mean")
            ax.set(title=f"{name} {lab} spectrogram", xlabel="frequency (cycles/pixel)",
                   ylabel=f"amplitude ({d['unit']})")
            if cidx == 0:
                ax.legend(fontsize=7)
    return fig


def general_figure(res: dict):
    """Release 4.0 General: the SNR against photons without the linear model (measured and, when
    the leakage account ran, predicted by the leakage model), the Linear module's SNR, and the
    differential responsivity."""
    g = res["general"]
    c = g["curves"]
    fig, (ax, ax2) = new_figure((6.4, 7.2), nrows=2)
    ax.loglog(c["u_p"], np.maximum(c["SNR"], 1e-3), "o", ms=3, label="General, measured")
    cu = res["curves"]
    lin = (np.asarray(cu["u_y"]) - np.asarray(cu["u_ydark"])) / np.sqrt(np.asarray(cu["s2_y"]))
    ax.loglog(cu["u_p"], np.maximum(lin, 1e-3), ":", color="0.4", label="Linear: signal / noise")
    model = g.get("model")
    if model is not None:
        ax.loglog(c["u_p"], np.maximum(model["curves"]["SNR"], 1e-3), "-", color="C3",
                  label="General, leakage model")
    i = g["index_sat"]
    ax.plot(c["u_p"][i], c["SNR"][i], "s", mfc="none", ms=9, color="k", label="saturation")
    ax.axhline(1.0, color="0.6", lw=0.6)
    ax.set(xlabel="u_p (photons per pixel)", ylabel="SNR", title="Release 4.0 General: SNR")
    ax.legend(fontsize=8)
    ax2.plot(c["u_p"], c["R_diff"], "o", ms=3, label="measured")
    if model is not None:
        ax2.plot(c["u_p"], model["curves"]["R_diff"], "-", color="C3", label="leakage model")
    ax2.axhline(res["figures"]["R"]["value"], color="0.4", ls=":", label="Linear R")
    ax2.set(xlabel="u_p (photons per pixel)", ylabel="dY/du_p (DN/p)",
            title="Differential responsivity")
    ax2.legend(fontsize=8)
    return fig


def leakage_figure(res: dict, leak: dict):
    """Beyond the standard: linearity error measured and predicted by the leakage model, and
    the dynamic saturation level against the light rate."""
    c = leak["curves"]
    lo, hi = leak["linearity"]["range_index"]
    fig, (ax, ax3, ax2) = new_figure((6.4, 9.6), nrows=3)
    r = slice(lo, hi + 1)
    ax.plot(c["u_p"][r], c["deviation_measured_percent"][r], "o", ms=3, label="measured")
    ax.plot(c["u_p"][r], c["deviation_model_percent"][r], "-", color="C3",
            label="leakage model (calibrated per pixel)")
    ax.plot(c["u_p"][r], c["deviation_without_leakage_percent"][r], ":", color="0.4",
            label="same pixels without leakage")
    ax.axhline(0, color="0.5", lw=0.6)
    share = leak["linearity"]["share_explained_model"]
    ax.set(xlabel="u_p (photons per pixel)", ylabel="linearity error (%)",
           title=f"Linearity error: {100 * share:.0f} % of its sum of squares explained")
    ax.legend(fontsize=8)
    sig = np.asarray(c["signal_measured_dn"], np.float64)
    ax3.plot(sig, c["variance_measured_dn2"], "o", ms=3, label="measured")
    ax3.plot(sig, c["variance_model_dn2"], "-", color="C3", label="leakage model")
    ax3.plot(sig, c["variance_without_leakage_dn2"], ":", color="0.4",
             label="same pixels without leakage")
    tv = leak["temporal_variance"]
    for key, col in (("measured", "k"), ("predicted", "C3")):
        i = tv[f"saturation_index_{key}"]
        y = c["variance_measured_dn2" if key == "measured" else "variance_model_dn2"][i]
        ax3.plot(sig[i], y, "s", mfc="none", ms=9, color=col)
    ax3.set(xlabel="u_y - u_y.dark (DN)", ylabel="s2_y - s2_y.dark (DN^2)",
            title="Photon transfer: the variance peak (saturation point), squares")
    ax3.legend(fontsize=8)
    d = leak["dynamic_saturation"]
    rate = np.asarray(d["light_rate_photons_per_ms"], np.float64)
    ok = np.isfinite(np.asarray(d["p50_dn"], np.float64)) & (rate > 0)
    o = np.argsort(rate[ok])
    ax2.fill_between(rate[ok][o], np.asarray(d["p10_dn"])[ok][o], np.asarray(d["p90_dn"])[ok][o],
                     color="C0", alpha=0.25, label="10th-90th percentile of pixels")
    ax2.plot(rate[ok][o], np.asarray(d["p50_dn"])[ok][o], "-", color="C0", label="median pixel")
    ax2.axhline(d["full_scale_dn"], color="k", lw=0.8, ls="--", label="full scale")
    ax2.set(xlabel="light rate (photons per pixel per ms)", ylabel="dynamic saturation (DN)",
            title="Dynamic saturation level against light rate")
    ax2.legend(fontsize=8)
    return fig
