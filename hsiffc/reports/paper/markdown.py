"""The paper report rendered as Markdown from its result (no computation here)."""

from __future__ import annotations

import numpy as np

from ... import __version__
from ..tables import fmt_value
from .config import (EMVA_MAX_CLIPPED, EMVA_MIN_SIGNAL_DN, PAPER_VALUES, SPECTRA_PEAK_K,
                     TEST_MS)

__all__ = ["render_markdown"]


def render_markdown(result) -> str:
    """``report.md`` of a :class:`~hsiffc.reports.paper.PaperResult`: every table with the
    paper's values beside ours, and links to the figures of :func:`paper_figures`."""
    sim, em, emva_note, timing = result.simulated, result.emva, result.emva_note, result.timing
    t1, t2, f2, f4, f5, sp, tr = (sim[k] for k in ("table1", "table2", "fig2", "fig4", "fig5",
                                                   "fig6", "tradeoff"))
    p1, p2 = PAPER_VALUES["table1_alpha_percent"], PAPER_VALUES["table2_improvement_pp"]
    thr = sim["threshold_percent"]
    L = [f"# The paper's section V, reproduced (hsiffc {__version__})", "",
         f"Simulated 8-band sensor {sim['shape'][0]} x {sim['shape'][1]} px (seed {sim['seed']}); "
         f"threshold {thr:g} %. Values in parentheses are the paper's. Total run time "
         f"{timing.get('total_s', timing['compute_total_s']):.1f} s.", "",
         "## Fig. 4: calibration of a and b", "",
         f"{f4['n_illuminations']} illuminations of lamp A (paper: 16); pixel {tuple(f4['pixel'])} "
         f"of band 1: a = {f4['a_dn_per_ms']:.3g} DN/ms (true {f4['a_true_dn_per_ms']:.3g}), "
         f"b = {f4['b_per_dn']:.5f} /DN (true {f4['b_true_per_dn']:.5f}); leakage at 800 DN "
         f"{f4['leak_at_800_dn_per_ms']:.2f} DN/ms (paper: about 2). Over the sensor the median "
         f"error is {100 * f4['sensor_median_abs_rel_error_b']:.1f} % in b and "
         f"{f4['sensor_median_abs_error_ln_a']:.2f} in ln a.", "",
         "![Fig. 4](fig4_saturation_vs_rate.png)", "",
         "## Fig. 5: simulated response with and without leakage, lamp B", "",
         "| quantity | ours | paper |", "|---|---|---|",
         f"| k (DN/ms) | {f5['k_dn_per_ms']:.2f} | about 2 |",
         f"| dynamic saturation (DN) | {f5['dynamic_saturation_dn']:.0f} (measured plateau "
         f"{f5['measured_plateau_dn']:.0f}) | about 800 |",
         f"| leakage at 800 DN (DN/ms) | {f5['leak_at_800_dn_per_ms']:.2f} | about 2 |",
         f"| leakage visible after (ms): linear model above the data by > 3 standard errors "
         f"| {fmt_value(f5['leakage_visible_after_ms'], 0)} | about 430 |",
         f"| ... by > 5 % of the signal | {fmt_value(f5['linear_5pct_high_after_ms'], 0)} | |",
         f"| RMS error, leakage model (DN) | {f5['rms_leakage_dn']:.1f} "
         f"(<= 430 ms: {f5['rms_leakage_early_dn']:.1f}, "
         f"later: {f5['rms_leakage_late_dn']:.1f}) | - |",
         f"| RMS error, linear model (DN) | {f5['rms_linear_dn']:.1f} "
         f"(<= 430 ms: {f5['rms_linear_early_dn']:.1f}, "
         f"later: {f5['rms_linear_late_dn']:.1f}) | - |",
         "", "![Fig. 5](fig5_response_lamp_b.png)", "",
         "## Fig. 2: points tagged by alpha", "",
         "| tag | exposure (ms) | response (DN) | alpha, k ~ Y/t (%) | alpha, k ~ (Y - dark)/t (%) "
         "| paper alpha (%) |", "|---|---|---|---|---|---|"]
    for name, tag in f2["tags"].items():
        L.append(f"| {name} | {tag['exposure_ms']:.0f} | {tag['response_dn']:.0f} | "
                 f"{tag['alpha_percent']:.2f} | {tag['alpha_signal_percent']:.2f} | "
                 f"{tag['paper_alpha_percent']:g} |")
    L += ["", f"The model reaches 99 % of its dynamic saturation signal at "
              f"{fmt_value(f2['t_99pct_saturation_ms'], 0)} ms (paper: saturated near 600 ms).", "",
          "![Fig. 2](fig2_alpha_tags.png)", "",
          f"## Table I: alpha (%) of the training images, [selected] at {thr:g} %", "",
          "| band | " + " | ".join(f"{e:g} ms" for e in t1.exposures_ms) + " |",
          "|---" * (len(t1.exposures_ms) + 1) + "|"]
    for band in range(t1.alpha.shape[0]):
        cells = []
        for j, e in enumerate(t1.exposures_ms):
            txt = f"{t1.alpha[band, j]:.2f}"
            if t1.selected_ms[band] == e:
                txt = f"**[{txt}]**"
            if band + 1 in p1:
                txt += f" ({p1[band + 1][j]:.2f})"
            cells.append(txt)
        L.append(f"| {band + 1} | " + " | ".join(cells) + " |")
    L += ["", "## Table II: uniformity improvement (percentage points) by two-point FFC", "",
          "Computed with the shipped stages: per training exposure a `Pipeline` of "
          "`create(\"dark\")` (master dark matched to each frame's exposure) and "
          "`create(\"two_point_ffc\", exposure_ms=...)` (eq. 5), fitted on the 10-frame flats and "
          "darks and applied to every raw test frame: the code `hsiffc correct` runs.", "",
          f"Test: {t2['n_test_frames']} raw frames at {TEST_MS} ms under lamp B; mean over the "
          "frames (standard error in the CSV); **bold**: best column; [brackets]: selected by "
          "alpha.", "",
          "| band | " + " | ".join(f"{e:g} ms" for e in t2["exposures_ms"])
          + " | best within 2 SE |",
          "|---" * (len(t2["exposures_ms"]) + 2) + "|"]
    for band in range(t2["improvement_pp"].shape[0]):
        cells = []
        for j, e in enumerate(t2["exposures_ms"]):
            txt = f"{t2['improvement_pp'][band, j]:+.3f}"
            if t2["best_ms"][band] == e:
                txt = f"**{txt}**"
            if t2["selected_ms"][band] == e:
                txt = f"[{txt}]"
            if band + 1 in p2:
                txt += f" ({p2[band + 1][j]:+.2f})"
            cells.append(txt)
        ok = "yes" if t2["selected_within_2se_of_best"][band] else "no"
        L.append(f"| {band + 1} | " + " | ".join(cells) + f" | {ok} |")
    sel_best = int(np.sum(t2["selected_ms"] == t2["best_ms"]))
    worse = int(np.sum(t2["improvement_pp"][:, -1] < np.array(
        [t2["improvement_pp"][b, list(t2["exposures_ms"]).index(s)] if np.isfinite(s) else np.nan
         for b, s in enumerate(t2["selected_ms"])])))
    L += ["", "The same improvement when the raw test image's non-uniformity is taken after "
              "subtracting the dark (eq. 6 then has no dark offset in its denominator; the "
              "corrected image has none either):", "",
          "| band | test level (DN above dark) | "
          + " | ".join(f"{e:g} ms" for e in t2["exposures_ms"]) + " |",
          "|---" * (len(t2["exposures_ms"]) + 2) + "|"]
    for band in range(t2["improvement_pp"].shape[0]):
        L.append(f"| {band + 1} | {t2['test_signal_dn'][band]:.0f} | "
                 + " | ".join(f"{v:+.3f}" for v in t2["improvement_dark_subtracted_pp"][band])
                 + " |")
    L += ["", "Eq. (6) on a single frame counts the test frame's temporal noise as non-uniformity. "
              "The fixed-pattern non-uniformity (EMVA 1288: spatial variance of the mean of the "
              f"{t2['n_test_frames']} test frames less their temporal variance / "
              f"{t2['n_test_frames']}, in % of the signal above dark) shows what the correction "
              "removes:", "",
          "| band | raw | " + " | ".join(f"{e:g} ms" for e in t2["exposures_ms"]) + " |",
          "|---" * (len(t2["exposures_ms"]) + 2) + "|"]
    for band in range(t2["fpn_percent"].shape[0]):
        L.append(f"| {band + 1} | {t2['fpn_raw_percent'][band]:.3f} | "
                 + " | ".join(f"{v:.3f}" for v in t2["fpn_percent"][band]) + " |")
    L += ["", f"alpha selects the best column in {sel_best} of {len(t2['best_ms'])} bands and a "
              f"column within two standard errors of it in "
              f"{int(np.sum(t2['selected_within_2se_of_best']))}; the longest exposure is worse "
              f"than the selected one in {worse} bands.", "",
          "## Fig. 6: spectra of lamp B at 11 exposures", "",
          f"Band means of the dark-subtracted frames (no flat-field), normalised by their maximum. "
          f"A spectrum is invalid when any band's median alpha exceeds {thr:g} %. Light: lamp B "
          f"with the brightest band at {SPECTRA_PEAK_K:g} DN/ms.", "",
          "| exposure (ms) | valid | max band alpha (%) | angle to best valid (deg) "
          "| angle to truth (deg) | per-tile angle to truth (deg) |", "|---|---|---|---|---|---|"]
    for i, e in enumerate(sp["exposure_ms"]):
        L.append(f"| {e:.3f} | {'yes' if sp['valid'][i] else 'no'} | "
                 f"{sp['alpha_percent'][:, i].max():.2f} | {sp['angle_to_best_deg'][i]:.3f} | "
                 f"{sp['angle_to_truth_deg'][i]:.3f} | {sp['tile_angle_to_truth_deg'][i]:.2f} |")
    L += ["", f"Mean spectral angle between valid spectra: "
              f"{fmt_value(sp['mean_angle_valid_pairs_deg'], 3)} deg; between an invalid and a valid "
              f"one: {fmt_value(sp['mean_angle_invalid_valid_pairs_deg'], 3)} deg; first invalid "
              f"exposure {fmt_value(sp['first_invalid_ms'], 3)} ms (paper: deformed above 29 ms).", "",
          "![Fig. 6](fig6_spectra.png)", "",
          "## Trade-off: SNR, spectral correctness and response uniformity against the threshold",
          "",
          "For every threshold 1-100 %: per band the longest training exposure (3.225-38.7 ms, "
          "lamp A) under it; SNR = mean over bands of the single-frame SNR of that flat (dB); "
          "RU = mean over bands of the Table II improvement with it; SC = mean spectral angle "
          "between each mosaic tile's lamp-B spectrum at the longest of the 11 Fig. 6 exposures "
          "whose alpha stays under the threshold and the tile's true spectrum. Each criterion "
          "is scaled to [0, 1] over the thresholds (1 = best) and combined with the weights.", "",
          "| weights | chosen threshold (%) | training ms per band | spectral exposure (ms) |",
          "|---|---|---|---|"]
    w = tr["weights"]
    L.append(f"| **snr={w['snr']:g}, sc={w['sc']:g}, ru={w['ru']:g} (this run)** | "
             f"**{tr['chosen_threshold_percent']:g}** | "
             f"{', '.join(f'{v:g}' for v in tr['chosen']['selected_ms'])} | "
             f"{tr['chosen']['spectral_ms']:g} |")
    for name, pr in tr["presets"].items():
        L.append(f"| {name} | {pr['threshold_percent']:g} | "
                 f"{', '.join(f'{v:g}' for v in pr['selected_ms'])} | {pr['spectral_ms']:g} |")
    c = tr["chosen"]
    L += ["", f"At the chosen threshold: SNR {c['snr_db']:.1f} dB, RU {c['ru_pp']:+.3f} pp, SC "
              f"{c['sc_tile_deg']:.2f} deg per tile.", "", "![trade-off](tradeoff.png)", "",
          "## The same questions on the real EMVA 1288 sweep", ""]
    if em is None:
        L += [emva_note, ""]
    else:
        L += [f"`{em['source']}`: {em['frame_shape'][0]} x {em['frame_shape'][1]} px, "
              f"{em['bit_depth']}-bit, {em['n_light_steps']} usable light steps. Two-point FFC "
              f"trained at each candidate flat (2-frame mean less the 2-frame dark at the same "
              f"exposure) and tested at the {len(em['test_steps'])} other light steps with at "
              f"least {EMVA_MIN_SIGNAL_DN:g} DN of signal and at most "
              f"{100 * EMVA_MAX_CLIPPED:g} % clipped pixels; alpha from a joint calibration of the "
              f"sweep.", "",
              "| flat step | signal (DN) | clipped (%) | median alpha (%) | p95 alpha (%) "
              "| mean residual non-uniformity, eq. (6) (%) | mean fixed-pattern "
              "non-uniformity (%) |", "|---|---|---|---|---|---|---|"]
        for i, r in enumerate(em["candidates"]):
            tag = (" **best**" if i == em["best_index"] else "") + \
                  (" [alpha]" if i == em["selected_index"] else "")
            L.append(f"| {r['step']}{tag} | {r['signal_dn']:.1f} | "
                     f"{100 * r['clipped_fraction']:.2f} | {r['alpha_median_percent']:.3g} | "
                     f"{r['alpha_p95_percent']:.3g} | {r['mean_nonuniformity_percent']:.3f} | "
                     f"{r['mean_fpn_percent']:.3f} |")
        b, s = em["best_index"], em["selected_index"]
        rb = em["candidates"][b]
        txt = (f"Without FFC the mean non-uniformity is "
               f"{em['raw_mean_nonuniformity_percent']:.3f} %. "
               f"The best flat is step {rb['step']} ({rb['signal_dn']:.0f} DN, "
               f"{rb['mean_nonuniformity_percent']:.3f} %).")
        if s is None:
            txt += f" No candidate has a median alpha under {em['threshold_percent']:g} %."
        else:
            rs = em["candidates"][s]
            txt += (f" alpha (median under {em['threshold_percent']:g} %) selects step "
                    f"{rs['step']} ({rs['signal_dn']:.0f} DN, "
                    f"{rs['mean_nonuniformity_percent']:.3f} %"
                    f", {rs['mean_nonuniformity_percent'] - rb['mean_nonuniformity_percent']:+.3f} "
                    "pp from the best).")
        rf = em["candidates"][em["best_fpn_index"]]
        txt += (" Eq. (6) on the 2-frame test means is dominated by their temporal noise (the "
                "dotted line of the figure). The fixed-pattern non-uniformity (EMVA 1288: "
                "covariance of the two test frames, each corrected alone; temporal noise taken "
                f"out) is {em['raw_mean_fpn_percent']:.3f} % without FFC and "
                f"{rf['mean_fpn_percent']:.3f} % after the best two-point flat (step "
                f"{rf['step']}, {rf['signal_dn']:.0f} DN), mean over the test levels: a flat "
                "from one 2-frame step prints its own temporal noise into every corrected "
                "frame. For a 100-frame flat and the model-based correction (`model_ffc`) on "
                "held-out steps see `hsiffc study-ffc`.")
        L += ["", txt, "", "![EMVA](emva_ffc_levels.png)", ""]
    L += ["## Run time", "", "| part | seconds |", "|---|---|"]
    for k, v in timing.items():
        L.append(f"| {k.replace('_s', '')} | {v:.1f} |")
    L += ["", "Every number is in the CSV files beside this report; `summary.json` has them all.",
          ""]
    return "\n".join(L)


