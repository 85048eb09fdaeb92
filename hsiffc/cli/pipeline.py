"""Commands on pipelines: ``stages``, ``fit``, ``correct``."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from ..batch.context import CUBE_METHODS, FFC_CHOICES
from ..errors import HsiffcError
from .args import count, percent, real
from .common import add_input_options, add_overwrite, input_overrides, write_json


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers."""
    _add_stages(sub)
    _add_fit(sub)
    _add_correct(sub)


def _add_stages(sub):
    p = sub.add_parser("stages", help="list the installed pipeline stages and where they come from")
    p.add_argument("--json", type=Path, default=None, help="also write the list as JSON")
    add_overwrite(p)
    p.set_defaults(func=_cmd_stages, output_args=("json",))


def _cmd_stages(args) -> int:
    from ..stages import describe

    rows = describe()
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        status = "" if r["status"] == "ok" else f"  [{r['status']}]"
        print(f"{r['name']:<{width}}  {r['source']:<24} {r['target']}{status}")
        if r["summary"]:
            print(f"{'':<{width}}  {r['summary']}")
    _print_filters()
    if args.json:
        write_json(args.json, rows)
    return 0


def _print_filters() -> None:
    """The filters the ``filter`` stage takes (``method = ...``), with their defaults."""
    from ..stages.filter import describe_filters

    rows = describe_filters()
    print("filters of the 'filter' stage (method = NAME, params = {...}):")
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        params = ", ".join(f"{k}={v!r}" for k, v in r["params"].items()) or "no parameters"
        status = "" if r["status"] == "ok" else f"[{r['status']}] "
        summary = r["summary"].rstrip(".") or "no summary"
        source = "" if r["source"] == "hsiffc (built-in)" else f"; from {r['source']}"
        print(f"  {r['name']:<{width}}  {status}{summary} ({params}{source}).")


def _add_fit(sub):
    p = sub.add_parser(
        "fit", help="fit a pipeline described in TOML on training frames and save it",
        description="Build the pipeline described by a TOML file ([[step]] tables with name, "
                    "stage and parameters), fit it on training frames (darks and flats, hsiffc "
                    "TIFF or EMVA 1288) and save the fitted pipeline (.npz, no pickle).")
    p.add_argument("description", type=Path, help="pipeline TOML file")
    p.add_argument("training", type=Path, nargs="*",
                   help="training frames (darks, flats): files of any supported format, "
                        "folders or globs")
    p.add_argument("--dark", type=Path, nargs="+", default=[], metavar="PATH",
                   help="dark reference frames (read as kind dark)")
    p.add_argument("--flat", "--white", dest="flat", type=Path, nargs="+", default=[],
                   metavar="PATH", help="flat / white reference frames (read as kind light)")
    p.add_argument("-o", "--output", type=Path, required=True, help="fitted pipeline (.npz)")
    add_input_options(p)
    add_overwrite(p)
    p.set_defaults(func=_cmd_fit, input_args=("description", "training", "dark", "flat"),
                   output_args=("output",))


def _cmd_fit(args) -> int:
    from ..data.mosaic import band_numbers, wavelength_order
    from ..stages import Pipeline

    if args.output.suffix != ".npz":  # before any input is read
        raise HsiffcError(f"-o {args.output}: a fitted pipeline file ends in .npz; rename it "
                          f"(e.g. {args.output.with_suffix('.npz').name})")
    pipe = Pipeline.from_toml(args.description)
    inputs = ([(p, {}) for p in args.training] + [(p, {"kind": "dark"}) for p in args.dark]
              + [(p, {"kind": "light"}) for p in args.flat])
    if not inputs:
        raise HsiffcError("give training frames: TRAINING paths, --dark and/or --flat")
    pipe.fit(read_training(args, inputs))
    pipe.save(args.output, overwrite=args.overwrite)
    for name, stage in pipe.steps:
        extra = ""
        if getattr(stage, "selected_ms_", None) is not None:  # by wavelength, as every table
            ms = list(stage.selected_ms_)
            wl = (getattr(stage, "alpha_table_", None) or {}).get("wavelengths_nm")
            wl = wl if wl and len(wl) == len(ms) else None
            number = band_numbers(len(ms), wl)
            extra = "  training exposure per band: " + ", ".join(
                f"band {number[i]} {ms[i]:g} ms" for i in wavelength_order(len(ms), wl))
        print(f"  fitted {name} ({stage.name}){extra}")
    print(f"wrote {args.output}")
    return 0


def read_training(args, inputs) -> list:
    """Training frames from ``inputs`` (``(path, fixed metadata)`` pairs, read with the
    command's input options), a summary of each printed; refuses inputs of other sensor sizes
    or mosaics than the first."""
    from ..data.frame import Frame
    from ..io import read_sweep

    frames, first = [], None
    for path, fixed in inputs:
        sweep = read_sweep(path, overrides=input_overrides(args, **fixed))
        print(sweep.summary())
        shape = tuple(sweep.frame_shape)
        if first is None:
            first = (path, shape, sweep.mosaic)
        elif shape != first[1]:
            raise HsiffcError(f"{path}: frames of {shape[0]} x {shape[1]} px, but {first[0]} has "
                              f"{first[1][0]} x {first[1][1]} px; train a pipeline on frames of "
                              "one sensor size (fit each size separately)")
        elif first[2] is not None and sweep.mosaic is not None and sweep.mosaic != first[2]:
            raise HsiffcError(f"{path}: mosaic {sweep.mosaic.describe()}, but {first[0]} has "
                              f"{first[2].describe()}; train a pipeline on frames of one sensor "
                              "(give the right --mosaic or fit each sensor separately)")
        dtype = str(sweep.data.dtype)  # recorded in the fitted pipeline (its fitted_on)
        frames += [f.replace(meta={"input_dtype": dtype}) for f in Frame.list_from_sweep(sweep)]
    return frames


def _add_correct(sub):
    p = sub.add_parser(
        "correct", help="correct a batch of frames (TIFF, PNG, ENVI, FITS) with a calibration "
                        "or a fitted pipeline",
        description="Correct every input (image files: TIFF, PNG, ENVI .hdr, FITS; folders "
                    "searched recursively, or globs) frame by frame and write one "
                    "<name>.corrected.tif per input under OUTDIR (pages per frame: data "
                    "float32, dq uint32, alpha float32; provenance JSON with the DQ bit "
                    "table); (H, W, bands) cubes when the pipeline's last step reconstructs "
                    "(--cube METHOD adds one), also as ENVI, OME-TIFF or netCDF (--format). "
                    "Outputs appear "
                    "atomically; a rerun skips the outputs that "
                    "are complete and up to date. Exit status 0: every file done or skipped; "
                    "1: some file failed (listed with its reason); 2: usage error.")
    p.add_argument("inputs", nargs="+",
                   help="image files (TIFF, PNG, ENVI .hdr, FITS), folders or globs (quote globs)")
    p.add_argument("--calibration", type=Path, default=None,
                   help="calibration file (.npz); needed by the default pipeline and by a "
                        "--pipeline whose stages use one")
    p.add_argument("-o", "--outdir", type=Path, required=True, help="output folder")
    p.add_argument("--pipeline", type=Path, default=None,
                   help="fitted pipeline (.npz from 'hsiffc fit'); default: dark from the "
                        "calibration + alpha mask + model-based flat field (--ffc)")
    p.add_argument("--threshold", type=percent, default=12.0,
                   help="alpha threshold in percent for the default pipeline (default 12)")
    p.add_argument("--ffc", choices=FFC_CHOICES, default=None,
                   help="flat-field step of the default pipeline: a flat-field method learnt "
                        "from the calibration alone (hsiffc.flatfield.FFC_METHODS; default "
                        "model: model_ffc, leakage inverted, each pixel divided by its "
                        "responsivity relative to its band) or none (dark + alpha mask only)")
    p.add_argument("--linearise", action="store_true",
                   help="with --ffc none: add leakage linearisation (model_ffc already "
                        "inverts the leakage)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="cuda: run the pipeline on an NVIDIA GPU (hsiffc[gpu]: numba-cuda; "
                        "dark, alpha mask, model or two-point FFC, nearest/bilinear/ppid "
                        "cubes, the correction matrix), in one process; a missing part is "
                        "named in one line (default: cpu)")
    p.add_argument("--workers", type=count, default=1,
                   help="at most this many worker processes on this machine (Dask local "
                        "cluster; default 1: in this process). Fewer are used where the input "
                        "is too small to pay for a cluster's start, or there are fewer files "
                        "or cores; each worker's kernels get cores/workers threads; the "
                        "summary says what ran")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on a Dask distributed cluster (e.g. tcp://host:8786); its workers "
                        "must see the inputs, calibration and OUTDIR at the same paths")
    p.add_argument("--overwrite", action="store_true",
                   help="redo outputs that are already complete and up to date, and replace an "
                        "existing --json file")
    p.add_argument("--nan", choices=("flag", "fail"), default="flag",
                   help="NaN/inf pixels in float inputs: flag them NONFINITE and warn "
                        "(default) or fail the file")
    p.add_argument("--no-hash", action="store_true",
                   help="do not record the inputs' sha256 in the provenance (saves one read)")
    p.add_argument("--wait", type=real, default=0.0, metavar="SECONDS",
                   help="when another run is writing into OUTDIR, wait up to SECONDS for it to "
                        "finish (default: refuse at once, naming that run)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (warnings are still printed)")
    p.add_argument("--fail-on-warning", action="append", default=[], metavar="CLASS",
                   help="fail a file that gives this warning class (e.g. "
                        "SceneBrighterThanReferenceWarning; a base class such as "
                        "ReflectanceWarning covers its subclasses; all: any warning): its "
                        "output is not written. Repeatable. Every warning is recorded either "
                        "way: printed with the file's name, in the --json results and in the "
                        "output's provenance")
    add_input_options(p)
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    p.add_argument("--format", default="tiff", metavar="FORMATS",
                   help="the files to write, one or more of tiff, envi, ome, netcdf "
                        "(comma-separated; default tiff): tiff the hsiffc TIFF "
                        "(NAME.corrected.tif, every frame), envi (NAME.hdr/.img, bands by "
                        "wavelength, DQ as NAME.dq.hdr/.img), ome (NAME.ome.tif, channels "
                        "named by wavelength), netcdf (NAME.nc: pip install 'hsiffc[xarray]'), "
                        "a cube per frame; mosaic frames become one spectrum per tile. Only "
                        "these are written; each keeps the provenance and resumes alone. See "
                        "the formats page")
    p.add_argument("--with-alpha", action="store_true",
                   help="also write the alpha planes in the envi, ome and netcdf files "
                        "(NAME.alpha.hdr/.img; the hsiffc TIFF always holds them)")
    p.add_argument("--cube", choices=CUBE_METHODS, default=None, metavar="METHOD",
                   help="append a reconstruct step: write full-resolution (H, W, bands) cubes "
                        f"by METHOD ({', '.join(CUBE_METHODS[:-1])}) or one spectrum per "
                        "mosaic tile "
                        "(tile). A --pipeline whose last step reconstructs writes cubes without "
                        "it. Which to use: ppid_edge for full-resolution cubes (the most "
                        "accurate against ground truth on both benchmark sensors, and faster "
                        "than ppid); ppid to match earlier results; ppid_paper and itsd to "
                        "compare with the literature (Mihoubi et al. 2017; iterative spectral "
                        "differences, Mizutani et al. 2014; both above ppid, below ppid_edge, "
                        "several times slower); bilinear for no mixing between "
                        "bands; tile when the spectra matter more than the resolution; nearest "
                        "for a quick look. Figures: docs/results/recon.md")
    p.add_argument("--cube-correction", choices=("imec", "derived"), default=None,
                   help="with --cube: apply the IMEC correction matrix to virtual bands (imec: "
                        "the vendor's; derived: computed from the band responses); needs "
                        "--imec-xml")
    p.add_argument("--imec-xml", type=Path, default=None, metavar="XML",
                   help="the sensor's IMEC calibration XML, for --cube-correction")
    p.add_argument("--compression", choices=("auto", "none", "zlib", "zstd", "lzma"),
                   default="auto",
                   help="lossless compression of the outputs: auto (default) the DQ plane, "
                        "zstd in the hsiffc TIFF, deflate (zlib) in ome and netcdf, none in envi "
                        "(the format has none), the float planes raw; none; or zlib, zstd, "
                        "lzma for every plane of the TIFF formats (netcdf takes zlib)")
    p.set_defaults(func=_cmd_correct,
                   input_args=("inputs", "calibration", "pipeline", "imec_xml"),
                   output_args=("json",))


class Progress:
    """What ``hsiffc correct`` says while it runs (an observer of
    :func:`hsiffc.batch.correct_batch`): each file's warnings as they come, one line per
    warning class naming the file (never merged across files; ``-q`` keeps them), and, with
    ``bar``, a rich progress bar on stderr: files, frames, input throughput."""

    def __init__(self, bar: bool = True):
        self.bar = bar
        self._p = None

    def start(self, n_files: int) -> None:
        if self.bar:
            self._start_bar(n_files)

    def _start_bar(self, n_files: int) -> None:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as Bar

        self._p = Bar(TextColumn("correct"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("files  {task.fields[frames]} frames  "
                                 "{task.fields[rate]:.1f} MB/s  {task.fields[failed]} failed"),
                      TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True))
        self._t0 = time.perf_counter()
        self._frames, self._bytes, self._failed = 0, 0.0, 0
        self._task = self._p.add_task("correct", total=n_files, frames=0, rate=0.0, failed=0)
        self._p.start()

    def _update(self, **kw):
        if self._p is None:
            return
        rate = self._bytes / max(time.perf_counter() - self._t0, 1e-9) / 1e6
        self._p.update(self._task, frames=self._frames, rate=rate, failed=self._failed, **kw)

    def frame(self, nbytes: float) -> None:
        if self._p is None:
            return
        self._frames += 1
        self._bytes += nbytes
        self._update()

    def file(self, res: dict, counted_frames: bool) -> None:
        for w in res["warnings"]:
            line = f"hsiffc correct: warning: {res['rel']}: {w['message']}"
            if self._p is not None:
                self._p.console.print(line, markup=False, highlight=False, soft_wrap=True)
            else:
                print(line, file=sys.stderr)
        if self._p is None:
            return
        if not counted_frames and res["status"] == "done":
            self._frames += res["frames"]
            self._bytes += res["bytes"]
        self._failed += res["status"] == "failed"
        self._update(advance=1)

    def close(self) -> None:
        if self._p is not None:
            self._p.stop()


def _cmd_correct(args) -> int:
    from ..batch import correct_batch
    from ..files.atomic import check_output
    from ..files.folderlock import LOCK_NAME
    from ..batch.plan import discover_inputs, is_batch_output

    if args.pipeline is not None and (args.ffc is not None or args.linearise):
        raise HsiffcError(f"--{'ffc' if args.ffc is not None else 'linearise'} sets up the "
                          "default pipeline; --pipeline brings its own steps: give one or the "
                          "other")
    if args.json is not None:  # checked now: the summary is written after the whole batch
        if args.json.name == LOCK_NAME:
            raise HsiffcError(f"--json {args.json}: {LOCK_NAME} is the name of the lock hsiffc "
                              "correct keeps in an output folder; give the summary another "
                              "name, e.g. summary.json")
        if is_batch_output(args.json):
            raise HsiffcError(f"--json {args.json}: is named like an output of hsiffc correct "
                              "(*.corrected.tif, *.reflectance.tif or their cubes); give the "
                              "summary another "
                              "name, e.g. summary.json")
        # an input found in a folder or glob
        check_output(args.json, overwrite=args.overwrite,
                     inputs=[path for path, _ in discover_inputs(args.inputs)[0]])
    if args.cube_correction is not None and args.cube is None:
        raise HsiffcError("--cube-correction applies to the cubes of --cube METHOD; add --cube")
    compression = None if args.compression == "none" else args.compression
    show = not args.quiet and sys.stderr.isatty()
    try:
        summary = correct_batch(args.inputs, args.outdir, args.calibration,
                                pipeline=args.pipeline, threshold_percent=args.threshold,
                                linearise=args.linearise, ffc=args.ffc or "model",
                                workers=args.workers,
                                scheduler=args.scheduler, overwrite=args.overwrite, nan=args.nan,
                                hash_inputs=not args.no_hash, wait_s=args.wait,
                                overrides=vars(input_overrides(args)),
                                observer=Progress(bar=show), cube=args.cube,
                                cube_correction=args.cube_correction,
                                imec_xml=args.imec_xml, compression=compression,
                                device=args.device, fail_on_warning=args.fail_on_warning,
                                formats=args.format, cube_alpha=args.with_alpha)
    except KeyboardInterrupt:
        print("hsiffc correct: interrupted; finished outputs are kept (no partial file is left "
              "under a final name): run the same command again to resume", file=sys.stderr)
        return 130
    print(summary.to_text())
    if args.json:
        write_json(args.json, summary.to_dict())
    return summary.exit_status

