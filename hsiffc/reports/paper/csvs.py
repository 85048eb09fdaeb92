"""The paper report's tables and figure data as CSV text (one file per table or figure)."""

from __future__ import annotations

import numpy as np

from ..tables import csv_text
from .config import PAPER_VALUES

__all__ = ["report_csvs"]


def report_csvs(sim, em) -> dict:
    """``{file name: CSV text}`` for every table and figure of the simulated experiment
    ``sim`` and, when ``em`` is not None, the real EMVA 1288 part."""
    out = {}
    t1 = sim["table1"]
    t2 = sim["table2"]
    p1, p2 = PAPER_VALUES["table1_alpha_percent"], PAPER_VALUES["table2_improvement_pp"]
    rows = []
    for band in range(t1.alpha.shape[0]):
        for j, e in enumerate(t1.exposures_ms):
            paper = p1.get(band + 1, [None] * 5)[j]
            rows.append([band + 1, sim["wavelengths_nm"][band], e, t1.alpha[band, j],
                         "" if paper is None else paper, t1.selected_ms[band] == e])
    out["table1_alpha.csv"] = csv_text(
        ["band", "wavelength_nm", "exposure_ms", "alpha_percent", "paper_alpha_percent",
         "selected"], rows)
    rows = []
    for band in range(t2["improvement_pp"].shape[0]):
        for j, e in enumerate(t2["exposures_ms"]):
            paper = p2.get(band + 1, [None] * 5)[j]
            rows.append([band + 1, e, t2["improvement_pp"][band, j], t2["se_pp"][band, j],
                         "" if paper is None else paper, t2["selected_ms"][band] == e,
                         t2["best_ms"][band] == e, t2["improvement_dark_subtracted_pp"][band, j],
                         t2["se_dark_subtracted_pp"][band, j], t2["raw_uniformity_percent"][band],
                         t2["raw_uniformity_dark_subtracted_percent"][band],
                         t2["test_mean_dn"][band], t2["fpn_raw_percent"][band],
                         t2["fpn_percent"][band, j]])
    out["table2_uniformity.csv"] = csv_text(
        ["band", "training_exposure_ms", "improvement_pp", "standard_error_pp",
         "paper_improvement_pp", "selected_by_alpha", "best",
         "improvement_vs_dark_subtracted_test_pp", "standard_error_dark_subtracted_pp",
         "test_uniformity_raw_percent", "test_uniformity_dark_subtracted_percent",
         "test_mean_raw_dn", "test_fixed_pattern_raw_percent",
         "test_fixed_pattern_corrected_percent"], rows)
    g = sim["grid"]
    rows = [[band + 1, e, g["alpha_percent"][band, j], g["signal_dn"][band, j], g["snr"][band, j],
             g["improvement_pp"][band, j], g["se_pp"][band, j]]
            for band in range(g["alpha_percent"].shape[0]) for j, e in enumerate(g["exposures_ms"])]
    out["training_grid.csv"] = csv_text(
        ["band", "exposure_ms", "alpha_percent", "flat_signal_dn", "flat_snr_single_frame",
         "improvement_pp", "standard_error_pp"], rows)
    f4 = sim["fig4"]
    rows = [[p["illumination"], p["relative_light"], p["saturated_dn"], p["k_dn_per_ms"],
             f4["a_dn_per_ms"] * np.exp(f4["b_per_dn"] * p["saturated_dn"])] for p in f4["pairs"]]
    out["fig4_saturation_vs_rate.csv"] = csv_text(
        ["illumination", "relative_light", "saturated_dn", "k_dn_per_ms", "fit_k_dn_per_ms"], rows)
    f5 = sim["fig5"]
    rows = [[t, m, s, lk, ln, ar, asg] for t, m, s, lk, ln, ar, asg in zip(
        f5["exposure_ms"], f5["measured_dn"], f5["measured_se_dn"], f5["leakage_model_dn"],
        f5["linear_model_dn"], f5["alpha_paper_raw_percent"], f5["alpha_signal_percent"])]
    out["fig5_response_lamp_b.csv"] = csv_text(
        ["exposure_ms", "measured_dn", "measured_se_dn", "leakage_model_dn", "linear_model_dn",
         "alpha_paper_percent", "alpha_dark_subtracted_percent"], rows)
    f2 = sim["fig2"]
    tag_at = {v["exposure_ms"]: k for k, v in f2["tags"].items()}
    rows = [[t, y, a, asg, tag_at.get(float(t), "")] for t, y, a, asg in zip(
        f2["exposure_ms"], f2["measured_dn"], f2["alpha_percent"], f2["alpha_signal_percent"])]
    out["fig2_alpha_tags.csv"] = csv_text(
        ["exposure_ms", "response_dn", "alpha_paper_percent", "alpha_dark_subtracted_percent",
         "tag"], rows)
    sp = sim["fig6"]
    nb = sp["normalised"].shape[1]
    rows = []
    for i, e in enumerate(sp["exposure_ms"]):
        rows.append([e, bool(sp["valid"][i]), sp["alpha_percent"][:, i].max(),
                     sp["angle_to_best_deg"][i], sp["angle_to_truth_deg"][i],
                     sp["tile_angle_to_truth_deg"][i], *sp["normalised"][i], *sp["spectra_dn"][i]])
    rows.append(["truth", "", "", "", 0.0, "", *sp["truth_normalised"], *sp["truth_spectrum"]])
    out["fig6_spectra.csv"] = csv_text(
        ["exposure_ms", "valid", "max_band_alpha_percent", "angle_to_best_deg",
         "angle_to_truth_deg", "mean_tile_angle_to_truth_deg"]
        + [f"band{b + 1}_normalised" for b in range(nb)]
        + [f"band{b + 1}_signal_dn" for b in range(nb)], rows)
    tr = sim["tradeoff"]
    rows = [[r["threshold_percent"], r["snr_db"], r["ru_pp"], r["sc_tile_deg"],
             r["sc_band_mean_deg"], r["spectral_ms"], r["score_snr"], r["score_sc"], r["score_ru"],
             r["score_total"], r["fallback"], *r["selected_ms"]] for r in tr["rows"]]
    out["tradeoff.csv"] = csv_text(
        ["threshold_percent", "snr_db", "ru_improvement_pp", "sc_tile_angle_deg",
         "sc_band_mean_angle_deg", "spectral_exposure_ms", "score_snr", "score_sc", "score_ru",
         "score_weighted", "fallback_to_shortest"]
        + [f"band{b + 1}_training_ms" for b in range(len(tr["rows"][0]["selected_ms"]))], rows)
    if em is not None:
        rows = [[r["step"], r["exposure_ms"], r["photons"], r["signal_dn"], r["clipped_fraction"],
                 r["alpha_median_percent"], r["alpha_p95_percent"], r["alpha_invalid_fraction"],
                 r["mean_nonuniformity_percent"], r["median_nonuniformity_percent"],
                 r["mean_fpn_percent"], r["median_fpn_percent"],
                 i == em["best_index"], i == em["selected_index"]]
                for i, r in enumerate(em["candidates"])]
        out["emva_ffc_levels.csv"] = csv_text(
            ["flat_step", "exposure_ms", "photons", "flat_signal_dn", "clipped_fraction",
             "alpha_median_percent", "alpha_p95_percent", "fraction_alpha_over_threshold",
             "mean_nonuniformity_percent", "median_nonuniformity_percent",
             "mean_fixed_pattern_percent", "median_fixed_pattern_percent", "best",
             "selected_by_alpha"], rows)
        rows = []
        for ti, step in enumerate(em["test_steps"]):
            rows.append([step, em["test_signal_dn"][ti], em["raw_nonuniformity_percent"][ti],
                         em["noise_floor_percent"][ti],
                         *em["nonuniformity_percent"][:, ti], em["raw_fpn_percent"][ti],
                         *em["fpn_percent"][:, ti]])
        out["emva_ffc_matrix.csv"] = csv_text(
            ["test_step", "test_signal_dn", "no_ffc_percent", "noise_floor_percent"]
            + [f"flat_step{r['step']}_percent" for r in em["candidates"]]
            + ["no_ffc_fixed_pattern_percent"]
            + [f"flat_step{r['step']}_fixed_pattern_percent" for r in em["candidates"]], rows)
    return out


