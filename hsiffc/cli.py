"""The ``hsiffc`` command line.

Sub-commands are small functions that parse, call the library and print a readable summary;
errors that concern the user's input end with a one-line message and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from . import __version__
from .errors import HsiffcError

log = logging.getLogger("hsiffc")

DEFAULT_SAMPLES = Path("sample_cubes")


def _add_demo(sub):
    p = sub.add_parser(
        "demo", help="show hsiffc's main job on the bundled sample cubes",
        description="Read the sample cubes (a 2900 K exposure sweep into dynamic saturation, "
                    "darks and 2200 K test frames), show per band how the response levels off "
                    "below full scale with the leakage percentage alpha of each exposure, and "
                    "write a plot.")
    p.add_argument("samples", nargs="?", type=Path, default=DEFAULT_SAMPLES,
                   help="folder with the sample cubes (default: ./sample_cubes)")
    p.add_argument("-o", "--outdir", type=Path, default=Path("hsiffc-demo"),
                   help="where to write the plot and the JSON summary (default: ./hsiffc-demo)")
    p.set_defaults(func=_cmd_demo)


def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="simulate an exposure sweep of a mosaic sensor and write it as TIFF",
        description="Simulate raw frames of the default (paper) sensor or a square IMEC-like "
                    "mosaic under a named lamp and write an hsiffc TIFF sweep.")
    p.add_argument("output", type=Path, help="TIFF file to write (not overwritten without --overwrite)")
    p.add_argument("--exposures-ms", type=float, nargs="+", required=True,
                   help="exposure times in ms")
    p.add_argument("--lamp", default="lamp A",
                   help="'lamp A' (2900 K), 'lamp B' (2200 K), '<T>K', or a CIE illuminant name")
    p.add_argument("--irradiance-w-m2", type=float, default=None,
                   help="irradiance over 400-1000 nm in W/m^2 (default: the paper's training level)")
    p.add_argument("--frames", type=int, default=2, help="frames per exposure (default 2)")
    p.add_argument("--no-darks", action="store_true", help="do not add dark frames")
    p.add_argument("--shape", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    p.add_argument("--mosaic", default="paper8", help="paper8, 4x4 or 5x5")
    p.add_argument("--vignetting", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=_cmd_simulate)


def _add_info(sub):
    p = sub.add_parser("info", help="describe a sweep (hsiffc TIFF or EMVA 1288)")
    p.add_argument("sweep", type=Path)
    p.add_argument("--json", type=Path, default=None, help="also write the description as JSON")
    p.set_defaults(func=_cmd_info)


def _add_calibrate(sub):
    p = sub.add_parser(
        "calibrate", help="calibrate the leakage model of every pixel from a sweep",
        description="Fit k (responsivity), a, b and the dark level of every pixel from an "
                    "exposure sweep (hsiffc TIFF or EMVA 1288) and write a calibration file (.npz).")
    p.add_argument("sweep", type=Path, help="sweep: hsiffc TIFF, EMVA 1288 descriptor or folder")
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration file (.npz)")
    p.add_argument("--method", choices=("joint", "paper"), default="joint",
                   help="joint per-pixel fit (default) or the paper's procedure (several "
                        "illuminations)")
    p.add_argument("--full-well-dn", type=float, default=None,
                   help="leave out samples at or above this level (full-well saturation)")
    p.add_argument("--steps", choices=("all", "sweep"), default="sweep",
                   help="EMVA 1288: use only the sweep steps (default) or also the spatial set")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=_cmd_calibrate)


def _add_select(sub):
    p = sub.add_parser(
        "select", help="select the training exposure per band by the leakage percentage",
        description="For each band, the longest candidate exposure whose leakage percentage "
                    "alpha stays under the threshold (the paper's section IV.2), with a table of "
                    "alpha per band and exposure like the paper's Table I.")
    p.add_argument("sweep", type=Path, help="candidate training frames (one step per exposure)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file (.npz)")
    p.add_argument("--threshold", type=float, required=True, help="alpha threshold in percent")
    p.add_argument("--alpha", choices=("paper", "model"), default="paper",
                   help="alpha as the paper computes it (k ~ signal/exposure) or with k from the "
                        "model (default: paper)")
    p.add_argument("--statistic", choices=("median", "mean", "p95"), default="median",
                   help="how a band's pixels are summarised (default: median)")
    p.add_argument("--json", type=Path, default=None, help="also write the table as JSON")
    p.set_defaults(func=_cmd_select)


def _add_stages(sub):
    p = sub.add_parser("stages", help="list the installed pipeline stages and where they come from")
    p.add_argument("--json", type=Path, default=None, help="also write the list as JSON")
    p.set_defaults(func=_cmd_stages)


def _add_fit(sub):
    p = sub.add_parser(
        "fit", help="fit a pipeline described in TOML on training frames and save it",
        description="Build the pipeline described by a TOML file ([[step]] tables with name, "
                    "stage and parameters), fit it on training frames (darks and flats, hsiffc "
                    "TIFF or EMVA 1288) and save the fitted pipeline (.npz, no pickle).")
    p.add_argument("description", type=Path, help="pipeline TOML file")
    p.add_argument("training", type=Path, nargs="+", help="training sweeps (darks, flats)")
    p.add_argument("-o", "--output", type=Path, required=True, help="fitted pipeline (.npz)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=_cmd_fit)


def _add_correct(sub):
    p = sub.add_parser(
        "correct", help="correct a batch of TIFF frames or cubes with a calibration",
        description="Correct every input (hsiffc TIFF files, folders searched recursively, or "
                    "globs) frame by frame and write one <name>.corrected.tif per input under "
                    "OUTDIR (pages per frame: data float32, dq uint32, alpha float32; "
                    "provenance JSON). Outputs appear atomically; a rerun skips the outputs that "
                    "are complete and up to date. Exit status 0: every file done or skipped; "
                    "1: some file failed (listed with its reason); 2: usage error.")
    p.add_argument("inputs", nargs="+", help="TIFF files, folders or globs (quote globs)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file (.npz)")
    p.add_argument("-o", "--outdir", type=Path, required=True, help="output folder")
    p.add_argument("--pipeline", type=Path, default=None,
                   help="fitted pipeline (.npz from 'hsiffc fit'); default: dark from the "
                        "calibration + alpha mask (+ --linearise)")
    p.add_argument("--threshold", type=float, default=12.0,
                   help="alpha threshold in percent for the default pipeline (default 12)")
    p.add_argument("--linearise", action="store_true",
                   help="add leakage linearisation to the default pipeline")
    p.add_argument("--workers", type=int, default=1,
                   help="parallel worker processes on this machine (Dask local cluster; "
                        "default 1: in this process)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on a Dask distributed cluster (e.g. tcp://host:8786); its workers "
                        "must see the inputs, calibration and OUTDIR at the same paths")
    p.add_argument("--overwrite", action="store_true",
                   help="redo outputs that are already complete and up to date")
    p.add_argument("--nan", choices=("flag", "fail"), default="flag",
                   help="NaN/inf pixels in float inputs: flag them NONFINITE and warn "
                        "(default) or fail the file")
    p.add_argument("--no-hash", action="store_true",
                   help="do not record the inputs' sha256 in the provenance (saves one read)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    p.set_defaults(func=_cmd_correct)


def _add_paper(sub):
    p = sub.add_parser(
        "paper", help="reproduce the paper's experiments (section V) as a report",
        description="Run the paper's section V on the simulated 8-band sensor (Fig. 4 "
                    "calibration, Fig. 5 and Fig. 2 responses, Tables I and II, Fig. 6 spectra) "
                    "and the trade-off of its future work (SNR, spectral correctness and "
                    "response uniformity against the alpha threshold), plus the flat-level "
                    "question on the real EMVA 1288 sweep when it is found. Writes report.md, "
                    "PNG figures, one CSV per table or figure and summary.json into OUTDIR.")
    p.add_argument("outdir", type=Path, help="folder for the report (created if missing)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated sensor (default 0)")
    p.add_argument("--weights", default="snr=1,sc=1,ru=1",
                   help="weights of the trade-off criteria: snr (SNR of the training flats), "
                        "sc (spectral correctness), ru (response uniformity); default "
                        "snr=1,sc=1,ru=1 (criteria not named get 1)")
    p.add_argument("--emva", type=Path, default=None, metavar="DIR",
                   help="EMVA 1288 sweep folder (default: ../shared/data/emva1288-cmos8-roi "
                        "if found, else that part is skipped with a note)")
    p.add_argument("--no-emva", action="store_true", help="skip the real-data part")
    p.add_argument("--threshold", type=float, default=12.0,
                   help="alpha threshold in percent for Tables I/II and Fig. 6 (default 12)")
    p.add_argument("--shape", type=int, nargs=2, default=(128, 128), metavar=("H", "W"),
                   help="simulated sensor size (multiple of the 2 x 4 tile; default 128 128)")
    p.set_defaults(func=_cmd_paper)


def _add_diagnose(sub):
    p = sub.add_parser(
        "diagnose", help="find where the model misses a sweep, trace it to an effect, report",
        description="Fit the base model (leakage model, constant dark level) per pixel on one "
                    "frame of every step, measure the error on the other frame, fit each "
                    "candidate effect, select those that beat the base model by more than the "
                    "noise allows, and report what remains unexplained.")
    p.add_argument("sweep", type=Path, nargs="?",
                   help="sweep: hsiffc TIFF, EMVA 1288 descriptor or folder")
    p.add_argument("--json", type=Path, default=None, help="write the result as JSON")
    p.add_argument("--report", type=Path, default=None,
                   help="folder for report.md, residuals.png and diagnosis.json")
    p.add_argument("--pixels", type=int, default=2048,
                   help="pixels analysed (random subset; default 2048)")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel subset")
    p.add_argument("--effects", default=None,
                   help="comma-separated candidate effects (default: the whole library)")
    p.add_argument("--list-effects", action="store_true", help="list the effect library and exit")
    p.set_defaults(func=_cmd_diagnose)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hsiffc",
        description="Leakage-aware calibration and flat-field correction for low-light CMOS "
                    "hyperspectral snapshot-mosaic sensors.")
    parser.add_argument("--version", action="version", version=f"hsiffc {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_demo, _add_simulate, _add_info, _add_calibrate, _add_select, _add_stages,
                _add_fit, _add_correct, _add_paper, _add_diagnose):
        add(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (HsiffcError, FileNotFoundError, FileExistsError) as exc:
        print(f"hsiffc {args.command}: error: {exc}", file=sys.stderr)
        return 2


# -- commands ----------------------------------------------------------------------------------

def _cmd_info(args) -> int:
    from .io import read_sweep

    sweep = read_sweep(args.sweep)
    print(sweep.summary())
    steps = sweep.step_means()
    print(f"{'step':>5} {'kind':>5} {'exposure_ms':>12} {'photons':>10} {'frames':>6} "
          f"{'mean_dn':>9} {'max_dn':>7}")
    for i in range(len(steps["step"])):
        print(f"{steps['step'][i]:>5} {steps['kind'][i]:>5} {steps['exposure_ms'][i]:>12.6g} "
              f"{steps['photons'][i]:>10.4g} {steps['n_frames'][i]:>6} "
              f"{steps['data'][i].mean():>9.2f} {steps['data'][i].max():>7.0f}")
    if args.json:
        doc = {"source": str(args.sweep), "summary": sweep.summary(),
               "n_frames": sweep.n_frames, "frame_shape": list(sweep.frame_shape),
               "bit_depth": sweep.bit_depth,
               "steps": [{"step": int(steps["step"][i]), "kind": str(steps["kind"][i]),
                          "exposure_ms": float(steps["exposure_ms"][i]),
                          "photons": None if np.isnan(steps["photons"][i])
                          else float(steps["photons"][i]),
                          "n_frames": int(steps["n_frames"][i]),
                          "mean_dn": float(steps["data"][i].mean())}
                         for i in range(len(steps["step"]))]}
        _write_json(args.json, doc)
    return 0


def _cmd_simulate(args) -> int:
    from .io import write_sweep
    from .mosaic import Mosaic
    from .simulate import PAPER_LIGHT_W_M2, MosaicSensor
    from .spectral import imec_4x4_visible, imec_5x5_nir

    irr = args.irradiance_w_m2 if args.irradiance_w_m2 is not None else PAPER_LIGHT_W_M2["training"]
    if args.mosaic == "paper8":
        sensor = MosaicSensor(tuple(args.shape), seed=args.seed)
    elif args.mosaic in ("4x4", "5x5"):
        bands = imec_4x4_visible() if args.mosaic == "4x4" else imec_5x5_nir()
        n = 4 if args.mosaic == "4x4" else 5
        sensor = MosaicSensor(tuple(args.shape), seed=args.seed, bands=bands,
                              mosaic=Mosaic.square(n, wavelengths_nm=bands.centres_nm))
    else:
        raise HsiffcError(f"--mosaic must be paper8, 4x4 or 5x5, got {args.mosaic!r}")
    sweep = sensor.sweep(args.exposures_ms, args.lamp, irradiance_w_m2=irr, n_frames=args.frames,
                         darks=not args.no_darks, vignetting=args.vignetting)
    meta = {k: v for k, v in sweep.meta.items() if k != "truth"}
    meta["irradiance_w_m2"] = irr
    from dataclasses import replace
    write_sweep(args.output, replace(sweep, meta=meta), overwrite=args.overwrite)
    print(f"wrote {args.output}: {sweep.summary()}")
    return 0


def _cmd_calibrate(args) -> int:
    from .calibrate import calibrate
    from .io import read_sweep

    sweep = read_sweep(args.sweep)
    if args.steps == "sweep" and "sweep_steps" in sweep.meta:
        sweep = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    print(sweep.summary())
    if args.output.suffix != ".npz":
        raise HsiffcError(f"the calibration file must end in .npz, got {args.output.name!r}")
    cal = calibrate(sweep, method=args.method, full_well_dn=args.full_well_dn)
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
        _write_json(args.json, doc)
    return 0


def _percentiles(arr) -> dict:
    v = np.asarray(arr, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {}
    q = np.percentile(v, [5, 50, 95])
    return {"p5": float(q[0]), "median": float(q[1]), "p95": float(q[2])}


def _cmd_select(args) -> int:
    from .calibrate import Calibration
    from .io import read_sweep
    from .validity import alpha_table

    sweep = read_sweep(args.sweep)
    cal = Calibration.load(args.calibration)
    table = alpha_table(sweep, cal, method=args.alpha, statistic=args.statistic)
    table = table.select(args.threshold)
    print(table.to_text())
    for i, e in enumerate(table.selected_ms):
        label = "none" if np.isnan(e) else f"{e:g} ms"
        print(f"band {i + 1}: train at {label}")
    if args.json:
        _write_json(args.json, {"sweep": str(args.sweep), "calibration": str(args.calibration),
                                "calibration_identity": cal.identity, **table.to_dict()})
    return 0


def _cmd_stages(args) -> int:
    from .stages import describe

    rows = describe()
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        status = "" if r["status"] == "ok" else f"  [{r['status']}]"
        print(f"{r['name']:<{width}}  {r['source']:<24} {r['target']}{status}")
        if r["summary"]:
            print(f"{'':<{width}}  {r['summary']}")
    if args.json:
        _write_json(args.json, rows)
    return 0


def _cmd_fit(args) -> int:
    from .frame import Frame
    from .io import read_sweep
    from .stages import Pipeline

    pipe = Pipeline.from_toml(args.description)
    frames = []
    for path in args.training:
        sweep = read_sweep(path)
        print(sweep.summary())
        frames += Frame.list_from_sweep(sweep)
    pipe.fit(frames)
    pipe.save(args.output, overwrite=args.overwrite)
    for name, stage in pipe.steps:
        extra = ""
        if hasattr(stage, "selected_ms_"):
            extra = f"  training exposure per band (ms): {stage.selected_ms_}"
        print(f"  fitted {name} ({stage.name}){extra}")
    print(f"wrote {args.output}")
    return 0


def _cmd_correct(args) -> int:
    from .batch import correct_batch

    try:
        summary = correct_batch(args.inputs, args.outdir, args.calibration,
                                pipeline=args.pipeline, threshold_percent=args.threshold,
                                linearise=args.linearise, workers=args.workers,
                                scheduler=args.scheduler, overwrite=args.overwrite, nan=args.nan,
                                hash_inputs=not args.no_hash,
                                progress=not args.quiet and sys.stderr.isatty())
    except KeyboardInterrupt:
        print("hsiffc correct: interrupted; finished outputs are kept (no partial file is left "
              "under a final name): run the same command again to resume", file=sys.stderr)
        return 130
    print(summary.to_text())
    if args.json:
        _write_json(args.json, summary.to_dict())
    return summary.exit_status


def _cmd_paper(args) -> int:
    from .reports.paper import parse_weights, run_paper_report

    try:
        weights = parse_weights(args.weights)
    except ValueError as exc:
        raise HsiffcError(f"--weights: {exc}") from None
    if args.emva is not None and not args.emva.exists():
        raise HsiffcError(f"--emva: folder {args.emva} does not exist")
    if args.shape[0] % 2 or args.shape[1] % 4 or min(args.shape) < 8:
        raise HsiffcError(f"--shape must be a multiple of the 2 x 4 mosaic tile and >= 8, "
                          f"got {args.shape[0]} {args.shape[1]}")
    res = run_paper_report(args.outdir, seed=args.seed, shape=tuple(args.shape),
                           emva_dir=False if args.no_emva else args.emva, weights=weights,
                           threshold=args.threshold)
    sim = res["simulated"]
    print(f"simulated 8-band sensor {sim['shape'][0]} x {sim['shape'][1]} px, seed {sim['seed']}")
    print("\nTable I. " + sim["table1"].to_text())
    t2 = sim["table2"]
    print(f"\nTable II. uniformity improvement (percentage points) by two-point FFC, test at "
          f"16.125 ms under lamp B ({t2['n_test_frames']} frames); [selected], *best*")
    print(f"{'band':>6} " + " ".join(f"{e:>9g}ms" for e in t2["exposures_ms"]))
    for band, row in enumerate(t2["improvement_pp"]):
        cells = []
        for j, e in enumerate(t2["exposures_ms"]):
            txt = f"{row[j]:+.3f}"
            if t2["best_ms"][band] == e:
                txt = f"*{txt}*"
            if t2["selected_ms"][band] == e:
                txt = f"[{txt}]"
            cells.append(f"{txt:>11}")
        print(f"{band + 1:>6} " + " ".join(cells))
    sp = sim["fig6"]
    print(f"\nFig. 6: {int(sp['valid'].sum())} of {len(sp['valid'])} lamp-B spectra valid; mean "
          f"spectral angle {sp['mean_angle_valid_pairs_deg']:.3f} deg between valid ones, "
          f"{sp['mean_angle_invalid_valid_pairs_deg'] or float('nan'):.3f} deg invalid-valid")
    tr = sim["tradeoff"]
    w = tr["weights"]
    print(f"trade-off: weights snr={w['snr']:g}, sc={w['sc']:g}, ru={w['ru']:g} choose an alpha "
          f"threshold of {tr['chosen_threshold_percent']:g} % (training ms per band: "
          f"{', '.join(f'{v:g}' for v in tr['chosen']['selected_ms'])})")
    em = res["emva"]
    if em is None:
        print(f"real data: {res['emva_note']}")
    else:
        best = em["candidates"][em["best_index"]]
        line = (f"real EMVA 1288 sweep: best flat step {best['step']} ({best['signal_dn']:.0f} DN, "
                f"{best['mean_nonuniformity_percent']:.3f} % residual non-uniformity)")
        if em["selected_index"] is not None:
            sel = em["candidates"][em["selected_index"]]
            line += (f"; alpha selects step {sel['step']} ({sel['signal_dn']:.0f} DN, "
                     f"{sel['mean_nonuniformity_percent']:.3f} %)")
        print(line)
    print(f"\nwrote {len(res['files'])} files to {args.outdir} in {res['timing']['total_s']:.1f} s:")
    for name in sorted(res["files"]):
        print(f"  {name}")
    return 0


def _cmd_diagnose(args) -> int:
    from .diagnose import diagnose, list_effects
    from .diagnose.report import write_json, write_report
    from .io import read_sweep

    if args.list_effects:
        for e in list_effects():
            print(f"{e['name']:<20} {e['scope']:<7} {e['summary']}")
        return 0
    if args.sweep is None:
        raise HsiffcError("give a SWEEP to diagnose (or --list-effects)")
    sweep = read_sweep(args.sweep)
    print(sweep.summary())
    effects = args.effects.split(",") if args.effects else None
    try:
        result = diagnose(sweep, max_pixels=args.pixels, seed=args.seed, effects=effects)
    except ValueError as exc:
        raise HsiffcError(str(exc)) from exc
    b, a = result["before"], result["after"]
    print(f"noise floor {result['noise_floor_dn']:.4g} DN; held-out RMS {b['rms_dn']:.4g} DN "
          f"(systematic {b['systematic_rms_dn']:.4g}) with the base model, {a['rms_dn']:.4g} DN "
          f"(systematic {a['systematic_rms_dn']:.4g}) with {result['selected_effects'] or 'no'} "
          "effects")
    for e in result["effects"]:
        print(f"  {e['name']}: {e['interpretation']}")
    print("  unexplained structure remains" if result["unexplained"]
          else "  no structure beyond the noise remains")
    print(f"  ({result['runtime_s']:.1f} s)")
    if args.json:
        write_json(result, args.json)
    if args.report:
        print(f"wrote {write_report(result, args.report)}")
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(args.samples, args.outdir)


def _write_json(path: Path, doc) -> None:
    from .atomic import atomic_write_text

    atomic_write_text(Path(path), json.dumps(doc, indent=2, default=_json_default) + "\n")


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
