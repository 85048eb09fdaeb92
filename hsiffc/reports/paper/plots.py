"""The paper report's figures, drawn with matplotlib's object API on figures created here.

Each ``plot_*`` function takes the part of the result it draws and returns a
:class:`matplotlib.figure.Figure`; :func:`paper_figures` gives them all by file name.
"""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps
from matplotlib.ticker import FormatStrFormatter, NullFormatter

from ..figures import new_figure
from ..tables import fmt_value
from .config import THRESHOLD_PERCENT

__all__ = ["paper_figures", "plot_emva", "plot_fig2", "plot_fig4", "plot_fig5", "plot_fig6",
           "plot_tradeoff"]


def paper_figures(sim: dict, emva: dict | None = None) -> dict:
    """Every figure of the report: ``{file name: Figure}`` (the EMVA one only with ``emva``)."""
    figs = {"fig2_alpha_tags.png": plot_fig2(sim["fig2"]),
            "fig4_saturation_vs_rate.png": plot_fig4(sim["fig4"]),
            "fig5_response_lamp_b.png": plot_fig5(sim["fig5"]),
            "fig6_spectra.png": plot_fig6(sim["fig6"]),
            "tradeoff.png": plot_tradeoff(sim["tradeoff"])}
    if emva is not None:
        figs["emva_ffc_levels.png"] = plot_emva(emva)
    return figs


def plot_fig4(f4):
    """Fig. 4: one pixel's (saturated level, light rate) pairs and the fitted ``k = a e^{bY}``.

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    fig, ax = new_figure((6.4, 4.2))
    y = np.array([p["saturated_dn"] for p in f4["pairs"]])
    k = np.array([p["k_dn_per_ms"] for p in f4["pairs"]])
    ax.plot(y, k, "o", color="k", ms=5, mfc="none", label="measured (saturated level, k)")
    yy = np.linspace(y.min() - 30, y.max() + 30, 200)
    ax.plot(yy, f4["a_dn_per_ms"] * np.exp(f4["b_per_dn"] * yy), "-", color="tab:red",
            label=f"fit k = a e^(bY): a = {f4['a_dn_per_ms']:.3g} DN/ms, "
                  f"b = {f4['b_per_dn']:.4f}/DN")
    ax.plot(yy, f4["a_true_dn_per_ms"] * np.exp(f4["b_true_per_dn"] * yy), ":", color="0.4",
            label="simulator truth")
    ax.axvline(800, color="0.7", lw=0.8)
    ax.axhline(2, color="0.7", lw=0.8)
    ax.set_xlabel("saturated level Y (DN)")
    ax.set_ylabel("light rate k = leakage at saturation (DN/ms)")
    ax.set_title(f"Fig. 4: saturated level vs light rate, pixel {tuple(f4['pixel'])} (band 1), "
                 f"{len(y)} illuminations of lamp A", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def plot_fig5(f5):
    """Fig. 5: one pixel under lamp B, measured against the leakage and the linear model.

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    fig, ax = new_figure((6.4, 4.2))
    ax.errorbar(f5["exposure_ms"], f5["measured_dn"], yerr=f5["measured_se_dn"], fmt="o", ms=3,
                color="k", mfc="none", lw=0.8, label="'measured' (simulated, 10-frame mean)")
    ax.plot(f5["t_fine_ms"], f5["leakage_fine_dn"], "-", color="tab:blue",
            label=f"leakage model, eq. (3): RMS {f5['rms_leakage_dn']:.1f} DN")
    ax.plot(f5["t_fine_ms"], f5["linear_fine_dn"], "--", color="tab:orange",
            label=f"linear model, eq. (1): RMS {f5['rms_linear_dn']:.1f} DN")
    if f5["leakage_visible_after_ms"] is not None:
        ax.axvline(f5["leakage_visible_after_ms"], color="0.5", lw=0.8, ls=":")
        ax.text(f5["leakage_visible_after_ms"] + 8, 80,
                f"leakage visible\nafter {f5['leakage_visible_after_ms']:.0f} ms", fontsize=8)
    ax.axhline(f5["dynamic_saturation_dn"], color="tab:blue", lw=0.7, ls=":")
    ax.set_ylim(0, 1060)
    ax.set_xlabel("exposure time (ms)")
    ax.set_ylabel("response (DN)")
    ax.set_title(f"Fig. 5: lamp B, pixel {tuple(f5['pixel'])} (band 1): k = "
                 f"{f5['k_dn_per_ms']:.2f} DN/ms, saturation {f5['dynamic_saturation_dn']:.0f} DN",
                 fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    return fig


def plot_fig2(f2):
    """Fig. 2: the Fig. 5 pixel's responses tagged by alpha (pentagram, circle, triangle).

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    fig, ax = new_figure((6.4, 4.2))
    ax.plot(f2["exposure_ms"], f2["measured_dn"], "-", color="0.6", lw=1, label="response")
    marks = {"pentagram": ("*", 14, "tab:green"), "circle": ("o", 9, "tab:orange"),
             "triangle": ("^", 10, "tab:red")}
    for name, tag in f2["tags"].items():
        m, ms, col = marks[name]
        t, y = tag["exposure_ms"], tag["response_dn"]
        ax.plot([0, t], [f2["dark_dn"], y], "--", color=col, lw=0.8)
        ax.plot(t, y, m, ms=ms, color=col,
                label=f"{name} {t:.0f} ms: alpha {tag['alpha_percent']:.2f} % "
                      f"(paper {tag['paper_alpha_percent']:g} %), "
                      f"k {tag['apparent_k_dn_per_ms']:.2f}")
    ax.axhline(1023, color="0.3", ls=":", lw=0.8)
    ax.text(10, 1000, "full scale 1023 DN (the fixed saturation rule)", fontsize=7)
    ax.set_ylim(0, 1060)
    ax.set_xlabel("exposure time (ms)")
    ax.set_ylabel("response (DN)")
    ax.set_title("Fig. 2: responses tagged by alpha (eq. 4, k ~ Y/t); dashed: apparent k from "
                 "the dark offset", fontsize=9)
    ax.legend(fontsize=7.5, loc="lower right")
    ax.grid(alpha=0.3)
    return fig


def plot_fig6(sp):
    """Fig. 6: lamp B spectra at 11 exposures, invalid ones (alpha over threshold) dotted.

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    fig, ax = new_figure((6.4, 4.2))
    wl = sp["wavelengths_nm"] or list(range(1, sp["normalised"].shape[1] + 1))
    cmap = colormaps["viridis"]
    n = len(sp["exposure_ms"])
    for i, e in enumerate(sp["exposure_ms"]):
        ok = bool(sp["valid"][i])
        ax.plot(wl, sp["normalised"][i], "-" if ok else ":", lw=1.4 if ok else 1.6,
                color=cmap(i / max(n - 1, 1)),
                label=f"{e:.3f} ms{'' if ok else ' (invalid)'}")
    ax.plot(wl, sp["truth_normalised"], "k--", lw=0.8, label="true spectrum")
    ax.set_xlabel("band centre (nm)")
    ax.set_ylabel("band mean / max")
    ax.set_title(f"Fig. 6: lamp B at 11 exposures; dotted: alpha over threshold in some band\n"
                 f"mean spectral angle: valid pairs "
                 f"{fmt_value(sp['mean_angle_valid_pairs_deg'], 2)} deg, "
                 f"invalid-valid pairs {fmt_value(sp['mean_angle_invalid_valid_pairs_deg'], 2)} deg",
                 fontsize=9)
    ax.legend(fontsize=6.5, ncol=2, loc="upper left")
    ax.grid(alpha=0.3)
    return fig


def plot_tradeoff(tr):
    """SNR, uniformity improvement and spectral angle against the alpha threshold, and the
    weighted score that chooses the threshold.

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    rows = tr["rows"]
    thr = np.array([r["threshold_percent"] for r in rows])
    fig, axes = new_figure((9.0, 6.0), nrows=2, ncols=2, sharex=True)
    chosen = tr["chosen_threshold_percent"]
    for ax, key, col, lab in ((axes[0, 0], "snr_db", "tab:green",
                               "SNR of the training flats (dB, single frame)"),
                              (axes[0, 1], "ru_pp", "tab:blue",
                               "RU: uniformity improvement (pp)"),
                              (axes[1, 0], "sc_tile_deg", "tab:purple",
                               "SC: spectral angle per tile (deg, lower = better)")):
        ax.plot(thr, [r[key] for r in rows], "-", color=col)
        ax.set_title(lab, fontsize=9)
        ax.axvline(chosen, color="k", ls="--", lw=0.8)
        ax.axvline(THRESHOLD_PERCENT, color="0.6", ls=":", lw=0.8)
        ax.grid(alpha=0.3)
    ax = axes[1, 1]
    for key, col, lab in (("score_snr", "tab:green", "SNR"), ("score_sc", "tab:purple", "SC"),
                          ("score_ru", "tab:blue", "RU")):
        ax.plot(thr, [r[key] for r in rows], "-", color=col, lw=1, label=lab)
    w = tr["weights"]
    ax.plot(thr, [r["score_total"] for r in rows], "k-", lw=2,
            label=f"weighted: snr={w['snr']:g}, sc={w['sc']:g}, ru={w['ru']:g}")
    ax.axvline(chosen, color="k", ls="--", lw=0.8)
    ax.axvline(THRESHOLD_PERCENT, color="0.6", ls=":", lw=0.8)
    ax.text(chosen * 1.06, 0.03, f"chosen {chosen:g} %", fontsize=8)
    ax.set_title("normalised scores (1 = best); dotted: the paper's 12 %", fontsize=9)
    ax.legend(fontsize=7.5, loc="lower left")
    ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xscale("log")
        ax.set_xlabel("alpha threshold (%)")
    fig.suptitle("Trade-off against the alpha threshold (simulated sensor)", fontsize=10)
    fig.tight_layout()
    return fig


def plot_emva(em):
    """The real EMVA 1288 sweep: residual non-uniformity against test level for flats at
    several levels, and the mean over test levels against the flat level with its alpha.

    Returns a new :class:`matplotlib.figure.Figure` (nothing is drawn on pyplot's state)."""
    fig, axes = new_figure((10.5, 4.2), ncols=2, gridspec_kw={"width_ratios": [1.5, 1]})
    ax = axes[0]
    x = em["test_signal_dn"]
    ax.plot(x, em["raw_nonuniformity_percent"], "-", color="0.5", lw=1.2,
            label="no FFC (dark subtracted)")
    ax.plot(x, em["noise_floor_percent"], ":", color="k", lw=1,
            label="temporal noise of the 2-frame test mean")
    rows = em["candidates"]
    show = {0, em["best_index"], len(rows) - 1, len(rows) // 2}
    if em["selected_index"] is not None:
        show.add(em["selected_index"])
    cmap = colormaps["plasma"]
    for ci in sorted(show):
        r = rows[ci]
        tags = []
        if ci == em["best_index"]:
            tags.append("best")
        if ci == em["selected_index"]:
            tags.append("alpha-selected")
        lab = (f"flat at {r['signal_dn']:.0f} DN (alpha {r['alpha_median_percent']:.2g} %)"
               + (f" [{', '.join(tags)}]" if tags else ""))
        yv = np.where(np.asarray(em["test_steps"]) == r["step"], np.nan,
                      em["nonuniformity_percent"][ci])
        ax.plot(x, yv, "-", lw=1.4,
                color=cmap(ci / max(len(rows) - 1, 1) * 0.9), label=lab)
        ax.axvline(r["signal_dn"], color=cmap(ci / max(len(rows) - 1, 1) * 0.9), lw=0.5, ls="--")
    ax.set_yscale("log")
    ax.set_ylim(0.4, 8)
    ax.set_yticks([0.5, 1, 2, 4, 8])
    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("test level: mean signal above dark (DN)")
    ax.set_ylabel("residual non-uniformity, eq. (6) (%)")
    ax.set_title("Real EMVA 1288 sweep: two-point FFC trained at one level, tested at the others",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.3, which="both")
    ax = axes[1]
    sig = [r["signal_dn"] for r in rows]
    ax.plot(sig, [r["mean_nonuniformity_percent"] for r in rows], "o-", color="tab:blue",
            label="eq. (6), mean over test levels")
    ax.plot(sig, [r["mean_fpn_percent"] for r in rows], "^-", color="tab:purple",
            label="fixed pattern (EMVA 1288), mean")
    ax.axhline(em["raw_mean_fpn_percent"], color="tab:purple", lw=0.8, ls="--",
               label="fixed pattern, no FFC")
    ax.plot(sig[em["best_index"]], rows[em["best_index"]]["mean_nonuniformity_percent"], "s",
            ms=11, mfc="none", color="tab:green", label="best")
    if em["selected_index"] is not None:
        ax.plot(sig[em["selected_index"]],
                rows[em["selected_index"]]["mean_nonuniformity_percent"], "*", ms=12,
                color="tab:red", label=f"alpha < {em['threshold_percent']:g} % (median)")
    ax.axhline(em["raw_mean_nonuniformity_percent"], color="0.5", lw=0.8, label="eq. (6), no FFC")
    ax.set_xlabel("flat level: mean signal above dark (DN)")
    ax.set_ylabel("mean residual non-uniformity (%)")
    ax3 = ax.twinx()
    ax3.semilogy(sig, [max(r["alpha_median_percent"], 1e-4) for r in rows], "--", color="tab:red",
                 lw=0.8)
    ax3.axhline(em["threshold_percent"], color="tab:red", lw=0.5, ls=":")
    ax3.set_ylabel("median alpha of the flat (%)", color="tab:red")
    ax.legend(fontsize=7, loc="upper center")
    ax.grid(alpha=0.3)
    ax.set_title("Which flat level?", fontsize=9)
    fig.tight_layout()
    return fig


