"""Applications: ``demo``, ``paper``."""

from __future__ import annotations

from pathlib import Path

from ..errors import HsiffcError
from .args import count, percent
from .common import DEFAULT_SAMPLES, add_overwrite


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    _add_demo(sub)
    _add_paper(sub)


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
    from ..data.mosaic import wavelength_order
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
    rows = t2["improvement_pp"]  # by wavelength, numbered from 1 as in every table
    for k, band in enumerate(wavelength_order(len(rows), sim["table1"].wavelengths_nm or None)):
        row = rows[band]
        cells = []
        for j, e in enumerate(t2["exposures_ms"]):
            txt = f"{row[j]:+.3f}"
            if t2["best_ms"][band] == e:
                txt = f"*{txt}*"
            if t2["selected_ms"][band] == e:
                txt = f"[{txt}]"
            cells.append(f"{txt:>11}")
        print(f"{k + 1:>6} " + " ".join(cells))
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
