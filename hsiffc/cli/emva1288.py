"""``emva1288``: the EMVA 1288 Release 4.0 figures of a measurement, as the standard's reference
implementation computes them, and what the leakage model says about them."""

from __future__ import annotations

import gc
from pathlib import Path

from ..errors import HsiffcError
from .args import positive
from .common import add_input_options, add_overwrite, input_overrides, write_json


def register(sub) -> None:
    """Add the ``emva1288`` sub-command to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    p = sub.add_parser(
        "emva1288", help="EMVA 1288 figures (K, QE, noise, DSNU, PRNU, linearity, saturation, "
                         "SNR, DR, dark current) and what leakage does to them",
        description="Characterise an EMVA 1288 measurement (descriptor + images) as the "
                    "standard's reference implementation (emva1288, Release 4.0) does: every "
                    "figure under its name with unit, fit range and standard error; per band "
                    "with --mosaic. Beyond the standard, a per-pixel leakage calibration says "
                    "how much of the linearity error and of the saturation capacity is leakage.")
    p.add_argument("descriptor", type=Path,
                   help="EMVA 1288 descriptor (.txt) or the folder holding it")
    p.add_argument("--json", type=Path, required=True, help="output JSON")
    p.add_argument("--report", type=Path, default=None, metavar="DIR",
                   help="also write emva1288.md, emva1288.json and the standard's plots (PNG) "
                        "into DIR")
    p.add_argument("--pixel-area-um2", type=positive, default=None, metavar="A",
                   help="pixel area in um^2: adds saturation and threshold per area")
    p.add_argument("--wavelength-nm", type=positive, default=None, metavar="L",
                   help="wavelength of the light in nm: adds the photon energy and, with the "
                        "pixel area, the irradiation at saturation and threshold (uJ/m^2); QE "
                        "needs neither, the descriptor gives photons per pixel")
    p.add_argument("--calibration", type=Path, default=None,
                   help="leakage calibration (.npz) of this measurement (default: calibrate it)")
    p.add_argument("--no-leakage", action="store_true",
                   help="only the standard's figures (no leakage calibration)")
    add_input_options(p)
    add_overwrite(p, "replace an existing --json file or the files of an earlier --report")
    # streamed statistics: no frame-sized arrays to keep for reuse (hsiffc.batch.memory)
    p.set_defaults(func=_cmd_emva1288, input_args=("descriptor", "calibration"),
                   output_args=("json",), output_dirs=("report",), reuse_memory=False)


def _cmd_emva1288(args) -> int:
    from ..emva1288 import run_characterisation
    from ..emva1288.render import fmt, to_json, write_report
    from ..io import open_source

    if args.no_leakage and args.calibration is not None:
        raise HsiffcError("--calibration is for the leakage part; drop --no-leakage or it")
    # streamed: each step is reduced to its statistics as its frames are read
    with open_source(args.descriptor, overrides=input_overrides(args)) as sweep:
        if sweep.meta.get("format") != "emva1288":
            raise HsiffcError(f"{args.descriptor}: not an EMVA 1288 measurement; give its "
                              "descriptor (.txt with 'b EXPOSURE PHOTONS' lines) or its folder")
        h, w = sweep.frame_shape
        print(f"{sweep.n_frames} frames of {h} x {w} px, {sweep.bit_depth}-bit, "
              f"{len(set(sweep.step.tolist()))} steps, from {sweep.label}")
        cal = None
        if args.calibration:
            from ..calibrate import Calibration

            cal = Calibration.load(args.calibration)
        res, leak, note = run_characterisation(
            sweep, pixel_area_um2=args.pixel_area_um2, wavelength_nm=args.wavelength_nm,
            leakage=not args.no_leakage, calibration=cal)
    # the process ends after the outputs: the collections of the interpreter's shutdown need not
    # walk the objects of the modules loaded (numba's and the calibration's: about 0.8 s of CPU)
    gc.freeze()
    write_json(args.json, to_json(res, leak, note))
    for name, f in res["figures"].items():
        se = f" +- {fmt(f['se'], 2)}" if f.get("se") is not None else ""
        print(f"  {name:<13} {fmt(f['value']):>12} {f['unit']:<7}{se}")
    fr = res["fit_ranges"]
    print(f"saturation: light step {fr['index_u_ysat']}; K/R fit indices "
          f"{fr['sensitivity']['index']}; linearity indices {fr['linearity']['index']}")
    for n in res["notes"]:
        print(f"note: {n}")
    if leak is not None:
        bud = leak["saturation_budget"]
        al = leak["alpha"]["saturation"]
        print(f"leakage: {leak['evidence']['text']}")
        print(f"leakage: alpha at the saturation point median "
              f"{al['p50']:.3g} % (max {al['max_percent']:.3g} %); at saturation "
              f"{100 * bud['leaked_share']:.2f} % of the generated signal leaked, "
              f"{100 * bud['share_pixels_leakage_limited']:.1f} % of pixels leakage-limited")
        tv = leak["temporal_variance"]
        print(f"leakage: saturation point predicted at light step "
              f"{tv['saturation_index_predicted']} (measured {tv['saturation_index_measured']}; "
              f"{tv['saturation_index_without_leakage']} without leakage)")
    elif note:
        print(f"leakage: {note}")
    print(f"wrote {args.json}")
    if args.report:
        files = write_report(sweep, res, args.report, leak, note)
        print(f"wrote {len(files)} files to {args.report}")
    return 0
