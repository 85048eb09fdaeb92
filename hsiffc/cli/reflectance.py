"""``hsiffc reflectance fit`` and ``hsiffc reflectance check``: reflectance from a white panel.

``fit`` builds and fits the pipeline a field user needs (``dark``, then ``reflectance``; with
``--cube``, reconstruction in between) from the dark frames, the white-panel frames and the
panel's value, prints the reference's checks and saves it; ``hsiffc correct --pipeline`` then
applies it to the scenes. ``check`` runs a fitted reflectance pipeline on frames of a uniform
target (the panel itself or a grey card) and reports its mean reflectance against the target's
value and the uniformity of the reflectance, per band.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.mosaic import band_labels
from ..data.params import LiveChoices
from ..errors import HsiffcError
from ..reconstruct import DEMOSAIC_METHODS
from ..reflectance import REFLECTANCE_METHODS, resolve_method
from .args import index, percent, positive
from .common import add_input_options, add_overwrite, input_overrides, write_json
from .pipeline import read_training

CUBE_METHODS = tuple(DEMOSAIC_METHODS)


def register(sub) -> None:
    """Add ``reflectance`` (with its actions ``fit`` and ``check``) to the sub-parsers."""
    p = sub.add_parser(
        "reflectance", help="reflectance factor from a white panel: fit the reference, check "
                            "a target",
        description="Reflectance factor per band: scenes divided by a white panel of known "
                    "reflectance, both less the dark (with a calibration: light rates "
                    "recovered through the leakage model). 'fit' makes the pipeline, 'hsiffc "
                    "correct --pipeline' applies it to scenes, 'check' measures a uniform "
                    "target with it.")
    acts = p.add_subparsers(dest="action", metavar="ACTION")
    _add_fit(acts)
    _add_check(acts)
    p.set_defaults(func=lambda args: _usage(p))


def _usage(parser) -> int:
    parser.print_help()
    return 2


def _add_fit(acts):
    p = acts.add_parser(
        "fit", help="fit a reflectance pipeline on dark and white-panel frames",
        description="Build the pipeline dark -> [reconstruct] -> reflectance, fit it on the "
                    "dark frames and the white panel's frames (any format hsiffc reads; "
                    "metadata from the files, a sidecar or the input options), print the "
                    "reference's checks (level, signal-to-noise ratio, saturation, leakage, "
                    "frames) and save it (.npz) for 'hsiffc correct --pipeline'.")
    p.add_argument("--dark", type=Path, nargs="+", required=True, metavar="PATH",
                   help="dark frames (read as kind dark), at the panel's and the scenes' "
                        "exposures")
    p.add_argument("--white", type=Path, nargs="+", required=True, metavar="PATH",
                   help="white-panel frames (read as kind light), 10 or more per exposure")
    panel = p.add_mutually_exclusive_group(required=True)
    panel.add_argument("--panel", type=positive, nargs="+", metavar="R",
                       help="the panel's reflectance factor (e.g. 0.99), one value or one per "
                            "band")
    panel.add_argument("--panel-file", type=Path, metavar="CSV",
                       help="the panel's spectrum: two columns, wavelength (nm) and reflectance "
                            "(factor or percent), interpolated at the band centres")
    p.add_argument("--calibration", type=Path, default=None,
                   help="leakage calibration (.npz from 'hsiffc calibrate'): reflectance from "
                        "the light rates the model recovers (leakage-aware)")
    default = "auto"
    p.add_argument("--method", choices=LiveChoices(REFLECTANCE_METHODS), default=default,
                   help="; ".join(f"{name}: {how.summary}"
                                  + (" (needs --calibration)" if how.leakage_aware else "")
                                  + (" (default)" if name == default else "")
                                  for name, how in REFLECTANCE_METHODS.items()))
    p.add_argument("--cube", choices=CUBE_METHODS, default=None,
                   help="reconstruct cubes before the reflectance (with the model: the "
                        "leakage is inverted per pixel first, by a linearise step)")
    p.add_argument("--precision", type=percent, default=1.0, metavar="PERCENT",
                   help="error of the averaged reference (per pixel) to reach; fewer frames "
                        "give a warning with the number needed (default 1)")
    p.add_argument("--max-reflectance", type=positive, default=1.2, metavar="R",
                   help="a scene with most good values above R is called brighter than the "
                        "reference (default 1.2)")
    p.add_argument("-o", "--output", type=Path, required=True, help="fitted pipeline (.npz)")
    add_input_options(p)
    add_overwrite(p)
    p.set_defaults(func=_cmd_fit, input_args=("dark", "white", "panel_file", "calibration"),
                   output_args=("output",))


def build_pipeline(args):
    """The unfitted pipeline ``fit`` fits, from its options."""
    from ..stages import Pipeline, create

    panel = None if args.panel is None else (args.panel[0] if len(args.panel) == 1
                                             else list(args.panel))
    cal = None if args.calibration is None else str(args.calibration)
    method = args.method
    if REFLECTANCE_METHODS[method].leakage_aware and cal is None:
        raise HsiffcError(f"--method {method} needs --calibration (the leakage calibration "
                          "from 'hsiffc calibrate')")
    steps = [("dark", create("dark"))]
    if args.cube is not None:
        if cal is not None and REFLECTANCE_METHODS[resolve_method(method, True)].leakage_aware:
            # the model inverts mosaic pixels: a linearise step, then a plain ratio of cubes
            steps.append(("linearise", create("linearise", calibration=cal)))
        steps.append(("cube", create("reconstruct", method=args.cube)))
        method, cal = "ratio", None
    steps.append(("reflectance", create(
        "reflectance", panel=panel,
        panel_file=None if args.panel_file is None else str(args.panel_file),
        calibration=cal, method=method, precision_percent=args.precision,
        max_reflectance=args.max_reflectance)))
    return Pipeline(steps)


def _cmd_fit(args) -> int:
    if args.output.suffix != ".npz":
        raise HsiffcError(f"-o {args.output}: a fitted pipeline file ends in .npz; rename it "
                          f"(e.g. {args.output.with_suffix('.npz').name})")
    pipe = build_pipeline(args)
    frames = read_training(args, [(p, {"kind": "dark"}) for p in args.dark]
                           + [(p, {"kind": "light"}) for p in args.white])
    pipe.fit(frames)
    pipe.save(args.output, overwrite=args.overwrite)
    stage = pipe.named_steps["reflectance"]
    how = REFLECTANCE_METHODS[stage.method_].summary
    if "linearise" in pipe.named_steps:
        how = "light rates through the leakage model (linearise step), then cubes"
    print(f"reflectance from {how}; panel {_values(stage.panel_)} ({stage.panel_source_})")
    for check in stage.checks_:
        print(reference_table(check))
    cal = "" if args.calibration is None else f" --calibration {args.calibration}"
    print(f"wrote {args.output}: apply it with hsiffc correct --pipeline {args.output}{cal} "
          "SCENES -o OUTDIR")
    return 0


def _values(values) -> str:
    uniq = sorted(set(round(v, 6) for v in values))
    return f"{uniq[0]:g}" if len(uniq) == 1 else ", ".join(f"{v:.4g}" for v in values)


def reference_table(check: dict) -> str:
    """The reference's figures per band, as text (one line per band)."""
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    n_bands = len(check["level_dn"])
    labels = check.get("band_labels") or band_labels(n_bands)
    width = max(len(s) for s in labels)
    lines = [f"white reference at {check['exposure_ms']:g} ms, {check['n_frames']} frame(s):",
             f"{'band':<{width}} {'level DN':>9} {'% range':>8} {'SNR/frame':>10} {'error %':>8} "
             f"{'saturated %':>12} {'alpha %':>8}"]
    n = check["n_frames"]
    alpha = check.get("alpha_percent") or [None] * n_bands
    for i in check.get("band_order") or range(n_bands):  # by wavelength
        level = check["level_dn"][i]
        rng = check["range_dn"][i]
        snr = check["snr_frame"][i]
        err = None if snr in (None, 0) else 100 / (snr * n ** 0.5)
        lines.append(f"{labels[i]:<{width}} {fmt(level, '9.1f')} "
                     f"{fmt(None if rng is None or level is None else 100 * level / rng, '8.1f')} "
                     f"{fmt(snr, '10.1f')} {fmt(err, '8.2f')} "
                     f"{fmt(check['saturated_percent'][i], '12.2f')} {fmt(alpha[i], '8.1f')}")
    lines.append("checks: " + ("passed" if not check.get("warnings")
                               else f"{len(check['warnings'])} warning(s), above"))
    return "\n".join(lines)


def _add_check(acts):
    p = acts.add_parser(
        "check", help="measure a uniform target (white or grey) with a reflectance pipeline",
        description="Run a fitted reflectance pipeline on frames of a uniform target (the "
                    "panel, a grey card) and print per band its mean reflectance against the "
                    "target's value and the non-uniformity of the reflectance with the "
                    "temporal noise removed: the figure that says whether the reflectance is "
                    "right (not the eq. (6) of a scene).")
    p.add_argument("target", type=Path, nargs="+", help="frames of the target (files, folders, "
                                                        "globs)")
    p.add_argument("--pipeline", type=Path, required=True,
                   help="fitted pipeline (.npz) ending in a reflectance step")
    p.add_argument("--expected", type=positive, default=None, metavar="R",
                   help="the target's reflectance factor (default: the panel's)")
    p.add_argument("--roi", type=index, nargs=4, default=None,
                   metavar=("ROW0", "ROW1", "COL0", "COL1"),
                   help="the target's rows ROW0..ROW1-1 and columns COL0..COL1-1, counted from 0 "
                        "(default: the whole frame)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    add_input_options(p)
    add_overwrite(p)
    p.set_defaults(func=_cmd_check, input_args=("target", "pipeline"), output_args=("json",))


def _cmd_check(args) -> int:
    from ..data.frame import Frame
    from ..io import read_sweep
    from ..reflectance import target_report
    from ..stages import Pipeline
    from ..stages.reflectance import frame_bands

    pipe = Pipeline.load(args.pipeline)
    stage = pipe.steps[-1][1]
    if stage.name != "reflectance":
        raise HsiffcError(f"{args.pipeline}: its last step is {stage.name!r}, not a reflectance "
                          "step; make one with 'hsiffc reflectance fit'")
    sweep = read_sweep(args.target, overrides=input_overrides(args))
    outs = [pipe.transform(f) for f in Frame.list_from_sweep(sweep) if f.kind == "light"]
    if not outs:
        raise HsiffcError(f"{args.target[0]}: no light frames of the target")
    data = np.stack([o.data for o in outs])
    dq = np.stack([o.dq for o in outs])
    bands, n_bands, wl = frame_bands(outs[0])
    if args.roi is not None:
        r0, r1, c0, c1 = args.roi
        if not (r0 < r1 <= data.shape[1] and c0 < c1 <= data.shape[2]):
            raise HsiffcError(f"--roi {r0} {r1} {c0} {c1}: outside the {data.shape[1]} x "
                              f"{data.shape[2]} frames or empty; give ROW0 < ROW1 and COL0 < COL1 "
                              "inside them (rows and columns count from 0)")
        data, dq = data[:, r0:r1, c0:c1], dq[:, r0:r1, c0:c1]
        bands = bands[r0:r1, c0:c1]
    expected = (np.asarray(stage.panel_) if args.expected is None
                else np.full(n_bands, args.expected))
    rep = target_report(data, dq, bands, n_bands, expected)
    labels = outs[0].band_labels()
    print(rep.to_text(wl, labels))
    worst = int(np.nanargmax(np.abs(rep.bias_percent)))
    print(f"worst: {labels[worst]}, mean {rep.mean[worst]:.4f} against {expected[worst]:.4f} "
          f"({rep.bias_percent[worst]:+.2f} %)")
    if args.json:
        write_json(args.json, {"target": [str(t) for t in args.target],
                               "pipeline": str(args.pipeline), "roi": args.roi,
                               "wavelengths_nm": wl, **rep.to_dict()})
    return 0


__all__ = ["register", "build_pipeline", "reference_table"]
