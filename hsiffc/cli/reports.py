"""Applications: ``demo``, ``paper``, ``diagnose``."""

from __future__ import annotations

from pathlib import Path

from ..errors import HsiffcError
from .args import count, percent
from .common import (DEFAULT_SAMPLES, add_input_options, add_overwrite, first_nonfinite,
                     input_overrides, nonfinite_samples)


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    _add_demo(sub)
    _add_paper(sub)
    _add_diagnose(sub)


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
                   help="where to write the plot, the JSON summary, the calibration and the "
                        "pipeline (default: ./hsiffc-demo); a folder an earlier demo wrote is "
                        "reused, its files replaced")
    add_overwrite(p, "write into an OUTDIR that holds other files (replacing the demo's names)")
    # the output folder is checked by run_demo, after the samples: a missing sample is named
    # even when the folder is taken, and a rerun into the demo's own folder is allowed
    p.set_defaults(func=_cmd_demo, input_args=("samples",))


def _cmd_demo(args) -> int:
    from ..reports.demo import run_demo, render_text

    res = run_demo(args.samples, args.outdir, overwrite=args.overwrite or None)
    print(res.sweep.summary())
    print()
    print(render_text(res))
    print("\nwrote " + ", ".join(res.correction["files"].values()))
    return 0


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
    p.add_argument("--threshold", type=percent, default=12.0,
                   help="alpha threshold in percent for Tables I/II and Fig. 6 (default 12)")
    p.add_argument("--shape", type=count, nargs=2, default=(128, 128), metavar=("H", "W"),
                   help="simulated sensor size (multiple of the 2 x 4 tile; default 128 128)")
    add_overwrite(p, "replace the files of an earlier report in OUTDIR")
    p.set_defaults(func=_cmd_paper, input_args=("emva",), output_dirs=("outdir",))


def _cmd_paper(args) -> int:
    from ..reports.paper import parse_weights, run_paper_report

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
    sim = res.simulated
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
    em = res.emva
    if em is None:
        print(f"real data: {res.emva_note}")
    else:
        best = em["candidates"][em["best_index"]]
        line = (f"real EMVA 1288 sweep: best flat step {best['step']} ({best['signal_dn']:.0f} DN, "
                f"{best['mean_nonuniformity_percent']:.3f} % residual non-uniformity)")
        if em["selected_index"] is not None:
            sel = em["candidates"][em["selected_index"]]
            line += (f"; alpha selects step {sel['step']} ({sel['signal_dn']:.0f} DN, "
                     f"{sel['mean_nonuniformity_percent']:.3f} %)")
        print(line)
    print(f"\nwrote {len(res.files)} files to {args.outdir} in {res.timing['total_s']:.1f} s:")
    for name in sorted(res.files):
        print(f"  {name}")
    return 0


def _add_diagnose(sub):
    p = sub.add_parser(
        "diagnose", help="find where the model misses a sweep, trace it to an effect, report",
        description="Fit the base model (leakage model, constant dark level) per pixel on one "
                    "frame of every step, measure the error on the other frame, fit each "
                    "candidate effect, select those that beat the base model by more than the "
                    "noise allows, and report what remains unexplained.")
    p.add_argument("sweep", type=Path, nargs="?",
                   help="sweep: a file of any supported format, a folder or a glob")
    add_input_options(p)
    p.add_argument("--json", type=Path, default=None, help="write the result as JSON")
    p.add_argument("--report", type=Path, default=None,
                   help="folder for report.md, residuals.png and diagnosis.json")
    p.add_argument("--pixels", type=count, default=2048,
                   help="pixels analysed (random subset; default 2048)")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel subset")
    p.add_argument("--effects", default=None,
                   help="comma-separated candidate effects (default: the whole library)")
    p.add_argument("--list-effects", action="store_true", help="list the effect library and exit")
    add_overwrite(p, "replace an existing --json file or the files of an earlier --report")
    p.set_defaults(func=_cmd_diagnose, input_args=("sweep",), output_args=("json",),
                   output_dirs=("report",))


def _cmd_diagnose(args) -> int:
    from ..diagnose import diagnose, list_effects
    from ..diagnose.report import write_json, write_report
    from ..io import read_sweep

    if args.list_effects:
        for e in list_effects():
            print(f"{e['name']:<20} {e['scope']:<7} {e['summary']}")
        return 0
    if args.sweep is None:
        raise HsiffcError("give a SWEEP to diagnose (or --list-effects)")
    sweep = read_sweep(args.sweep, overrides=input_overrides(args))
    print(sweep.summary())
    bad = nonfinite_samples(sweep, args.sweep, what="diagnose")
    if bad:
        raise HsiffcError(f"{args.sweep}: {bad} samples are NaN/inf (the first at "
                          f"{first_nonfinite(sweep)}); diagnose needs finite samples: fix or "
                          "drop those frames")
    effects = args.effects.split(",") if args.effects else None
    try:
        result = diagnose(sweep, max_pixels=args.pixels, seed=args.seed, effects=effects)
    except ValueError as exc:
        raise HsiffcError(str(exc)) from exc
    from ..diagnose.report import headline
    for line in headline(result):
        print(line)
    b, a = result["before"], result["after"]
    print(f"held-out: {result['held_out']}; noise floor {result['noise_floor_dn']:.4g} DN "
          f"({result['noise_source']})")
    print(f"base model: {result['base_model']}")
    print(f"held-out RMS {b['rms_dn']:.4g} DN (systematic {b['systematic_rms_dn']:.4g}) with the "
          f"base model, {a['rms_dn']:.4g} DN (systematic {a['systematic_rms_dn']:.4g}) with "
          f"{result['selected_effects'] or 'no'} effects")
    for e in result["effects"]:
        print(f"  {e['name']}: {e['interpretation']}")
    print(f"  dark model: {result['dark_model']['model']}")
    print(f"  leakage: {result['leakage']['verdict']} ({result['leakage']['reason']})")
    for s_ in result["skipped"]:
        print(f"  skipped {s_['name']}: {s_['reason']}")
    print(f"  {'unexplained' if result['unexplained'] else 'nothing unexplained'}: "
          f"{result['unexplained_reason']}")
    for amb in result["ambiguous"]:
        print(f"  equally good: {' / '.join(amb['effects'])} ({amb['reason']})")
    print(f"  ({result['runtime_s']:.1f} s)")
    if args.json:
        write_json(result, args.json)
    if args.report:
        print(f"wrote {write_report(result, args.report)}")
    return 0

