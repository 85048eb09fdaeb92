"""The ``diagnose`` command: which effect a sweep shows that the model lacks."""

from __future__ import annotations

from pathlib import Path

from ..errors import HsiffcError
from .args import count
from .common import (add_input_options, add_overwrite, first_nonfinite, input_overrides,
                     nonfinite_samples)


def register(sub) -> None:
    """Add ``diagnose`` to the parser's sub-parsers (:func:`hsiffc.cli.build_parser`)."""
    _add_diagnose(sub)


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

