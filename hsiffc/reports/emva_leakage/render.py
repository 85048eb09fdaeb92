"""The EMVA 1288 leakage report rendered: Markdown and the figure (matplotlib object API)."""

from __future__ import annotations

import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .analysis import BIN_WIDTH_DN

__all__ = ["leakage_figure", "render_markdown"]


def render_markdown(res: dict) -> str:
    """``emva_leakage.md`` of an :func:`analyse_emva_leakage` result."""
    c, s = res["criterion"], res["saturation"]

    def f(v, nd=2):
        return "n/a" if v is None else f"{v:.{nd}f}"

    lines = [
        "# Linear model against leakage model: real EMVA 1288 sweep", "",
        f"Source: `{res['source']}`; {res['frame_shape'][0]} x {res['frame_shape'][1]} pixels, "
        f"{res['n_light_steps']} light + {res['n_dark_steps']} dark usable steps, "
        f"{res['n_valid_samples']} valid samples (step means). hsiffc {res['hsiffc_version']}.", "",
        f"Linear model: {res['linear_model']}. Weights: {res['weights']}. Residual = "
        f"{res['residual']}.", "",
        "## Pixels that level off below full scale", "",
        f"Criterion: {c['text']}.", "",
        "| count | pixels |", "|---|---:|",
        f"| never clipped | {c['n_never_clipped']} |",
        f"| ... and highest step mean < full scale - {c['full_scale_margin_dn']:g} DN | "
        f"{c['n_never_clipped_below_margin']} |",
        f"| ... and rise < {c['roll_off_ratio']:g} x linear (**levels off**) | "
        f"**{c['n_levels_off']}** |",
        "", f"Rise ratio of the levelling-off pixels: median "
        f"{f(c['rise_ratio_levels_off'].get('p50'))}, p5-p95 "
        f"{f(c['rise_ratio_levels_off'].get('p5'))}-{f(c['rise_ratio_levels_off'].get('p95'))}, "
        f"max {f(c['rise_ratio_levels_off'].get('max'))}; its noise (1 sigma, from the photon "
        f"transfer curve) {f(c['rise_ratio_noise_sigma'].get('p50'))}. A linear pixel has 1.", "",
        "## RMS error (DN) over valid samples", "",
        "| pixels | pixels (n) | samples | linear | leakage | linear, median pixel | "
        "leakage, median pixel |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in res["rms"].items():
        lines.append(f"| {name} | {r['n_pixels']} | {r['n_samples']} | {f(r['linear_dn'], 3)} | "
                     f"{f(r['leakage_dn'], 3)} | {f(r['linear_median_pixel_dn'], 3)} | "
                     f"{f(r['leakage_median_pixel_dn'], 3)} |")
    lines += ["", "## By signal range (step mean above the fitted dark level)", "",
              "| range | pixels | samples | linear RMS | leakage RMS | linear bias | leakage bias "
              "| linear RMS w/o step-common | leakage RMS w/o step-common | temporal noise |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rms_by_signal"]:
        lines.append(
            f"| {r['range']} | {r['pixels']} | {r['n_samples']} | {f(r['linear_rms_dn'], 3)} | "
            f"{f(r['leakage_rms_dn'], 3)} | {f(r['linear_bias_dn'], 3)} | "
            f"{f(r['leakage_bias_dn'], 3)} | {f(r['linear_rms_without_step_common_dn'], 3)} | "
            f"{f(r['leakage_rms_without_step_common_dn'], 3)} | {f(r['noise_rms_dn'], 3)} |")
    lines += ["", "Bias: mean residual. Step-common: the median residual over all pixels of each "
              "step, removed. Temporal noise: RMS expected from the photon transfer curve for a "
              "step mean (the floor no model can beat).", "",
              "## Fitted dynamic saturation level against plateau (levelling-off pixels, DN)", "",
              f"Plateau: mean of the step means of the {len(s['plateau_steps'])} brightest light "
              f"steps (steps {s['plateau_steps']}).", "",
              "| quantity | median | p5 | p25 | p75 | p95 | median abs |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for key, lab in (("plateau_dn", "plateau"), ("max_step_mean_dn", "highest step mean"),
                     ("ref_minus_plateau_dn", "saturation_ref (brightest rate) - plateau"),
                     ("ref_minus_max_step_mean_dn", "saturation_ref - highest step mean"),
                     ("at_plateau_rate_minus_plateau_dn",
                      "saturation at the plateau steps' rate - plateau"),
                     ("model_minus_plateau_dn", "leakage model at plateau steps - plateau"),
                     ("linear_minus_plateau_dn", "linear model at plateau steps - plateau"),
                     ("gap_from_remaining_slope_dn",
                      "-ln(1 - rise ratio) / b (gap implied by the remaining slope)")):
        st = s[key]
        lines.append(f"| {lab} | {f(st.get('p50'))} | {f(st.get('p5'))} | {f(st.get('p25'))} | "
                     f"{f(st.get('p75'))} | {f(st.get('p95'))} | {f(st.get('median_abs'))} |")
    cs = s["clipping_pixels_saturation_ref_dn"]
    lines += ["", f"Brightest light rate {s['brightest_rate_photons_per_ms']:.4g} photons/ms; "
              f"plateau steps {s['plateau_rate_photons_per_ms']:.4g} photons/ms. Pixels that clip "
              f"({cs['n']}): fitted saturation_ref median {f(cs.get('p50'))} DN (p5-p95 "
              f"{f(cs.get('p5'))}-{f(cs.get('p95'))}), i.e. above full scale.", "",
              "## Example pixels", "", "| role | row | col | linear RMS | leakage RMS | "
              "saturation_ref | plateau |", "|---|---:|---:|---:|---:|---:|---:|"]
    for e in res["examples"]:
        lines.append(f"| {e['role']} | {e['row']} | {e['col']} | {f(e['linear_rms_dn'], 3)} | "
                     f"{f(e['leakage_rms_dn'], 3)} | {f(e['saturation_ref_dn'])} | "
                     f"{f(e['plateau_dn'])} |")
    lines += ["", "![example pixels](emva_leakage_pixels.png)", ""]
    return "\n".join(lines)


def leakage_figure(res: dict):
    """The example pixels, residual-against-signal curves and the low-signal step-common
    residual of an :func:`analyse_emva_leakage` result, as a new Figure."""

    ex = res["examples"]
    nrow = max(2, math.ceil(len(ex) / 2))
    fig = Figure(figsize=(18, 5.6 * nrow))
    FigureCanvasAgg(fig)
    outer = fig.add_gridspec(nrow, 3, hspace=0.28, wspace=0.27)
    col_lin, col_leak, fs = "tab:orange", "tab:blue", res["full_scale_dn"]
    for i, e in enumerate(ex):
        inner = outer[i // 2, i % 2].subgridspec(2, 1, height_ratios=[3, 1.1], hspace=0.06)
        ax, axr = fig.add_subplot(inner[0]), fig.add_subplot(inner[1])
        x = np.asarray(e["photons"], float)
        yv = np.asarray([np.nan if v is None else v for v in e["y_dn"]], float)
        clip = np.asarray(e["clipped"], bool)
        ax.plot(x[~clip], yv[~clip], "o", ms=3.5, mfc="none", mew=0.7, color="k",
                label="step means (valid samples)")
        if clip.any():
            ax.plot(x[clip], np.full(clip.sum(), fs), "x", ms=4, color="tab:red",
                    label="clipped steps (left out)")
        lin, leak = np.asarray(e["linear_dn"], float), np.asarray(e["leakage_dn"], float)
        ax.plot(x, lin, "-", color=col_lin, lw=1.6, zorder=3,
                label=f"linear, eq. (1): RMS {e['linear_rms_dn']:.2f} DN")
        ax.plot(x, leak, "-", color=col_leak, lw=1.6, zorder=3,
                label=f"leakage model: RMS {e['leakage_rms_dn']:.2f} DN")
        ax.axhline(fs, color="0.6", ls=":", lw=1)
        sat = e["saturation_ref_dn"]
        if sat is not None and sat < fs + 40:
            ax.axhline(sat, color=col_leak, ls="--", lw=0.8,
                       label=f"fitted saturation at brightest rate: {sat:.1f} DN")
        ax.set_ylim(-5, fs + 20)
        ax.set_title(f"{e['role']}: row {e['row']}, col {e['col']}", fontsize=10)
        ax.set_ylabel("step mean (DN)")
        ax.legend(fontsize=7.5, loc="upper left")
        ax.tick_params(labelbottom=False)
        # inset: the top of the range, where the models differ
        ins = ax.inset_axes([0.58, 0.08, 0.39, 0.42])
        top = x > 0.75 * x.max()
        ins.plot(x[top & ~clip], yv[top & ~clip], "o", ms=3, mfc="none", mew=0.7, color="k")
        ins.plot(x[top], lin[top], "-", color=col_lin, lw=1.4, zorder=3)
        ins.plot(x[top], leak[top], "-", color=col_leak, lw=1.4, zorder=3)
        ins.axhline(fs, color="0.6", ls=":", lw=1)
        ins.set_ylim(np.nanmin(yv[top]) - 5, fs + 8)
        ins.tick_params(labelsize=7)
        ins.set_title("brightest quarter", fontsize=7)
        axr.axhline(0, color="0.5", lw=0.8)
        axr.plot(x[~clip], (lin - yv)[~clip], ".-", ms=2, lw=0.6, color=col_lin)
        axr.plot(x[~clip], (leak - yv)[~clip], ".-", ms=2, lw=0.6, color=col_leak)
        axr.set_ylabel("model - data (DN)", fontsize=8)
        axr.set_xlabel("photons per pixel")
        lim = max(3.0, 1.5 * float(np.nanmax(np.abs((leak - yv)[~clip]))))
        axr.set_ylim(-lim, lim)
    right = outer[:, 2].subgridspec(3, 1, hspace=0.5)
    for j, (pname, title) in enumerate((("all", "all pixels"),
                                        ("levels_off", "pixels that level off below 255"))):
        ax = fig.add_subplot(right[j])
        for mname, col, lab in (("linear", col_lin, "linear, eq. (1)"),
                                ("leakage", col_leak, "leakage model")):
            b = res["binned_residual"][pname][mname]
            ax.fill_between(b["center"], b["q25"], b["q75"], color=col, alpha=0.2, lw=0)
            ax.plot(b["center"], b["median"], "-o", ms=2.5, color=col,
                    label=f"{lab}: median (band: quartiles)")
        ax.axhline(0, color="0.5", lw=0.8)
        n = res["criterion"]["n_levels_off"] if pname == "levels_off" else res["n_pixels"]
        ax.set_title(f"Residual against signal, {title} ({n})", fontsize=10)
        ax.set_xlabel(f"step mean above dark (DN), {BIN_WIDTH_DN:g}-DN bins")
        ax.set_ylabel("model - data (DN)")
        ax.legend(fontsize=8, loc="upper left")
        ax.grid(alpha=0.3)
    ax = fig.add_subplot(right[2])
    sc = res["step_common_residual"]
    light = np.asarray(sc["kind"]) == "light"
    sig = np.asarray(sc["signal_dn"], float)[light]
    o = np.argsort(sig)
    low = sig[o] <= 120
    span = 0.5
    for key, col, lab in (("linear_dn", col_lin, "linear, eq. (1)"),
                          ("leakage_dn", col_leak, "leakage model")):
        v = np.asarray(sc[key], float)[light][o]
        ax.plot(sig[o][low], v[low], "-o", ms=2.5, color=col, label=lab)
        span = max(span, float(np.nanmax(np.abs(v[low]))))
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xlim(0, 120)
    ax.set_ylim(-1.15 * span, 1.15 * span)
    ax.set_title("Low signal: residual common to all pixels\n(median over pixels, per light step)",
                 fontsize=10)
    ax.set_xlabel("median step mean above dark (DN)")
    ax.set_ylabel("model - data (DN)")
    ax.legend(fontsize=8, loc="lower left")
    ax.grid(alpha=0.3)
    fig.suptitle("Linear model (eq. 1) vs leakage model on the real EMVA 1288 sweep "
                 f"({res['frame_shape'][0]} x {res['frame_shape'][1]} region; "
                 f"{res['criterion']['n_levels_off']} pixels level off below 255)",
                 fontsize=13, y=0.93)
    return fig


