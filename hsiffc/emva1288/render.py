"""The EMVA 1288 report: figures table (Markdown), the standard's plots (PNG) and the JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..files.atomic import atomic_write_text
from ..files.jsonsafe import json_safe
from .compute import FIGURES

__all__ = ["figures_table", "defect_markdown", "general_markdown", "leakage_markdown", "render_markdown", "to_json",
           "write_report", "fmt"]

LABELS = {
    "K": "system gain", "R": "responsivity", "QE": "quantum efficiency",
    "sigma_y_dark": "temporal dark noise", "sigma_d": "temporal dark noise",
    "DSNU1288_DN": "dark signal nonuniformity", "DSNU1288": "dark signal nonuniformity",
    "PRNU1288": "photo response nonuniformity", "LE_min": "linearity error, min",
    "LE_max": "linearity error, max", "u_p_sat": "saturation capacity",
    "u_e_sat": "saturation capacity", "SNR_max": "maximum SNR", "SNR_max_dB": "maximum SNR",
    "DR": "dynamic range", "DR_dB": "dynamic range", "u_p_min": "absolute sensitivity threshold",
    "u_e_min": "absolute sensitivity threshold", "u_I_mean": "dark current, from the mean",
    "u_I_var": "dark current, from the variance",
    "LE_mean": "linearity error, mean of its absolute value",
    "DSNU1288_row": "DSNU, row part", "DSNU1288_col": "DSNU, column part",
    "DSNU1288_pixel": "DSNU, pixel part", "DSNU1288_row_DN": "DSNU, row part",
    "DSNU1288_col_DN": "DSNU, column part", "DSNU1288_pixel_DN": "DSNU, pixel part",
    "PRNU1288_row": "PRNU, row part", "PRNU1288_col": "PRNU, column part",
    "PRNU1288_pixel": "PRNU, pixel part",
    "PRNU1288_highpass": "PRNU after the standard's 5 x 5 high-pass filter",
}


def fmt(v, digits: int = 5) -> str:
    """A number with ``digits`` significant digits; "n/a" for None."""
    if v is None:
        return "n/a"
    return f"{v:.{digits}g}"


def figures_table(figures: dict) -> list[str]:
    """Markdown rows: name, what it is, value, unit, standard error."""
    lines = ["| figure | what | value | unit | standard error |", "|---|---|---:|---|---:|"]
    for name, f in figures.items():
        lines.append(f"| `{name}` | {LABELS.get(name, '')} | {fmt(f['value'])} | {f['unit']} | "
                     f"{fmt(f['se'], 2) if f.get('se') is not None else ''} |")
    return lines


def leakage_markdown(leak: dict) -> list[str]:
    """The 'beyond the standard' section."""
    lin, al, bud = leak["linearity"], leak["alpha"], leak["saturation_budget"]
    pct = (lambda v: "n/a" if v is None else f"{100 * v:.1f} %")  # noqa: E731
    cal = leak["calibration"]
    drawn = ""
    if cal.get("drawn_seed") is not None:
        drawn = (f" on {cal['n_pixels']} of the sensor's {cal['sensor_pixels']} pixels, drawn "
                 f"at random (seed {cal['drawn_seed']}): the figures below are over them")
    lines = [
        "## What leakage does to the figures (beyond the standard)", "",
        f"Per-pixel leakage calibration: {cal['method']} "
        f"({', '.join(f'{k}: {v}' for k, v in (cal['fit_status'] or {}).items())})"
        f"{drawn}. Definitions: module docstring of `hsiffc.emva1288.leakage`.", "",
        f"**Evidence: {leak['evidence']['text']}.**", "",
        "### Linearity error", "",
        "| curve | LE_min (%) | LE_max (%) | share of the linearity error's sum of squares "
        "explained |", "|---|---:|---:|---:|",
        f"| measured (the standard's) | {lin['LE_min_measured']:.3f} | "
        f"{lin['LE_max_measured']:.3f} | |",
        f"| leakage model, calibrated per pixel | {lin['LE_min_model']:.3f} | "
        f"{lin['LE_max_model']:.3f} | {pct(lin['share_explained_model'])} |",
        f"| same pixels without leakage (control) | {lin['LE_min_without_leakage']:.3f} | "
        f"{lin['LE_max_without_leakage']:.3f} | {pct(lin['share_explained_without_leakage'])} |",
        f"| left after the model (measured - model) | {lin['LE_min_left']:.3f} | "
        f"{lin['LE_max_left']:.3f} | |", "",
        f"Share explained by leakage: **{pct(lin['share_explained_by_leakage'])}**; RMS "
        f"linearity error {lin['rms_measured_percent']:.3f} % measured, "
        f"{lin['rms_left_percent']:.3f} % left after the model; the temporal noise of the "
        f"step means gives {lin['noise_rms_percent']:.3f} % (a lower bound of the random "
        "error).", "",
        "### Leakage percentage alpha at the standard's points", "",
        "| point | u_p (p) | signal (DN) | alpha median (%) | p90 (%) | max (%) | pixels > 5 % | "
        "pixels > 12 % |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    names = {"sensitivity_end": "end of the K/R fit range (70 %)",
             "linearity_end": "end of the linearity range (95 %)",
             "saturation": "saturation point (variance peak)"}
    for key, lab in names.items():
        a = al.get(key)
        if a is None:
            continue
        lines.append(f"| {lab} | {a['u_p']:.6g} | {a['signal_dn']:.1f} | {fmt(a['p50'], 3)} | "
                     f"{fmt(a['p90'], 3)} | {fmt(a['max_percent'], 3)} | "
                     f"{pct(a['share_above_5_percent'])} | {pct(a['share_above_12_percent'])} |")
    fsp = bud["u_p_full_scale_without_leakage"]
    tv = leak.get("temporal_variance")
    if tv is not None:
        at = tv["at_saturation_dn2"]
        lines += [
            "", "### Temporal variance and the saturation point", "",
            "The standard's saturation point is the peak of the temporal variance. Predicted "
            f"from the calibration ({tv['pixels']} pixels, seed {tv['seed']}; leakage damps the "
            "noise before it bends the mean):", "",
            "| | saturation step (index) | u_p_sat (p) | variance there (DN^2) |",
            "|---|---:|---:|---:|",
            f"| measured (the standard's) | {tv['saturation_index_measured']} | "
            f"{tv['u_p_sat_measured']:.6g} | {at['measured']:.3f} |",
            f"| leakage model | {tv['saturation_index_predicted']} | "
            f"{tv['u_p_sat_predicted']:.6g} | {at['predicted']:.3f} |",
            f"| same pixels without leakage (peak where they clip) | "
            f"{tv['saturation_index_without_leakage']} | {tv['u_p_sat_without_leakage']:.6g} | "
            f"{at['without_leakage']:.3f} |", "",
            f"At the measured saturation step leakage has damped "
            f"{pct(tv['share_damped_by_leakage_at_saturation'])} of the temporal variance; the "
            f"saturation capacity the standard reports is "
            f"{fmt(tv['u_p_sat_measured'] / tv['u_p_sat_without_leakage'], 3)} of the one the "
            "same pixels would have without leakage."]
    lines += [
        "", "### Saturation capacity: leakage or well", "",
        f"At the saturation step ({bud['u_p']:.6g} photons, {bud['exposure_ms']:.4g} ms), mean "
        "over the pixels:", "",
        "| | DN | e- (over K) | share of generated |", "|---|---:|---:|---:|",
        f"| generated (k t; the standard's u_e_sat = {bud['u_e_sat_standard']:.5g} e-) | "
        f"{bud['generated_dn']:.2f} | {bud['generated_e']:.5g} | 100 % |",
        f"| lost to leakage | {bud['leaked_dn']:.2f} | {bud['leaked_e']:.4g} | "
        f"{pct(bud['leaked_share'])} |",
        f"| lost to clipping at full scale | {bud['clipped_dn']:.2f} | {bud['clipped_e']:.4g} | "
        f"{pct(bud['clipped_share'])} |",
        f"| stored (model) | {bud['stored_dn']:.2f} | {bud['stored_e']:.5g} | "
        f"{pct(bud['stored_share'])} |",
        f"| measured signal | {bud['measured_signal_dn']:.2f} | | |", "",
        f"Pixels at the saturation step: {pct(bud['share_pixels_leakage_limited'])} "
        "leakage-limited (their dynamic saturation level is below full scale at this light "
        f"rate), {pct(bud['share_pixels_clipped_measured'])} clipped in the data "
        f"({pct(bud['share_pixels_clipped_model'])} by the model). Without leakage the median "
        f"pixel would reach full scale at {fmt(fsp['p50'])} photons (10th-90th percentile "
        f"{fmt(fsp['p10'])}-{fmt(fsp['p90'])}): the standard's u_p_sat is "
        f"{fmt(bud['u_p_sat_over_median_u_p_full_scale'], 3)} of it.", "",
        "### Dynamic saturation level against light rate", "",
        "| light rate (p/ms) | u_p (p) | median (DN) | 10th-90th percentile (DN) | pixels below "
        "full scale |", "|---:|---:|---:|---|---:|"]
    d = leak["dynamic_saturation"]
    rate = np.asarray(d["light_rate_photons_per_ms"], np.float64)
    ok = np.flatnonzero(np.isfinite(np.asarray(d["p50_dn"], np.float64)) & (rate > 0))
    if ok.size:
        pick = ok[np.argsort(rate[ok])]
        pick = pick[np.unique(np.linspace(0, len(pick) - 1, min(8, len(pick))).round().astype(int))]
        for i in pick:
            lines.append(f"| {rate[i]:.5g} | {d['u_p'][i]:.6g} | {d['p50_dn'][i]:.1f} | "
                         f"{d['p10_dn'][i]:.1f}-{d['p90_dn'][i]:.1f} | "
                         f"{pct(d['share_below_full_scale'][i])} |")
    return lines


def general_markdown(res: dict) -> list[str]:
    """The Release 4.0 General figures (no linearity assumed), measured and, when the leakage
    account ran, as the leakage model predicts them, beside the Linear module's."""
    g = res.get("general")
    if g is None:
        return []
    f = res["figures"]
    model = g.get("model")
    lines = ["", "## Release 4.0 General (no linearity assumed)", "",
             "Differential responsivity, SNR = u_p R / sigma_y, saturation at the largest SNR "
             "where the camera still responds, threshold at SNR = 1 (definitions: module "
             "docstring of `hsiffc.emva1288.general`).", "",
             "| figure | General, measured |" + (" General, leakage model |" if model else "")
             + " Linear |", "|---|---:|" + ("---:|" if model else "") + "---:|"]
    linear = {"u_p_sat_general": "u_p_sat", "SNR_max_general": "SNR_max",
              "SNR_max_general_dB": "SNR_max_dB", "u_p_min_general": "u_p_min",
              "DR_general": "DR", "DR_general_dB": "DR_dB", "QE_general": "QE"}
    for name, fig in g["figures"].items():
        cells = [fmt(fig["value"], 4)]
        if model:
            cells.append(fmt(model["figures"][name]["value"], 4))
        cells.append(fmt(f[linear[name]]["value"], 4))
        lines.append(f"| `{name}` ({fig['unit']}) | " + " | ".join(cells) + " |")
    lines += ["", f"Saturation: light step index {g['index_sat']} measured"
              + (f", {model['index_sat']} predicted by the leakage model" if model else "")
              + f"; {res['fit_ranges']['index_u_ysat']} by the Linear module's variance peak."]
    return lines


def defect_markdown(res: dict) -> list[str]:
    """The defect-pixel counts (Release 4.0): pixels deviating from the mean by more than
    multiples of the figure, from the accumulated histograms, and the share of the spatial
    variance in rows, columns and pixels."""
    h, nu = res.get("defect_pixels"), res.get("nonuniformity")
    if h is None or nu is None:
        return []
    f = res["figures"]
    lines = ["", "## Nonuniformity: rows, columns, pixels and defect pixels", "",
             "Share of the spatial variance (DN^2) in each part (the split of Release 4.0; "
             "negative where the temporal noise left in the stack exceeds a part):", "",
             "| stack | total s2 (DN^2) | rows | columns | pixels |", "|---|---:|---:|---:|---:|"]
    for kind in ("dark", "light"):
        v = nu[kind]
        tot = v["s2"]
        cells = [fmt(None if v[k] is None or not tot else v[k] / tot, 3)
                 for k in ("s2_row", "s2_col", "s2_pixel")]
        lines.append(f"| {kind} | {fmt(tot, 4)} | " + " | ".join(cells) + " |")
    lines += ["", "Defect pixels from the accumulated histograms (share of pixels whose "
              "deviation from the mean reaches the first bin edge at or above each value):", "",
              "| histogram | deviation (DN) | pixels (%) |", "|---|---:|---:|"]
    for key, base in (("DSNU_accumulated", f["DSNU1288_DN"]["value"]),
                      ("PRNU_accumulated", None)):
        a = h[key]
        bins, vals = np.asarray(a["bins"]), np.asarray(a["values"])
        if base is None:  # PRNU: in DN of the (light - dark) signal, at 1 %, 3 %, 10 % of it
            sp = res["spatial"]
            base = 0.01 * (sp["light"]["avg_mean"] - sp["dark"]["avg_mean"])
            steps = ((1, "1 % of the signal"), (3, "3 %"), (10, "10 %"))
        else:
            steps = ((3, "3 x DSNU1288.DN"), (6, "6 x"), (10, "10 x"))
        for mult, lab in steps:
            x = mult * base
            i = int(np.searchsorted(bins, x, side="left"))
            share = float(vals[i]) if i < len(vals) else 0.0
            lines.append(f"| {key.split('_')[0]} ({lab}) | {x:.3g} | {share:.3g} |")
    return lines


def render_markdown(res: dict, leak: dict | None = None, images: dict | None = None,
                    leak_note: str | None = None, title: str = "EMVA 1288 characterisation"
                    ) -> str:
    """The report page: figures table, fit ranges, notes, bands, leakage, plots."""
    fr = res["fit_ranges"]
    lines = [f"# {title}", "",
             f"Source: `{res['source']}`; {res['frame_shape'][0]} x {res['frame_shape'][1]} px, "
             f"{res['bit_depth']}-bit. Computed as the EMVA 1288 Release 4.0 reference "
             "implementation computes it (definitions: module docstring of "
             "`hsiffc.emva1288.compute`). Standard errors: regression standard errors of the "
             "fits (1 sigma), propagated to the figures derived from them.", ""]
    lines += figures_table(res["figures"])
    sat, sens, lin = fr["saturation"], fr["sensitivity"], fr["linearity"]
    lines += ["", "## Fit ranges", "",
              f"- saturation point: light step index {fr['index_u_ysat']} (step {sat['step']}), "
              f"u_p = {sat['u_p']:.6g} p, signal {sat['signal_dn']:.2f} DN (temporal variance "
              "peak)",
              f"- K and R: indices {sens['index'][0]}-{sens['index'][1]}, u_p "
              f"{sens['u_p'][0]:.6g}-{sens['u_p'][1]:.6g} p ({sens['rule']})",
              f"- linearity: indices {lin['index'][0]}-{lin['index'][1]}, u_p "
              f"{lin['u_p'][0]:.6g}-{lin['u_p'][1]:.6g} p ({lin['rule']})",
              f"- sigma_y_dark: {fr['sigma_y_dark']}"]
    if res["notes"]:
        lines += ["", "Notes:", ""] + [f"- {n}" for n in res["notes"]]
    lines += defect_markdown(res) + general_markdown(res)
    if res.get("bands"):
        names = ["K", "QE", "sigma_y_dark", "DSNU1288", "PRNU1288", "LE_min", "LE_max",
                 "u_e_sat", "DR_dB"]
        lines += ["", "## Per band", "", "| band | wavelength (nm) | " + " | ".join(
            f"`{n}` ({FIGURES[n]})" for n in names) + " |", "|---" * (len(names) + 2) + "|"]
        for b in res["bands"]:
            wl = "" if b["wavelength_nm"] is None else f"{b['wavelength_nm']:g}"
            lines.append(f"| {b.get('label', b['band'])} | {wl} | " + " | ".join(
                fmt(b["figures"][n]["value"], 4) for n in names) + " |")
    if leak is not None:
        lines += [""] + leakage_markdown(leak)
    elif leak_note:
        lines += ["", "## What leakage does to the figures", "", leak_note]
    if images:
        lines += ["", "## Plots", ""]
        for name, path in images.items():
            lines += [f"![{name}]({Path(path).name})", ""]
    return "\n".join(lines).rstrip() + "\n"


def to_json(res: dict, leak: dict | None = None, leak_note: str | None = None) -> dict:
    """The JSON document: every figure with unit and standard error, fit ranges, curves."""
    doc = {"standard": "EMVA 1288 Release 4.0, computed as its reference implementation "
                       "(emva1288) computes it", **res}
    if leak is not None:
        doc["leakage"] = leak
    elif leak_note:
        doc["leakage"] = {"not_computed": leak_note}
    return json_safe(doc)


def write_report(sweep, res: dict, outdir, leak: dict | None = None,
                 leak_note: str | None = None, *, dpi: float = 90) -> dict:
    """Write the plots (PNG), ``emva1288.md`` and ``emva1288.json`` into ``outdir``.

    Parameters
    ----------
    sweep : Sweep, FrameSource or None
        The characterised measurement (unused: the result holds what the plots need; kept
        for callers that pass it).
    res : dict
        :func:`hsiffc.emva1288.characterise` of it.
    outdir : path-like
        Created if missing; existing files are replaced only as the write policy allows.
    leak : dict, optional
        :func:`hsiffc.emva1288.leakage_effects` of it.
    leak_note : str, optional
        Why the leakage section is missing, when it is.
    dpi : float
        Of the PNGs.

    Returns
    -------
    dict
        Name -> path of every file written.
    """
    from ..reports.figures import save_figure  # matplotlib: only when plots are written
    from . import plot

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    figs = {"photon transfer": plot.photon_transfer_figure(res),
            "sensitivity": plot.sensitivity_figure(res), "SNR": plot.snr_figure(res),
            "linearity": plot.linearity_figure(res)}
    dc = plot.dark_current_figure(res)
    if dc is not None:
        figs["dark current"] = dc
    if res.get("defect_pixels") is not None:
        figs["DSNU and PRNU histograms"] = plot.histogram_figure(res)
        figs["DSNU and PRNU spectrograms"] = plot.spectrogram_figure(res)
    if res.get("general") is not None:
        figs["general SNR"] = plot.general_figure(res)
    if leak is not None:
        figs["leakage"] = plot.leakage_figure(res, leak)
    files = {}
    for name, fig in figs.items():
        path = outdir / f"emva1288_{name.split(' ')[0].lower()}.png"
        if name.startswith("DSNU"):
            path = outdir / f"emva1288_{name.split(' ')[-1].lower()}.png"
        # fixed margins instead of a tight bounding box: the box costs a second draw
        fig.subplots_adjust(left=0.13, right=0.97, top=0.92, bottom=0.1, hspace=0.4, wspace=0.3)
        files[name] = save_figure(fig, path, dpi=dpi, tight=False)
    md = outdir / "emva1288.md"
    atomic_write_text(md, render_markdown(res, leak, files, leak_note))
    js = outdir / "emva1288.json"
    atomic_write_text(js, json.dumps(to_json(res, leak, leak_note), indent=1,
                                     allow_nan=False) + "\n")
    files["markdown"], files["json"] = md, js
    return {k: str(v) for k, v in files.items()}
