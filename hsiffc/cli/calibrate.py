"""The ``calibrate`` command: the leakage model of every pixel from a sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import HsiffcError
from .args import positive
from .common import add_input_options, add_overwrite, input_overrides, write_json


def register(sub) -> None:
    """Add ``calibrate`` to the parser's sub-parsers (:func:`hsiffc.cli.build_parser`)."""
    _add_calibrate(sub)


def _rows_done(done: int, total: int) -> None:
    """The joint calibration's progress, as an INFO record (the status line shows it)."""
    import logging

    logging.getLogger("hsiffc.calibrate").info("calibrating: %d of %d rows fitted (%.0f %%)",
                                               done, total, 100.0 * done / max(total, 1))


def _add_calibrate(sub):
    from ..calibrate import CALIBRATION_METHODS
    from ..data.params import LiveChoices

    p = sub.add_parser(
        "calibrate", help="calibrate the leakage model of every pixel from a sweep",
        description="Fit k (responsivity), a, b and the dark level of every pixel from an "
                    "exposure sweep (hsiffc TIFF or EMVA 1288) and write a calibration file (.npz).")
    p.add_argument("sweep", type=Path, nargs="+",
                   help="sweep: files of any supported format, folders or globs")
    add_input_options(p)
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration file (.npz)")
    p.add_argument("--method", choices=LiveChoices(CALIBRATION_METHODS), default="joint",
                   help="joint per-pixel fit (default) or the paper's procedure (several "
                        "illuminations)")
    p.add_argument("--full-well-dn", type=positive, default=None,
                   help="leave out samples at or above this level (full-well saturation)")
    p.add_argument("--steps", choices=("all", "sweep"), default="sweep",
                   help="EMVA 1288: fit the sweep steps and fold the spatial flat stack into "
                        "the responsivity map (default), or fit every step")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    add_overwrite(p)
    p.set_defaults(func=_cmd_calibrate, input_args=("sweep",), output_args=("output", "json"))


def _cmd_calibrate(args) -> int:
    from ..calibrate import CALIBRATION_METHODS, calibrate
    from ..io import read_sweep

    sweep = full = read_sweep(args.sweep, overrides=input_overrides(args))
    if args.steps == "sweep" and "sweep_steps" in sweep.meta:
        sweep = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    print(sweep.summary())
    if args.output.suffix != ".npz":
        raise HsiffcError(f"{args.output}: the calibration file must end in .npz; rename it")
    extra = ({"progress": _rows_done}  # on the status line
             if CALIBRATION_METHODS[args.method].reports_progress else {})
    stacks = (full.select(np.isin(full.step, full.meta["spatial_steps"]))
              if args.steps == "sweep" and full.meta.get("spatial_steps") else None)
    if args.method == "joint":  # the stack two-point is one of the models compared
        extra["flats"] = stacks
    cal = calibrate(sweep, method=args.method, full_well_dn=args.full_well_dn, **extra)
    if stacks is not None:
        # the EMVA 1288 flat stack: folded into the responsivity map, not a sample of the fit
        from ..calibrate.flats import add_flat_stacks

        cal = add_flat_stacks(cal, stacks)
        for s in cal.fitted_on.get("flat_stacks", []):
            print(f"  flat stack: step {s['step']}, {s['n_frames']} frames at "
                  f"{s['exposure_ms']:g} ms, {s['level_dn']:.0f} DN above dark ({s['dark']} "
                  "dark): folded into the responsivity map")
    cal.save(args.output, overwrite=args.overwrite)
    print(cal.summary())
    counts = {k: int(cal[k].sum()) for k in ("n_valid", "n_clipped", "n_full_well")
              if k in cal.arrays}
    if counts:
        print("  samples: " + ", ".join(f"{v} {k[2:].replace('_', ' ')}" for k, v in counts.items()))
    print(f"wrote {args.output} (calibration {cal.identity})")
    if args.json:
        doc = {"calibration": str(args.output), "identity": cal.identity,
               "manifest": cal.manifest(), "sample_counts": counts,
               "parameters": {name: _percentiles(cal[name]) for name in cal.arrays
                              if name not in ("flags",) and cal[name].dtype.kind == "f"}}
        write_json(args.json, doc)
    return 0


def _percentiles(arr) -> dict:
    v = np.asarray(arr, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {}
    q = np.percentile(v, [5, 50, 95])
    return {"p5": float(q[0]), "median": float(q[1]), "p95": float(q[2])}
