"""Flat-field correction on the real EMVA 1288 CMOS sweep, held out: raw, two-point, model.

The sweep's light steps alternate between training and test: the calibration is fitted on the
even light steps and all dark steps, and every correction is measured on the odd light steps
(two frames each), with the fixed-pattern non-uniformity of :mod:`hsiffc.uniformity`, so the
temporal noise does not count. Corrections, all run as shipped pipelines:

* ``two_point_2frame``: ``dark`` (per-pixel line through all dark masters) + ``two_point_ffc``
  with the flat = the even 2-frame step nearest ``FLAT_LEVEL_DN``;
* ``two_point_stack``: the same with the flat = the measurement's 100-frame flat stack (the
  EMVA 1288 spatial set, ``meta["spatial_steps"]`` of the reader);
* ``model_ffc``: the model-based correction from the calibration, trained on all training
  frames (the even steps, the darks and the flat stack);
* ``model_ffc_calibration``: the same from the calibration alone (no training frames, the
  calibration's dark): what ``hsiffc correct`` applies by default.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..calibrate import calibrate
from ..frame import Frame
from ..io import read_sweep
from ..stages import Pipeline, create
from .sweep_uniformity import summarise, sweep_uniformity

__all__ = ["FFCStudy", "run_ffc_study", "render_markdown", "to_dict", "write_ffc_study", "METHODS",
           "FLAT_LEVEL_DN"]

log = logging.getLogger(__name__)

METHODS = ("two_point_2frame", "two_point_stack", "model_ffc", "model_ffc_calibration")
FLAT_LEVEL_DN = 125.0
GOAL_PERCENT = 0.3  # model_ffc from 30 DN to the top of the valid range


@dataclass
class FFCStudy:
    """Result of :func:`run_ffc_study` (render with :func:`render_markdown`)."""

    source: str
    steps: list  # StepUniformity of every odd (test) step
    summary: list  # per signal range (see sweep_uniformity.summarise)
    flat_2frame: dict  # step, exposure_ms, signal_dn
    flat_stack: dict  # step, n_frames, exposure_ms, signal_dn
    calibration: dict  # identity, training steps
    uncertainty: dict  # model_ffc's per-band factor uncertainties
    goals: dict = field(default_factory=dict)
    worst: dict = field(default_factory=dict)


def _split(sweep):
    kinds = {int(s): str(sweep.kind[np.flatnonzero(sweep.step == s)[0]]) for s in sweep.steps()}
    sweep_steps = sweep.meta.get("sweep_steps", list(kinds))
    spatial = sweep.meta.get("spatial_steps", [])
    light = [s for s in sweep_steps if kinds[s] == "light"]
    darks = [s for s in kinds if kinds[s] == "dark"]
    flat = [s for s in spatial if kinds[s] == "light"]
    if not flat:
        raise ValueError(f"{sweep.source}: no flat stack (EMVA 1288 spatial light step) found")
    return light[0::2], light[1::2], darks, flat[0]


def run_ffc_study(emva_dir, *, calibration=None) -> FFCStudy:
    """Run the held-out FFC study on an EMVA 1288 measurement folder.

    Parameters
    ----------
    emva_dir : path
        Folder (or descriptor) of an EMVA 1288 measurement with a spatial flat stack.
    calibration : Calibration, optional
        A calibration of the even light steps and the darks (made here when not given; about
        30 s for the 256 x 128 ROI on two cores).
    """
    sweep = read_sweep(emva_dir)
    even, odd, darks, flat_step = _split(sweep)
    if calibration is None:
        log.info("calibrating on %d even light steps and %d dark steps", len(even), len(darks))
        calibration = calibrate(sweep.select(np.isin(sweep.step, even + darks)))
    frames = Frame.list_from_sweep(sweep)
    by_step: dict = {}
    for f in frames:
        by_step.setdefault(f.meta["step"], []).append(f)
    dark_frames = [f for s in darks for f in by_step[s]]
    dark_stage = create("dark", match="scale", average="mean").fit(dark_frames)
    dark_for = (lambda t: dark_stage.dark_for(t, sweep.frame_shape)[0])
    level = {s: float(np.mean([f.data.mean() for f in by_step[s]])
                      - dark_for(by_step[s][0].exposure_ms).mean()) for s in even + [flat_step]}
    flat2 = min(even, key=lambda s: abs(level[s] - FLAT_LEVEL_DN))

    def two_point(step):
        return Pipeline([("dark", create("dark", match="scale", average="mean")),
                         ("ffc", create("two_point_ffc", exposure_ms=by_step[step][0].exposure_ms,
                                        normalisation="mean_gain", average="mean"))]
                        ).fit(dark_frames + by_step[step])

    model = Pipeline([("ffc", create("model_ffc", calibration=calibration))]).fit(
        [f for s in even + [flat_step] for f in by_step[s]] + dark_frames)
    alone = Pipeline([("ffc", create("model_ffc", calibration=calibration).fit([]))])
    corrections = {"two_point_2frame": two_point(flat2), "two_point_stack": two_point(flat_step),
                   "model_ffc": model, "model_ffc_calibration": alone}
    test_frames = [f for s in odd for f in by_step[s]]
    steps = sweep_uniformity(test_frames, corrections, dark_for=dark_for)
    summary = summarise(steps, METHODS)
    res = FFCStudy(
        source=str(sweep.source), steps=steps, summary=summary,
        flat_2frame={"step": int(flat2), "exposure_ms": by_step[flat2][0].exposure_ms,
                     "signal_dn": level[flat2], "n_frames": len(by_step[flat2])},
        flat_stack={"step": int(flat_step), "exposure_ms": by_step[flat_step][0].exposure_ms,
                    "signal_dn": level[flat_step], "n_frames": len(by_step[flat_step])},
        calibration={"identity": calibration.identity, "light_steps": len(even),
                     "dark_steps": len(darks)},
        uncertainty=model.named_steps["ffc"].uncertainty_)
    res.goals, res.worst = _goals(summary)
    return res


def _goals(summary):
    """Whether model_ffc meets the issue's goals, and its worst step from 30 DN up."""
    best_tp, below, worst = {}, True, {"fpn_percent": -1.0}
    at_most_best = True
    for row in summary:
        m = row["methods"]
        if "model_ffc" not in m:
            continue
        lo = row["signal_range_dn"][0]
        best = min(m[k]["fpn_percent_median"] for k in ("two_point_2frame", "two_point_stack"))
        best_tp[f"{lo:g}"] = best
        at_most_best &= m["model_ffc"]["fpn_percent_median"] <= best
        if lo >= 30:
            below &= m["model_ffc"]["fpn_percent_median"] <= GOAL_PERCENT
            if m["model_ffc"]["fpn_percent_max"] > worst["fpn_percent"]:
                worst = {"fpn_percent": m["model_ffc"]["fpn_percent_max"],
                         "step": m["model_ffc"]["worst_step"],
                         "signal_dn": m["model_ffc"]["worst_signal_dn"]}
    return ({"model_at_most_0.3_percent_from_30_dn": bool(below),
             "model_at_most_best_two_point_every_range": bool(at_most_best)}, worst)


def _step(res, step):
    return next(s for s in res.steps if s.step == step)


def render_markdown(res: FFCStudy) -> str:
    """The study as a Markdown page (tables, goals, the worst step and what limits it)."""
    names = {"raw": "raw", "two_point_2frame": "two-point, flat = one 2-frame step at "
             f"{res.flat_2frame['signal_dn']:.0f} DN",
             "two_point_stack": f"two-point, flat = the {res.flat_stack['n_frames']}-frame "
             f"stack at {res.flat_stack['signal_dn']:.0f} DN",
             "model_ffc": "model_ffc (calibration + flat stack)",
             "model_ffc_calibration": "model_ffc (calibration alone: `hsiffc correct`'s "
             "default)"}
    cols = ("raw", *METHODS)
    lines = ["# Flat-field correction on the real EMVA 1288 CMOS sweep (held out)", "",
             f"Data: `{res.source}`. Calibration ({res.calibration['identity']}) on the "
             f"{res.calibration['light_steps']} even light steps and "
             f"{res.calibration['dark_steps']} dark steps; every figure is measured on the odd "
             "light steps, which no correction saw. Fixed-pattern non-uniformity in the EMVA "
             "1288 way (covariance of the two frames of a step: temporal noise removed), median "
             "over the steps of a signal range (steps with more than 1 % of pixels clipped left "
             "out); all methods over the same pixels of a step (no DQ flag in any frame).", "",
             "| signal (DN above dark) | steps | " + " | ".join(names[c] for c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for row in res.summary:
        lo, hi = row["signal_range_dn"]
        cells = [f"{row['methods'][c]['fpn_percent_median']:.2f} %" if c in row["methods"]
                 else "-" for c in cols]
        lines.append(f"| {lo:g}-{hi:g} | {row['n_steps']} | " + " | ".join(cells) + " |")
    lines += ["", "Worst single step per range (percent):", "",
              "| signal (DN) | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for row in res.summary:
        lo, hi = row["signal_range_dn"]
        cells = [f"{row['methods'][c]['fpn_percent_max']:.2f} (step {row['methods'][c]['worst_step']})"
                 if c in row["methods"] else "-" for c in cols]
        lines.append(f"| {lo:g}-{hi:g} | " + " | ".join(cells) + " |")
    g = res.goals
    lines += ["", "Goals: model_ffc at or below 0.3 % from 30 DN up: "
              f"**{'met' if g['model_at_most_0.3_percent_from_30_dn'] else 'not met'}**; at or "
              "below the best two-point in every range: "
              f"**{'met' if g['model_at_most_best_two_point_every_range'] else 'not met'}**."]
    if res.worst.get("step") is not None:
        s = _step(res, res.worst["step"])
        fp = s.corrected["model_ffc"]
        lines += ["", f"Worst model_ffc step from 30 DN up: step {s.step} at "
                  f"{s.signal_dn:.0f} DN, {fp.pooled_fpn_percent:.2f} % (+- "
                  f"{float(np.nanmean(fp.fpn_se_percent)):.2f} % measurement error from two "
                  f"frames), {100 * s.clipped_fraction:.2f} % of its pixels clipped and "
                  f"{100 * s.flagged_fraction:.2f} % flagged. Near full scale the response "
                  "levels off: the correction rests on the fitted leakage a and b, and the "
                  "model alpha amplifies the noise of the inversion like 1 / (1 - alpha)."]
    u = res.uncertainty["bands"][0]
    lines += ["", "## What limits model_ffc: the uncertainty of each pixel's factor", "",
              f"- sweep fit alone: median {u['sigma_sweep_median_percent']:.3f} % per pixel "
              f"(`sigma_ln_g` of the calibration, {res.calibration['light_steps']} two-frame "
              "steps);",
              f"- model inconsistency with the flat stack beyond both noises: "
              f"{u['model_inconsistency_percent']:.3f} %;"]
    if "flat0_sigma_median_percent" in u:
        lines.append(f"- the {res.flat_stack['n_frames']}-frame flat stack alone: median "
                     f"{u['flat0_sigma_median_percent']:.3f} % (its temporal noise / "
                     f"sqrt({res.flat_stack['n_frames']}));")
    lines += [f"- combined (inverse variance): RMS {u['sigma_combined_rms_percent']:.3f} %: "
              "the fixed-pattern floor the calibration data set where the response is linear. The "
              "flat stack's share falls to zero at 5 % model alpha (parameter "
              "`flat_alpha_percent`); above that the sweep fit alone sets the floor, and near "
              "full scale the errors of the fitted leakage a and b add.", "",
              "Eq. (6) on single frames (temporal noise included) for comparison, median per "
              "range:", "", "| signal (DN) | " + " | ".join(cols) + " |",
              "|---|" + "---|" * len(cols)]
    for row in res.summary:
        lo, hi = row["signal_range_dn"]
        cells = [f"{row['methods'][c]['eq6_percent_median']:.2f} %" if c in row["methods"]
                 else "-" for c in cols]
        lines.append(f"| {lo:g}-{hi:g} | " + " | ".join(cells) + " |")
    lines += ["", "Made by `hsiffc study-ffc OUTDIR` (function "
              "`hsiffc.reports.ffc_study.run_ffc_study`)."]
    return "\n".join(lines) + "\n"



def to_dict(res: FFCStudy) -> dict:
    """JSON-safe form of the study (the per-step table in the ``hsiffc uniformity`` format)."""
    from .sweep_uniformity import to_json

    doc = to_json(res.steps, METHODS, res.summary)
    doc.update(source=res.source, flat_2frame=res.flat_2frame, flat_stack=res.flat_stack,
               calibration=res.calibration, uncertainty=res.uncertainty, goals=res.goals,
               worst=res.worst)
    return doc


def write_ffc_study(emva_dir, outdir, *, calibration=None) -> list:
    """Run the study and write ``ffc_study.md``, ``ffc_study.json`` and ``ffc_study.png``
    into ``outdir`` (atomically; existing files only under the caller's overwrite policy)."""
    import json
    from pathlib import Path

    from ..jsonsafe import json_safe
    from ..atomic import atomic_path, atomic_write_text
    from .sweep_uniformity import plot_uniformity

    res = run_ffc_study(emva_dir, calibration=calibration)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "ffc_study.md", out / "ffc_study.json", out / "ffc_study.png"]
    atomic_write_text(paths[0], render_markdown(res) + "\n![fixed-pattern non-uniformity "
                      "against signal](ffc_study.png)\n")
    atomic_write_text(paths[1], json.dumps(json_safe(to_dict(res)), indent=1) + "\n")
    fig = plot_uniformity(res.steps, METHODS, title="EMVA 1288 CMOS sweep, odd (held-out) steps")
    with atomic_path(paths[2]) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return paths
