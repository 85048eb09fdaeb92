"""``uniformity`` (fixed-pattern non-uniformity of a sweep, raw and corrected) and
``study-ffc`` (the held-out FFC study on the real EMVA 1288 sweep)."""

from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import HsiffcError, HsiffcWarning
from .common import add_input_options, add_overwrite, input_overrides, write_json


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    _add_uniformity(sub)
    _add_study(sub)


def _add_uniformity(sub):
    p = sub.add_parser(
        "uniformity", help="fixed-pattern non-uniformity of every step of a sweep, raw and "
                           "corrected (EMVA 1288: temporal noise removed)",
        description="For every light step with two or more frames: exposure, signal level (DN "
                    "above dark), clipped and flagged fractions, eq. (6) and the fixed-pattern "
                    "non-uniformity (EMVA 1288 Release 4.0: spatial variance of the step mean "
                    "minus temporal variance / frames), raw and after the correction: the "
                    "fitted pipeline given, else the model-based FFC (model_ffc) from the "
                    "calibration. A summary per signal range, JSON and an optional plot.")
    p.add_argument("sweep", type=Path, help="sweep: multi-page TIFF or EMVA 1288 folder/.txt")
    add_input_options(p)
    p.add_argument("--calibration", type=Path, default=None,
                   help="calibration (.npz): model_ffc corrects (or the pipeline uses it)")
    p.add_argument("--pipeline", type=Path, default=None,
                   help="fitted pipeline (.npz from 'hsiffc fit') to measure instead")
    p.add_argument("--json", type=Path, default=None,
                   help="also write every step's figures as JSON (the table is printed always)")
    p.add_argument("--plot", type=Path, default=None, help="also plot against signal (PNG)")
    add_overwrite(p)
    p.set_defaults(func=_cmd_uniformity, input_args=("sweep", "calibration", "pipeline"),
                   output_args=("json", "plot"))


def _correction(args):
    """The corrections to measure (name -> fitted pipeline or prepared stage) and the calibration."""
    from ..calibrate import Calibration
    from ..stages import Pipeline, create

    cal = Calibration.load(args.calibration) if args.calibration else None
    if args.pipeline is not None:
        if args.pipeline.suffix != ".npz":
            raise HsiffcError(f"{args.pipeline}: --pipeline takes a fitted pipeline (.npz from "
                              "'hsiffc fit'); fit a TOML description first")
        pipe = Pipeline.load(args.pipeline, calibration=cal)
        if any(s.name == "reconstruct" for _, s in pipe.steps):
            raise HsiffcError(f"{args.pipeline}: the pipeline reconstructs cubes; measure a "
                              "pipeline that keeps mosaic frames (H, W)")
        return {"pipeline": pipe}, cal
    if cal is not None:
        return {"model_ffc": create("model_ffc", calibration=cal).fit([]).prepare()}, cal
    return {}, cal


def _cmd_uniformity(args) -> int:
    import numpy as np

    from ..files.jsonsafe import json_safe
    from ..data.frame import Frame
    from ..io import read_sweep
    from ..reports.sweep_uniformity import (dark_frames_by_exposure, plot_uniformity,
                                            summarise, sweep_uniformity, to_json)

    corrections, cal = _correction(args)
    sweep = read_sweep(args.sweep, overrides=input_overrides(args))
    if cal is not None:
        cal.check_compatible(sweep)  # frame shape, bit depth and mosaic, naming the file
    frames = Frame.list_from_sweep(sweep)
    dark_frames = [f for f in frames if f.kind == "dark"]
    dark_for = None
    if dark_frames:  # raw figures: per-pixel line through all dark masters (low noise)
        from ..stages import create

        stage = create("dark", match="scale", average="mean",
                       calibration=cal).fit(dark_frames)
        prepared = stage.prepare()  # its dark line, made once
        dark_for = (lambda t: prepared.dark_for(t, sweep.frame_shape)[0])
        if len(stage.exposures_ms_) == 1 and cal is None:
            only = stage.exposures_ms_[0]
            if any(not np.isclose(f.exposure_ms, only, rtol=1e-6, atol=0.0)
                   for f in frames if f.kind == "light"):  # a light sweep at one exposure
                warnings.warn(f"{args.sweep}: dark frames at one exposure only ({only:g} ms): "
                              "their master is subtracted at every exposure, the dark "
                              "current not scaled; record darks at two exposures or give "
                              "--calibration for the dark at each exposure", HsiffcWarning,
                              stacklevel=2)  # has its darks there: nothing to scale
            dark_for = (lambda t, master=stage.masters_[0]: master)
    # raw figures: the dark frames of each step's exposure where there are two or more, their
    # temporal variance removed too (EMVA 1288), so no dark's noise or error counts as pattern
    steps = sweep_uniformity(frames, corrections, dark_for=dark_for,
                             dark_frames_for=dark_frames_by_exposure(frames))
    if not steps:
        raise HsiffcError(f"{args.sweep}: no light step with two or more frames; the fixed "
                          "pattern cannot be told from temporal noise with one frame per step")
    methods = tuple(corrections)
    ranges, fractions = _ranges(sweep, dark_for)
    summary = summarise(steps, methods, ranges=ranges)
    for row, frac in zip(summary, fractions or ()):
        row["range_fraction"] = list(frac)
    if args.json is not None:
        write_json(args.json, json_safe(to_json(steps, methods, summary)))
    if args.plot:
        from ..files.atomic import atomic_path

        fig = plot_uniformity(steps, methods, title=str(args.sweep), ranges=ranges)
        with atomic_path(args.plot) as tmp:
            fig.savefig(tmp, dpi=120, format="png")
    print(f"{'signal (DN)':<24} {'steps':>5}  "
          + "  ".join(f"{m:>18}" for m in ("raw", *methods)))
    for i, row in enumerate(summary):
        lo, hi = row["signal_range_dn"]
        label = f"{lo:.0f}-{hi:.0f}"
        if fractions is not None:
            label += f" ({100 * fractions[i][0]:g}-{100 * fractions[i][1]:g} %)"
        cells = [_cell(row["methods"].get(m)) for m in ("raw", *methods)]
        print(f"{label:<24} {row['n_steps']:>5}  " + "  ".join(cells))
    if fractions is not None:
        print(f"ranges in percent of saturation ({ranges[-1][1]:.0f} DN above dark: the "
              "brightest light step with at most 1 % of its pixels clipped, below the dose "
              "where the response grows at less than half its linear slope)")
    print("fixed-pattern non-uniformity (EMVA 1288, temporal noise removed), median per range; "
          + (f"{len(steps)} steps written to {args.json}" if args.json is not None else
             f"{len(steps)} steps (--json FILE writes each step's figures)"))
    if any(v["fpn_percent_median"] < v["fpn_se_percent_median"]
           for row in summary for v in row["methods"].values()):
        print("< x: the fixed pattern left is below what the frames can resolve (x is twice the "
              "standard error of the figure, from the pixel and frame counts)")
    if any(value["worst_step"] is None for row in summary for value in row["methods"].values()):
        print("n/a: no step of the range has a figure: every pixel flagged (e.g. dynamically "
              "saturated) or none left after the correction's flags")
    return 0


def _ranges(sweep, dark_for):
    """The summary's signal ranges (DN above dark) and their fractions of saturation: 2-12,
    12-40, 40-80 and 80-100 % of the sweep's saturation where it has darks to measure it and
    reaches it (:func:`hsiffc.reports.ffc_study.saturation_level`), else the same fractions of
    full scale at the sweep's bit depth (fractions None): a sweep that stops below saturation
    does not say where saturation is."""
    from ..reports.ffc_study import RANGES_FRACTION, saturation_level
    from ..reports.sweep_uniformity import signal_ranges_dn

    light = [int(s) for s in sweep.steps() if sweep.kind[sweep.step == s][0] == "light"
             and (sweep.step == s).sum() >= 2]
    if dark_for is None or not light:
        return signal_ranges_dn(sweep.bit_depth), None
    try:
        level = saturation_level(sweep, light, dark_for)
    except HsiffcError:  # every step clipped: full scale it is
        return signal_ranges_dn(sweep.bit_depth), None
    if not level["reached"]:
        return signal_ranges_dn(sweep.bit_depth), None
    sat = level["signal_dn"]
    return (tuple((lo * sat, hi * sat * (1 + 1e-9)) for lo, hi in RANGES_FRACTION),
            RANGES_FRACTION)


def _cell(figures) -> str:
    """A summary table cell: the median percent; '< x' where it is below its standard error
    (x twice that error: the frames cannot tell the pattern left from none, so "0.00 %" would
    claim too much); '-' for no step in the range; 'n/a' where no step of the range has a
    figure (e.g. every pixel flagged, as in dynamically saturated steps)."""
    if figures is None:
        return f"{'-':>18}"
    value, se = figures["fpn_percent_median"], figures.get("fpn_se_percent_median", 0.0)
    if value != value:
        return f"{'n/a':>18}"
    if value < se:  # below what the frames resolve: a bound, not "0.00 %"
        return f"{'< ' + format(2 * se, '.2f'):>17}%"
    return f"{value:>17.2f}%"


def _add_study(sub):
    p = sub.add_parser(
        "study-ffc", help="held-out flat-field correction study on an EMVA 1288 sweep",
        description="Calibrate on the even light steps and the darks of an EMVA 1288 sweep "
                    "(any bit depth; exposure or light sweep), correct the odd light steps "
                    "with two-point FFC (2-frame flat near half saturation, flat stack) and "
                    "model_ffc, and write ffc_study.md, ffc_study.json and ffc_study.png "
                    "(fixed-pattern non-uniformity against signal, per range of saturation) "
                    "into OUTDIR.")
    p.add_argument("outdir", type=Path, help="folder for the page (created if missing)")
    p.add_argument("--emva", type=Path, default=Path("../shared/data/emva1288-cmos8-roi"),
                   help="EMVA 1288 folder (default: ../shared/data/emva1288-cmos8-roi)")
    p.add_argument("--goal", type=float, default=None,
                   help="also check model_ffc at or below this percent from 12 %% of "
                        "saturation up")
    add_overwrite(p, "replace the files of an earlier study in OUTDIR")
    p.set_defaults(func=_cmd_study, input_args=("emva",), output_dirs=("outdir",))


def _cmd_study(args) -> int:
    from ..reports.ffc_study import write_ffc_study

    if not args.emva.exists():
        raise HsiffcError(f"--emva: {args.emva} not found; give the EMVA 1288 measurement folder")
    paths = write_ffc_study(args.emva, args.outdir, goal_percent=args.goal)
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0
