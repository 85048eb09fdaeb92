"""Batch correction of TIFF cubes (``hsiffc correct``): streaming, resumable, parallel.

One task per input file (:mod:`.task`): it reads the input one frame at a time, runs the
pipeline on the frame and hands data, DQ and alpha to the writers of the formats asked for
(``formats``: the hsiffc TIFF of :mod:`hsiffc.io.corrected`, ENVI, OME-TIFF, netCDF cubes:
:mod:`hsiffc.cubes.stream`), written to temporary files renamed into place together only when
the input is complete. Memory is a few frames per
worker whatever the batch size. :mod:`.plan` turns inputs into jobs, :mod:`.context` holds the
calibration and pipeline, :mod:`.executors` runs the tasks in this process (one worker), on a
local Dask cluster (``workers > 1``) or on any Dask distributed scheduler (``scheduler=``).
Each task returns a small result dict, so a bad input is reported with its reason and the rest
carries on. The output folder is locked while a batch writes into it
(:func:`hsiffc.files.folderlock.folder_lock`).

>>> from hsiffc.batch import output_name
>>> output_name("day1/cube_07.tif")
'day1/cube_07.corrected.tif'
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from ..files.atomic import protect_inputs
from ..files.folderlock import folder_lock
from ..calibrate.product import Calibration
from .context import (
    FFC_CHOICES,
    NAN_POLICIES,
    Settings,
    check_ffc,
    context_for,
    default_pipeline,
    load_pipeline,
)
from .executors import check_scheduler, run_jobs
from .plan import (BatchError, Job, check_formats, discover_inputs, output_name, output_suffix,
                   plan_jobs, unread_files)
from .summary import BatchSummary
from .replace import check_replacements
from .task import correct_file
from .warnrec import check_classes
from .workers import WorkerPlan, plan_workers

__all__ = ["FFC_CHOICES", "BatchError", "BatchSummary", "Job", "Settings", "check_scheduler", "correct_batch",
           "correct_file", "default_pipeline", "discover_inputs", "load_pipeline", "output_name",
           "plan_jobs", "plan_workers", "WorkerPlan"]


def correct_batch(inputs, outdir, calibration=None, *, pipeline=None, threshold_percent: float = 12.0,
                  linearise: bool = False, ffc: str = "model", workers: int = 1,
                  scheduler: str | None = None,
                  overwrite: bool = False, nan: str = "flag", hash_inputs: bool = True,
                  overrides: dict | None = None, observer=None,
                  wait_s: float = 0.0, cube: str | None = None,
                  cube_correction: str | None = None, imec_xml=None,
                  compression: str | None = "auto", device: str = "cpu",
                  after=None, fail_on_warning=(), formats="tiff",
                  cube_alpha: bool = False) -> BatchSummary:
    """Correct every input (files, folders, globs) into ``outdir``; see ``hsiffc correct``.

    Parameters
    ----------
    inputs : sequence of path or str
        TIFF files, folders (searched recursively) and globs.
    outdir : path
        Output folder (created if missing; locked while the batch runs).
    calibration : path
        Calibration file (.npz); required (the default pipeline is built from it; with
        ``pipeline`` it must be the calibration the pipeline was fitted with).
    pipeline : path, optional
        Fitted pipeline (.npz from ``hsiffc fit``); default: :func:`default_pipeline`.
    threshold_percent : float
        Alpha threshold (%) of the default pipeline.
    linearise : bool
        Add leakage linearisation to the default pipeline (only with ``ffc="none"``).
    ffc : "model" or "none"
        Flat-field step of the default pipeline: ``model_ffc`` from the calibration alone
        (default) or none. Ignored with ``pipeline``.
    workers : int
        1: in this process. More: a local Dask cluster of that many single-threaded processes.
    scheduler : str, optional
        Address of a Dask distributed scheduler (``tcp://host:8786``); the workers must see the
        inputs, the calibration and OUTDIR at the same absolute paths. Checked for a connection
        (a few seconds) before anything else.
    overwrite : bool
        Redo outputs that are complete and up to date (otherwise skipped), replace the outputs
        of another job (another calibration, pipeline or options: otherwise the batch is
        refused before anything is written, :mod:`hsiffc.batch.replace`), and replace files at
        output names that are not outputs of ``hsiffc correct`` or are symbolic links (the link
        itself is replaced, never its target).
    nan : "flag" or "fail"
        NaN/inf pixels in float inputs: flag them NONFINITE (set to 0 DN) and warn, or fail
        the file.
    hash_inputs : bool
        Record each input's sha256 in the provenance (one extra read of the input).
    overrides : dict, optional
        Metadata for inputs that do not carry it (in their file or a sidecar): fields of
        :class:`hsiffc.io.Overrides` (``exposure_ms``, ``bit_depth``, ``kind``, ``mosaic``,
        ``illumination``, ``bit_shift``, ``sidecar``). Part of the outputs' fingerprint.
    observer : object, optional
        Told of progress: ``start(n_files)``, ``frame(nbytes)`` (in-process runs only),
        ``file(result, counted_frames)`` and ``close()`` (the CLI's progress bar).
    wait_s : float
        Seconds to wait when another run holds OUTDIR's lock (default: refuse at once).
    cube : {"nearest", "bilinear", "ppid", "tile"}, optional
        Append a reconstruct step: the outputs hold (H, W, B) cubes ("tile": one spectrum per
        mosaic tile). A fitted pipeline whose last step reconstructs writes cubes without it.
    cube_correction : {"imec", "derived"}, optional
        With ``cube``: the IMEC correction matrix to virtual bands (needs ``imec_xml``).
    imec_xml : path, optional
        The sensor's IMEC calibration XML (for ``cube_correction``).
    compression : {"auto", "zlib", "zstd", "lzma"} or None
        Lossless compression of the outputs. "auto" (default): each format's
        (:data:`hsiffc.cubes.stream.DEFAULT_COMPRESSION`: zstd for the hsiffc TIFF, deflate
        for the OME-TIFF and netCDF, none for ENVI); None: none; a name: the TIFF formats'
        pages (imagecodecs) and netCDF's variables (zlib whatever is given).
    device : {"cpu", "cuda"}
        ``"cuda"``: the pipeline runs on the GPU (:mod:`hsiffc.gpu`, one process); refused in
        one line, before anything is read, without numba-cuda or a GPU, with ``workers`` above
        1 or a ``scheduler``, or for a step the GPU does not run.
    after : callable, optional
        ``after(summary)`` runs once every file is done, while the output folder's lock is
        still held.
    fail_on_warning : sequence of str
        Warning classes (e.g. ``"SceneBrighterThanReferenceWarning"``; a base class such as
        ``"ReflectanceWarning"`` covers its subclasses) or ``"all"`` that fail a file: its
        output is not written and its result says which warning. Every warning is recorded
        for its file either way (:mod:`hsiffc.batch.warnrec`).
    formats : str or sequence of str
        The product files (:data:`hsiffc.cubes.stream.PRODUCT_FORMATS`; a comma-separated
        string or a sequence): "tiff" the hsiffc TIFF (default), "envi", "ome", "netcdf" a
        cube per frame (a mosaic frame becomes one spectrum per tile). Only these are
        written; each holds the provenance and resumes the batch alone.
    cube_alpha : bool
        Also write the alpha planes in the cube formats (the hsiffc TIFF always has them).

    Returns
    -------
    BatchSummary

    Raises
    ------
    BatchError, DataFormatError
        Before any file is processed: bad options, missing inputs, unreadable calibration or
        pipeline, an unreachable scheduler, an output that would overwrite an input, or an
        output of another job without ``overwrite``.
    hsiffc.files.folderlock.FolderLockedError
        Another run is writing into ``outdir`` (the message names its pid, host and start).
    """
    t0 = time.perf_counter()
    workers = _check_options(nan, workers, scheduler, threshold_percent)
    formats = check_formats(formats)
    if "netcdf" in formats:  # checked before any file is corrected
        from ..cubes.xr import require_xarray

        require_xarray()
    _check_device(device, workers, scheduler)
    check_ffc(ffc, bool(linearise) and pipeline is None)
    if calibration is None and pipeline is None:
        raise BatchError("give --calibration (for the default pipeline) or --pipeline (a fitted "
                         "pipeline; a calibration is needed only if its stages use one)")
    cal_path = None if calibration is None else Path(calibration).resolve()
    cal = None if cal_path is None else Calibration.load(cal_path)
    settings = Settings(calibration=None if cal_path is None else str(cal_path),
                        calibration_identity=None if cal is None else cal.identity,
                        pipeline=None if pipeline is None else str(Path(pipeline).resolve()),
                        threshold_percent=float(threshold_percent), linearise=bool(linearise),
                        ffc=ffc if pipeline is None else "none",
                        overwrite=bool(overwrite), nan=nan, hash_inputs=bool(hash_inputs),
                        overrides=_overrides(overrides), cube=cube,
                        cube_correction=cube_correction,
                        imec_xml=None if imec_xml is None else str(Path(imec_xml).resolve()),
                        compression=_compression(compression), device=device,
                        fail_on_warning=check_classes(fail_on_warning), formats=formats,
                        cube_alpha=bool(cube_alpha))
    if settings.imec_xml and not Path(settings.imec_xml).is_file():
        raise BatchError(f"{imec_xml}: IMEC calibration XML not found")
    if settings.pipeline and not Path(settings.pipeline).is_file():
        raise BatchError(f"{pipeline}: pipeline file not found")
    ctx = context_for(settings, cal)  # validates the pipeline here, before any file is touched
    del cal
    jobs, ignored = plan_jobs(inputs, outdir, output_suffix(ctx.info["steps"]))
    used = [p for p in (cal_path, settings.pipeline, settings.imec_xml) if p]
    with protect_inputs([j.input for j in jobs] + used), \
            folder_lock(outdir, wait_s=wait_s, what="hsiffc correct"):
        check_replacements(jobs, ctx, settings)  # another job's outputs: refused, untouched
        if observer is not None:
            observer.start(len(jobs))
        plan = None if scheduler else plan_workers(workers, _sizes(jobs))
        try:
            results = run_jobs(jobs, settings, workers=1 if plan is None else plan.workers,
                               scheduler=scheduler, observer=observer,
                               threads=None if plan is None else plan.threads_per_worker)
        finally:
            if observer is not None:
                observer.close()
        steps = [s["name"] for s in ctx.info["steps"]]
        summary = BatchSummary(
            [results[i] for i in sorted(results)], time.perf_counter() - t0,
            str(Path(outdir).resolve()),
            {"path": None if cal_path is None else str(cal_path), "identity": ctx.identity},
            {k: v for k, v in ctx.info.items() if k != "steps"} | {"steps": steps}, ignored,
            execution={"scheduler": scheduler} if plan is None else plan.to_dict()
            | {"text": plan.describe()},
            unread=[str(p) for p in unread_files(inputs)])
        if after is not None:
            after(summary)
    return summary


def _check_device(device, workers: int, scheduler) -> None:
    """BatchError for an unknown device or a GPU batch on several processes;
    :class:`hsiffc.gpu.GpuUnavailableError` (one line: what is missing) without one."""
    if device not in ("cpu", "cuda"):
        raise BatchError(f"--device must be cpu or cuda, got {device!r}")
    if device == "cpu":
        return
    from ..gpu import require

    require("--device cuda")
    if workers > 1 or scheduler:
        raise BatchError("--device cuda runs the batch in this process, on one GPU: drop "
                         f"{'--scheduler' if scheduler else '--workers'}")


def _sizes(jobs) -> list[int]:
    """Each job's input size in bytes (0 where it cannot be read now: the task reports it)."""
    out = []
    for job in jobs:
        try:
            out.append(os.stat(job.input).st_size)
        except OSError:
            out.append(0)
    return out


def _compression(name):
    """A compression the outputs take ("auto": each format's default; None: uncompressed)."""
    from ..cubes.writers import COMPRESSIONS

    if name is None or name == "none":
        return None
    if name == "auto":
        return name
    if name not in COMPRESSIONS:
        raise BatchError(f"--compression must be one of auto, none, "
                         f"{', '.join(COMPRESSIONS)}, got {name!r}")
    return name


def _overrides(values) -> tuple:
    """Input overrides as sorted (name, value) pairs (None dropped; paths made absolute so
    workers elsewhere find them); checked here, before any file is read."""
    from ..io import Overrides

    given = {k: v for k, v in (values or {}).items() if v is not None}
    if "sidecar" in given:
        given["sidecar"] = str(Path(given["sidecar"]).resolve())
    Overrides(**given)  # raises DataFormatError for a bad value
    return tuple(sorted(given.items()))


def _check_options(nan, workers, scheduler, threshold_percent) -> int:
    """The options a batch checks before reading anything; returns ``workers`` as an int."""
    if nan not in NAN_POLICIES:
        raise BatchError(f"nan must be one of {NAN_POLICIES}, got {nan!r}")
    try:
        workers = int(workers)
    except (TypeError, ValueError):
        raise BatchError(f"--workers must be a whole number, got {workers!r}") from None
    if workers < 1:
        raise BatchError(f"--workers must be at least 1, got {workers}")
    if scheduler and workers > 1:
        raise BatchError("give either --workers (a local cluster) or --scheduler, not both")
    try:
        threshold = float(threshold_percent)
    except (TypeError, ValueError):
        threshold = float("nan")
    if not 0 < threshold < float("inf"):
        raise BatchError(f"--threshold must be a positive, finite percentage, got "
                         f"{threshold_percent!r}")
    if scheduler:
        check_scheduler(scheduler)
    return workers
