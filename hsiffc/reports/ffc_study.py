"""Flat-field correction on any EMVA 1288-style sweep, held out: raw, two-point, model.

The sweep's light steps alternate between training and test: the calibration is fitted on the
even light steps, all dark steps and the flat stack, and every correction is measured on the
odd light steps (two frames each), with the fixed-pattern non-uniformity of
:mod:`hsiffc.flatfield.uniformity` (temporal noise removed). The raw figure subtracts the dark frames of
the step's own exposure and removes their temporal variance too (EMVA 1288 Release 4.0), so
neither a dark's noise nor a modelled dark's error counts as the raw pattern.

Signal ranges are fractions of the sensor's saturation (:data:`RANGES_FRACTION`), so one table
reads the same at 8 or 16 bits: saturation is the mean signal above dark of the brightest light
step with at most 1 % of its pixels clipped, clipped meaning at the sweep's highest raw value
(the ADC's full scale, or a full well below it), and below the dose where a response that
levels off (leakage's dynamic saturation) grows at less than half its linear slope: steps
beyond either are saturated and left out of the ranges. Corrections, all run as shipped
pipelines:

* ``two_point_2frame``: ``dark`` + ``two_point_ffc`` with the flat = the even 2-frame step
  nearest half saturation;
* ``two_point_stack``: the same with the flat = the measurement's flat stack (the EMVA 1288
  spatial set, ``meta["spatial_steps"]`` of the reader), when it has one;
* ``model_ffc``: the model-based correction from the calibration, trained on all training
  frames (the even steps, the darks and the flat stack);
* ``model_ffc_calibration``: the same from the calibration alone (no training frames, the
  calibration's dark): what ``hsiffc correct`` applies by default. The calibration carries the
  flat stack (:func:`hsiffc.calibrate.flats.add_flat_stacks`, as ``hsiffc calibrate`` does), so
  the two differ only where the training frames add something.

The dark of the two-point corrections is a per-pixel line through the dark masters when darks
were recorded at two or more exposures, else the master of the frame's exposure (a light sweep
at one exposure needs no scaling).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..calibrate import calibrate
from ..calibrate.flats import add_flat_stacks
from ..data.dq import DQ
from ..errors import DataFormatError
from ..data.frame import Frame
from ..io import read_sweep
from ..stages import Pipeline, create
from ..stages.refchecks import ReferenceWarning
from ..data.sweep import Sweep
from .sweep_uniformity import dark_frames_by_exposure, summarise, sweep_uniformity

__all__ = ["FFCStudy", "run_ffc_study", "render_markdown", "to_dict", "write_ffc_study", "METHODS",
           "RANGES_FRACTION", "FLAT_FRACTION", "check_rule", "saturation_level"]

log = logging.getLogger(__name__)

METHODS = ("two_point_2frame", "two_point_stack", "model_ffc", "model_ffc_calibration")
#: signal ranges of the summary, in fractions of saturation
RANGES_FRACTION = ((0.02, 0.12), (0.12, 0.40), (0.40, 0.80), (0.80, 1.00))
#: the 2-frame flat: the even step nearest this fraction of saturation
FLAT_FRACTION = 0.5
#: model_ffc within this factor of the stack two-point from RULE_FROM_FRACTION up
RULE_STACK_FACTOR = 1.10
RULE_FROM_FRACTION = 0.12
MAX_CLIPPED_FRACTION = 0.01
#: the model alpha (percent) beyond which a step is saturated (the response grows at less than
#: 1 - alpha of its linear slope): model_ffc's default ``alpha_limit_percent``, where it flags
#: a pixel LEAKAGE as not correctable
SATURATION_ALPHA_PERCENT = 50.0


@dataclass
class FFCStudy:
    """Result of :func:`run_ffc_study` (render with :func:`render_markdown`)."""

    source: str
    steps: list  # StepUniformity of every odd (test) step
    summary: list  # per signal range (see sweep_uniformity.summarise)
    flat_2frame: dict  # step, exposure_ms, signal_dn
    flat_stack: dict | None  # step, n_frames, exposure_ms, signal_dn (None: no stack)
    calibration: dict  # identity, training steps
    uncertainty: dict  # model_ffc's per-band factor uncertainties
    saturation: dict = field(default_factory=dict)  # signal_dn, clip_code_dn, bit_depth
    goals: dict = field(default_factory=dict)
    worst: dict = field(default_factory=dict)
    goal_percent: float | None = None

    @property
    def methods(self) -> tuple:
        """The corrections measured (no stack two-point without a flat stack)."""
        return tuple(m for m in METHODS if self.flat_stack is not None
                     or m != "two_point_stack")


def _split(sweep):
    kinds = {int(s): str(sweep.kind[np.flatnonzero(sweep.step == s)[0]]) for s in sweep.steps()}
    sweep_steps = sweep.meta.get("sweep_steps", list(kinds))
    spatial = sweep.meta.get("spatial_steps", [])
    light = [s for s in sweep_steps if kinds[s] == "light"
             and (sweep.step == s).sum() >= 2]
    darks = [s for s in kinds if kinds[s] == "dark"]
    flat = [s for s in spatial if kinds[s] == "light"]
    if len(light) < 6:
        raise DataFormatError(f"{len(light)} light steps with two or more frames; the held-out "
                              "study needs at least 6 (every other one is held out)",
                              path=sweep.source or None)
    if not darks:
        raise DataFormatError("no dark step: the study needs dark frames to measure the raw "
                              "pattern above dark; record darks", path=sweep.source or None)
    return light[0::2], light[1::2], darks, (flat[0] if flat else None)


def _light(sweep, i) -> float:
    """The light a frame collected, in arbitrary units: photons where the sweep gives them,
    else its exposure (ms: a sweep at one light level)."""
    if sweep.photons is not None and np.isfinite(sweep.photons[i]):
        return float(sweep.photons[i])
    return float(sweep.exposure_ms[i])


def _levels_off(levels, compression: float = 0.1) -> bool:
    """True when the brightest step's signal lies ``compression`` or more below the line
    through the origin fitted to the steps in the lower half of the signal."""
    light, signal = (np.asarray(v, float) for v in zip(*levels))
    if np.unique(light).size < 3:  # a light sweep without photons: the light is unknown
        return False
    low = (signal <= 0.5 * signal.max()) & (signal > 0) & (light > 0)
    if low.sum() < 2:
        return False
    slope = float((light[low] * signal[low]).sum() / (light[low] ** 2).sum())
    top = int(np.argmax(light))
    return bool(signal[top] < (1 - compression) * slope * light[top])


def _dynamic_saturation(levels) -> float | None:
    """The signal (DN above dark) where the sensor's mean response stops measuring the light,
    or None where it does not level off: the brightest step below the first step (by light,
    in the upper half of the signal) to which the response grew at less than
    ``1 - SATURATION_ALPHA_PERCENT / 100`` of its slope through the lower half. Beyond it the
    leakage takes more than that share of the light (the model alpha at which model_ffc flags
    a pixel LEAKAGE: not correctable), so a step there is saturated like a clipped one."""
    light, signal = (np.asarray(v, float) for v in zip(*levels))
    if np.unique(light).size < 3:  # a light sweep without photons: the light is unknown
        return None
    order = np.argsort(light, kind="stable")
    light, signal = light[order], signal[order]
    low = (signal <= 0.5 * signal.max()) & (signal > 0) & (light > 0)
    if low.sum() < 2:
        return None
    slope = float((light[low] * signal[low]).sum() / (light[low] ** 2).sum())
    floor = (1.0 - SATURATION_ALPHA_PERCENT / 100.0) * slope
    for i in range(1, light.size):
        dl = light[i] - light[i - 1]
        if dl > 0 and signal[i] > 0.5 * signal.max() and (signal[i] - signal[i - 1]) < floor * dl:
            return float(signal[:i].max())
    return None


def saturation_level(sweep, steps, dark_for) -> dict:
    """The sensor's saturation for the summary's ranges.

    ``clip_code_dn``: the highest raw value of the sweep (the ADC's full scale, or a full well
    below it where the response stops there); ``signal_dn``: the mean signal above dark of the
    brightest of ``steps`` with at most 1 % of its pixels at that code and below the sensor's
    dynamic saturation (:func:`_dynamic_saturation`: a leaky response that levels off below the
    clip code; steps beyond it carry no measure of the light, and their raw figure is the
    spread of the pixels' saturation levels, which no flat field changes); ``reached``:
    whether some step has more clipped pixels, or the response levels off (the brightest step
    10 % or more below the line through the lower half of the signal, or beyond its dynamic
    saturation). False: the sweep stops below saturation, and ``signal_dn`` is only its
    brightest step."""
    code = float(np.max(sweep.data[np.isin(sweep.step, steps)]))
    best = None
    reached = False
    levels = []  # (light of the step, arbitrary units; signal above dark, DN)
    for s in steps:
        idx = np.flatnonzero(sweep.step == s)
        d = sweep.data[idx]
        if (d >= code).any(axis=0).mean() > MAX_CLIPPED_FRACTION:
            reached = True
            continue
        level = float(d.mean() - dark_for(float(sweep.exposure_ms[idx[0]])).mean())
        best = level if best is None else max(best, level)
        levels.append((_light(sweep, idx[0]), level))
    if best is not None and len(levels) >= 3:
        dynamic = _dynamic_saturation(levels)
        if dynamic is not None:
            best, reached = min(best, dynamic), True
        reached = reached or _levels_off(levels)
    if best is None or best <= 0:
        raise DataFormatError("every light step has more than 1 % of its pixels clipped at "
                              f"{code:g} DN: no saturation level below clipping; record light "
                              "steps below saturation", path=sweep.source or None)
    return {"signal_dn": best, "clip_code_dn": code, "reached": reached,
            "bit_depth": int(sweep.bit_depth),
            "full_scale_dn": int(sweep.full_scale_dn)}


def _dark_stage(dark_frames):
    exposures = {round(f.exposure_ms, 9) for f in dark_frames}
    # a line through the masters when darks span two or more exposures (less noise at every
    # exposure); a light sweep at one exposure has its darks there: no scaling needed
    return create("dark", match="scale" if len(exposures) >= 2 else "exposure",
                  average="mean").fit(dark_frames)


def run_ffc_study(source, *, calibration=None, goal_percent: float | None = None,
                  calibrate_kwargs=None) -> FFCStudy:
    """Run the held-out FFC study on an EMVA 1288 measurement folder or a :class:`Sweep`.

    Parameters
    ----------
    source : path or Sweep
        EMVA 1288 folder (or descriptor), or a sweep whose ``meta["spatial_steps"]`` lists its
        flat and dark stacks (and ``meta["sweep_steps"]`` the others); without a flat stack the
        stack two-point column is left out.
    calibration : Calibration, optional
        A calibration of the training steps (made here when not given, as ``hsiffc
        calibrate`` makes it: fitted on the even light steps and the darks, the flat stack
        folded in by :func:`hsiffc.calibrate.flats.add_flat_stacks`).
    goal_percent : float, optional
        A sensor-specific goal: model_ffc at or below it from 12 % of saturation up.
    calibrate_kwargs : dict, optional
        Passed to :func:`hsiffc.calibrate.calibrate`.
    """
    sweep = source if isinstance(source, Sweep) else read_sweep(source)
    even, odd, darks, flat_step = _split(sweep)
    train_light = even + ([flat_step] if flat_step is not None else [])
    if calibration is None:
        log.info("calibrating on %d even light steps and %d dark steps", len(even), len(darks))
        stacks = (None if flat_step is None else
                  sweep.select(np.isin(sweep.step, [flat_step] + darks)))
        calibration = calibrate(sweep.select(np.isin(sweep.step, even + darks)),
                                **{"flats": stacks, **(calibrate_kwargs or {})})
        if stacks is not None:  # as hsiffc calibrate does: the stack in the calibration
            calibration = add_flat_stacks(calibration, stacks)
    frames = Frame.list_from_sweep(sweep)
    by_step: dict = {}
    for f in frames:
        by_step.setdefault(f.meta["step"], []).append(f)
    dark_frames = [f for s in darks for f in by_step[s]]
    dark_stage = _dark_stage(dark_frames)
    dark_prepared = dark_stage.prepare()  # its dark line, made once
    dark_for = (lambda t: dark_prepared.dark_for(t, sweep.frame_shape)[0])
    sat = saturation_level(sweep, even + odd, dark_for)
    level = {s: float(np.mean([f.data.mean() for f in by_step[s]])
                      - dark_for(by_step[s][0].exposure_ms).mean()) for s in train_light}
    flat2 = min(even, key=lambda s: abs(level[s] - FLAT_FRACTION * sat["signal_dn"]))

    def two_point(step):
        with warnings.catch_warnings():  # flats across the range on purpose: not a campaign's
            warnings.simplefilter("ignore", ReferenceWarning)  # reference to check
            return Pipeline([("dark", _dark_stage(dark_frames)),
                             ("ffc", create("two_point_ffc",
                                            exposure_ms=by_step[step][0].exposure_ms,
                                            normalisation="mean_gain", average="mean"))]
                            ).fit(dark_frames + by_step[step])

    model = Pipeline([("ffc", create("model_ffc", calibration=calibration))]).fit(
        [f for s in train_light for f in by_step[s]] + dark_frames)
    alone = Pipeline([("ffc", create("model_ffc", calibration=calibration).fit([]))])
    corrections = {"two_point_2frame": two_point(flat2), "model_ffc": model,
                   "model_ffc_calibration": alone}
    if flat_step is not None:
        corrections["two_point_stack"] = two_point(flat_step)
    corrections = {m: corrections[m] for m in METHODS if m in corrections}
    test_frames = [f for s in odd for f in by_step[s]]
    steps = sweep_uniformity(test_frames, corrections, dark_for=dark_for,
                             dark_frames_for=dark_frames_by_exposure(dark_frames))
    _clipped_at_code(steps, test_frames, sat["clip_code_dn"])
    ranges = tuple((lo * sat["signal_dn"], hi * sat["signal_dn"] * (1.0 + 1e-9))
                   for lo, hi in RANGES_FRACTION)
    summary = summarise(steps, tuple(corrections), ranges=ranges)
    for row, (lo, hi) in zip(summary, RANGES_FRACTION):
        row["range_fraction"] = [lo, hi]
    res = FFCStudy(
        source=str(sweep.source), steps=steps, summary=summary,
        flat_2frame={"step": int(flat2), "exposure_ms": by_step[flat2][0].exposure_ms,
                     "signal_dn": level[flat2], "n_frames": len(by_step[flat2])},
        flat_stack=None if flat_step is None else {
            "step": int(flat_step), "exposure_ms": by_step[flat_step][0].exposure_ms,
            "signal_dn": level[flat_step], "n_frames": len(by_step[flat_step])},
        calibration={"identity": calibration.identity, "light_steps": len(even),
                     "dark_steps": len(darks)},
        uncertainty=model.named_steps["ffc"].uncertainty_, saturation=sat,
        goal_percent=goal_percent)
    res.goals, res.worst = check_rule(summary, goal_percent=goal_percent)
    return res


def _clipped_at_code(steps, frames, code):
    """Count pixels at the sweep's clip code (a full well below the ADC's full scale) as
    clipped too: the summary leaves steps with more than 1 % of them out."""
    by_step: dict = {}
    for f in frames:
        by_step.setdefault(f.meta["step"], []).append(f.raw)
    for s in steps:
        at = np.any([r >= code for r in by_step[s.step]], axis=0).mean()
        s.clipped_fraction = max(s.clipped_fraction, float(at))


def check_rule(summary, *, goal_percent=None) -> tuple[dict, dict]:
    """Whether model_ffc meets the rule on this sensor, and its worst step from 12 % up.

    The rule: model_ffc at or below raw in every range; within 10 % of the stack two-point
    (where there is one) from 12 % of saturation up; with ``goal_percent``, at or below it from
    12 % up. A difference within twice its standard error (the two medians' errors over the
    range's steps) does not break the comparisons: the frames cannot tell the two apart; such
    ranges are listed in ``goals["unresolved"]``.
    """
    ok_raw, ok_stack, ok_goal, worst = True, True, True, {"fpn_percent": -1.0}
    failures, unresolved = [], []
    for row in summary:
        m = row["methods"]
        if "model_ffc" not in m:
            continue
        lo = row.get("range_fraction", [row["signal_range_dn"][0]])[0]
        model = m["model_ffc"]
        root_n = np.sqrt(max(row["n_steps"], 1))

        def beyond(other, factor=1.0):
            """model_ffc above ``factor`` x other by more than twice the standard error of the
            difference (both medians' errors, over the range's steps): True; above it but
            within that: None (unresolved); else False."""
            se = np.hypot(model["fpn_se_percent_median"],
                          factor * other["fpn_se_percent_median"]) / root_n
            excess = model["fpn_percent_median"] - factor * other["fpn_percent_median"]
            return True if excess > 2 * se else (None if excess > 0 else False)

        what = {"raw": "above raw", "two_point_stack": "above 1.1 x the stack two-point"}
        checks = [("raw", 1.0)]
        if lo >= RULE_FROM_FRACTION - 1e-12 and "two_point_stack" in m:
            checks.append(("two_point_stack", RULE_STACK_FACTOR))
        for other, factor in checks:
            verdict = beyond(m[other], factor)
            if verdict:
                ok_raw &= other != "raw"
                ok_stack &= other == "raw"
                failures.append(f"{100 * lo:g} %: model_ffc {what[other]}")
            elif verdict is None:
                unresolved.append(f"{100 * lo:g} %: model_ffc {what[other]} within twice "
                                  "the standard error")
        if lo >= RULE_FROM_FRACTION - 1e-12:
            if goal_percent is not None and model["fpn_percent_median"] > goal_percent:
                ok_goal = False
                failures.append(f"{100 * lo:g} %: model_ffc above {goal_percent:g} %")
            if model["fpn_percent_max"] > worst["fpn_percent"]:
                worst = {"fpn_percent": model["fpn_percent_max"], "step": model["worst_step"],
                         "signal_dn": model["worst_signal_dn"]}
    goals = {"model_at_most_raw": bool(ok_raw),
             "model_within_10_percent_of_stack_two_point": bool(ok_stack),
             "failures": failures, "unresolved": unresolved}
    if goal_percent is not None:
        goals[f"model_at_most_{goal_percent:g}_percent_from_12_percent"] = bool(ok_goal)
    return goals, (worst if worst.get("step") is not None else {})


def _step(res, step):
    return next(s for s in res.steps if s.step == step)


def cell(figures, *, se: bool = False) -> str:
    """A table cell: the median percent (with its standard error when ``se``), "below noise"
    where the median fixed-pattern variance is not positive, "-" where the range has no step."""
    if figures is None:
        return "-"
    if figures.get("below_noise"):
        return f"below noise (< {2 * figures['fpn_se_percent_median']:.2f} %)"
    value = figures["fpn_percent_median"]
    if value != value:
        return "n/a"
    if se:
        return f"{value:.2f} ± {figures['fpn_se_percent_median']:.2f} %"
    return f"{value:.2f} %"


def range_label(row) -> str:
    """``12-40 % (492-1640 DN)``: a summary row's range in fractions of saturation and DN."""
    lo, hi = row["signal_range_dn"]
    if "range_fraction" in row:
        flo, fhi = row["range_fraction"]
        return f"{100 * flo:g}-{100 * fhi:g} % ({lo:.0f}-{hi:.0f} DN)"
    return f"{lo:g}-{hi:g} DN"


def method_names(res: FFCStudy) -> dict:
    """Column titles of the methods of a study."""
    names = {"raw": "raw", "two_point_2frame": "two-point, flat = one 2-frame step at "
             f"{res.flat_2frame['signal_dn']:.0f} DN",
             "model_ffc": "model_ffc (calibration + training frames)",
             "model_ffc_calibration": "model_ffc (calibration alone: `hsiffc correct`'s "
             "default)"}
    if res.flat_stack is not None:
        names["two_point_stack"] = (f"two-point, flat = the {res.flat_stack['n_frames']}-frame "
                                    f"stack at {res.flat_stack['signal_dn']:.0f} DN")
    return names


def render_markdown(res: FFCStudy, *, title: str | None = None) -> str:
    """The study as a Markdown page (tables, the rule, the worst step and what limits it)."""
    names = method_names(res)
    cols = ("raw", *res.methods)
    sat = res.saturation
    lines = [f"# {title or 'Flat-field correction held out'}", "",
             f"Data: `{res.source}` ({sat['bit_depth']}-bit; saturation "
             f"{sat['signal_dn']:.0f} DN above dark, clip code {sat['clip_code_dn']:.0f} DN). "
             f"Calibration ({res.calibration['identity']}) on the "
             f"{res.calibration['light_steps']} even light steps, "
             f"{res.calibration['dark_steps']} dark steps"
             + (" (the flat stack folded into it)" if res.flat_stack else "") + "; every figure "
             "is measured "
             "on the odd light steps, which no correction saw. Fixed-pattern non-uniformity in "
             "the EMVA 1288 way (temporal noise of the step's frames and of the dark frames of "
             "its exposure removed), median over the steps of a range of saturation (steps with "
             "more than 1 % of pixels clipped left out), ± its standard error; all methods over "
             "the same pixels of a step (no DQ flag in any frame).", "",
             "| signal (of saturation) | steps | " + " | ".join(names[c] for c in cols) + " |",
             "|---|---|" + "---|" * len(cols)]
    for row in res.summary:
        cells = [cell(row["methods"].get(c), se=True) for c in cols]
        lines.append(f"| {range_label(row)} | {row['n_steps']} | " + " | ".join(cells) + " |")
    lines += ["", "Worst single step per range (percent):", "",
              "| signal | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for row in res.summary:
        cells = [f"{row['methods'][c]['fpn_percent_max']:.2f} (step "
                 f"{row['methods'][c]['worst_step']})" if c in row["methods"] else "-"
                 for c in cols]
        lines.append(f"| {range_label(row)} | " + " | ".join(cells) + " |")
    g = res.goals
    verdict = lambda ok: "**met**" if ok else "**not met**"  # noqa: E731
    lines += ["", "Rule (on every sensor): model_ffc at or below raw in every range: "
              f"{verdict(g['model_at_most_raw'])}; within 10 % of the stack two-point from 12 % "
              f"of saturation up: {verdict(g['model_within_10_percent_of_stack_two_point'])}"
              + ("" if res.flat_stack else " (no flat stack: nothing to compare)") + "."]
    if res.goal_percent is not None:
        key = f"model_at_most_{res.goal_percent:g}_percent_from_12_percent"
        lines[-1] += (f" At or below {res.goal_percent:g} % from 12 % up: "
                      f"{verdict(g[key])}.")
    if g.get("failures"):
        lines[-1] += " Broken at: " + "; ".join(g["failures"]) + "."
    if g.get("unresolved"):
        lines[-1] += (" Not resolved by these frames (model_ffc higher, but by less than "
                      "twice the standard error): " + "; ".join(g["unresolved"]) + ".")
    if res.worst.get("step") is not None:
        s = _step(res, res.worst["step"])
        fp = s.corrected["model_ffc"]
        lines += ["", f"Worst model_ffc step from 12 % of saturation up: step {s.step} at "
                  f"{s.signal_dn:.0f} DN, {fp.pooled_fpn_percent:.2f} % (± "
                  f"{fp.pooled_fpn_se_percent:.2g} % measurement error), "
                  f"{100 * s.clipped_fraction:.2f} % of its pixels clipped and "
                  f"{100 * s.flagged_fraction:.2f} % flagged."]
    u = res.uncertainty["bands"][0]
    lines += ["", "## What limits model_ffc: the uncertainty of each pixel's factor", "",
              f"- sweep fit alone: median {u['sigma_sweep_median_percent']:.3f} % per pixel "
              f"(`sigma_ln_g` of the calibration);",
              f"- model inconsistency with the flat stacks beyond both noises: "
              f"{u['model_inconsistency_percent']:.3f} %;"]
    if "flat0_sigma_median_percent" in u and res.flat_stack:
        lines.append(f"- the {res.flat_stack['n_frames']}-frame flat stack alone: median "
                     f"{u['flat0_sigma_median_percent']:.3f} % (its temporal noise / "
                     f"sqrt({res.flat_stack['n_frames']}));")
    lines += [f"- combined (inverse variance): RMS {u['sigma_combined_rms_percent']:.3f} %: "
              "the fixed-pattern floor the calibration data set where the response is linear.",
              "", "Eq. (6) on single frames (temporal noise included) for comparison, median per "
              "range:", "", "| signal | " + " | ".join(cols) + " |",
              "|---|" + "---|" * len(cols)]
    for row in res.summary:
        cells = [f"{row['methods'][c]['eq6_percent_median']:.2f} %" if c in row["methods"]
                 else "-" for c in cols]
        lines.append(f"| {range_label(row)} | " + " | ".join(cells) + " |")
    lines += ["", "Made by `hsiffc study-ffc OUTDIR --emva FOLDER` (function "
              "`hsiffc.reports.ffc_study.run_ffc_study`)."]
    return "\n".join(lines) + "\n"


def to_dict(res: FFCStudy) -> dict:
    """JSON-safe form of the study (the per-step table in the ``hsiffc uniformity`` format)."""
    from .sweep_uniformity import to_json

    doc = to_json(res.steps, res.methods, res.summary)
    doc.update(source=res.source, flat_2frame=res.flat_2frame, flat_stack=res.flat_stack,
               calibration=res.calibration, uncertainty=res.uncertainty, goals=res.goals,
               worst=res.worst, saturation=res.saturation, goal_percent=res.goal_percent)
    return doc


def write_ffc_study(emva_dir, outdir, *, calibration=None, goal_percent=None) -> list:
    """Run the study and write ``ffc_study.md``, ``ffc_study.json`` and ``ffc_study.png``
    into ``outdir`` (atomically; existing files only under the caller's overwrite policy)."""
    import json
    from pathlib import Path

    from ..files.jsonsafe import json_safe
    from ..files.atomic import atomic_path, atomic_write_text
    from .sweep_uniformity import plot_uniformity

    res = run_ffc_study(emva_dir, calibration=calibration, goal_percent=goal_percent)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "ffc_study.md", out / "ffc_study.json", out / "ffc_study.png"]
    atomic_write_text(paths[0], render_markdown(res) + "\n![fixed-pattern non-uniformity "
                      "against signal](ffc_study.png)\n")
    atomic_write_text(paths[1], json.dumps(json_safe(to_dict(res)), indent=1) + "\n")
    fig = plot_uniformity(res.steps, res.methods, title=f"{res.source}: odd (held-out) steps",
                          ranges=tuple(r["signal_range_dn"] for r in res.summary))
    with atomic_path(paths[2]) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return paths
