"""Batch correction of TIFF cubes (``hsiffc correct``): streaming, resumable, parallel.

One task per input file. A task reads the input one page (frame) at a time, runs the pipeline on
the frame and appends data, DQ and alpha to the output (:mod:`hsiffc.io.corrected`), written to
a temporary file renamed into place only when complete. Memory is a few frames per worker
whatever the batch size. Tasks run in this process (one worker), on a local Dask cluster
(``workers > 1``) or on any Dask distributed scheduler (``scheduler=``); each returns a small
result dict, so a bad input is reported with its reason and the rest carries on.

>>> from hsiffc.batch import output_name
>>> output_name("day1/cube_07.tif")
'day1/cube_07.corrected.tif'
"""

from __future__ import annotations

import glob
import hashlib
import json
import logging
import os
import re
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePath

import numpy as np
import tifffile

from . import __version__
from .atomic import atomic_path, folder_lock, protect_inputs
from .calibrate.product import Calibration
from .dq import DQ
from .errors import DataFormatError, HsiffcError
from .frame import Frame
from .io.corrected import FORMAT as CORRECTED_FORMAT
from .io.corrected import (
    SUFFIX,
    BackgroundWriter,
    CorrectedWriter,
    is_corrected_file,
    json_safe,
    read_provenance,
)
from .io.tiff import (
    TIFF_SUFFIXES,
    _CollectLog,
    _floats,
    _ifd_end,
    _parse_document,
    _per_frame,
    _strings,
    exposure_to_ms,
)
from .mosaic import Mosaic
from .stages import Pipeline, create
from .sweep import FRAME_KINDS

__all__ = ["BatchError", "BatchSummary", "Job", "Settings", "correct_batch", "correct_file",
           "default_pipeline", "discover_inputs", "load_pipeline", "output_name", "plan_jobs"]

log = logging.getLogger(__name__)
NAN_POLICIES = ("flag", "fail")
_MAGIC = re.compile(r"[*?[]")
_STATS_PIXELS = 1 << 16  # uniformity is estimated on whole tile rows totalling about this


class BatchError(HsiffcError):
    """The batch cannot start (bad arguments, inputs or options): a usage error."""


# -- inputs and outputs -----------------------------------------------------------------------
def _is_tiff(path) -> bool:
    return PurePath(path).suffix.lower() in TIFF_SUFFIXES


def _is_output(path) -> bool:
    name = PurePath(path).name.lower()
    return name.endswith(SUFFIX) or name.endswith(SUFFIX + "f")


def _hidden(rel: PurePath) -> bool:
    return any(part.startswith(".") for part in rel.parts)


def discover_inputs(args) -> tuple[list[tuple[Path, PurePath]], list[Path]]:
    """Expand files, folders and globs into ``(path, relative name)`` pairs.

    Folders are searched recursively for ``*.tif``/``*.tiff`` (hidden entries skipped) and
    globs (``*``, ``?``, ``[...]``, ``**``) are expanded; their relative name is the path below
    the folder or below the glob's fixed leading part. A file named directly keeps its name.
    Files named ``*.corrected.tif`` found by a folder or a glob are outputs of this command
    and are ignored (returned as the second list). Duplicates are dropped.

    Raises
    ------
    BatchError
        An argument that does not exist, a glob or folder without TIFF files, or a file that
        is not a ``.tif``/``.tiff``.
    """
    found: dict[Path, tuple[Path, PurePath]] = {}
    ignored: list[Path] = []

    def add(path: Path, rel: PurePath):
        key = path.resolve()
        if key not in found:
            found[key] = (path, rel)

    for arg in args:
        text = os.fspath(arg)
        if _MAGIC.search(text) and not Path(text).exists():
            root = _glob_root(text)
            files = [Path(m) for m in sorted(glob.glob(text, recursive=True))
                     if Path(m).is_file() and _is_tiff(m)]
            if not files:
                raise BatchError(f"{text}: the pattern matches no TIFF file (.tif/.tiff)")
            for f in files:
                rel = PurePath(os.path.relpath(f, root)) if root else PurePath(f)
                if rel.parts and rel.parts[0] == "..":
                    rel = PurePath(f.name)
                if _is_output(f):
                    ignored.append(f)
                else:
                    add(f, rel)
            continue
        path = Path(text)
        if path.is_dir():
            files = sorted(q for q in path.rglob("*")
                           if q.is_file() and _is_tiff(q) and not _hidden(q.relative_to(path)))
            if not files:
                raise BatchError(f"{path}: the folder holds no TIFF file (.tif/.tiff)")
            for f in files:
                if _is_output(f):
                    ignored.append(f)
                else:
                    add(f, f.relative_to(path))
        elif path.is_file():
            if not _is_tiff(path):
                raise BatchError(f"{path}: not a TIFF file name (.tif/.tiff); hsiffc correct "
                                 "reads hsiffc TIFF frames or cubes")
            add(path, PurePath(path.name))
        elif path.exists():
            raise BatchError(f"{path}: neither a regular file nor a folder")
        else:
            raise BatchError(f"{path}: no such file or folder")
    return list(found.values()), ignored


def _glob_root(pattern: str) -> str:
    parts = PurePath(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if _MAGIC.search(part):
            break
        fixed.append(part)
    return str(PurePath(*fixed)) if fixed else ""


def output_name(rel) -> str:
    """The output's name below OUTDIR for an input's relative name (POSIX separators)."""
    rel = PurePath(rel)
    return rel.with_name(rel.stem + SUFFIX).as_posix()


@dataclass(frozen=True)
class Job:
    """One input file and where its output goes (absolute paths)."""

    input: str
    rel: str
    output: str


def plan_jobs(inputs, outdir) -> tuple[list[Job], list[Path]]:
    """Jobs for ``inputs`` (files, folders, globs) writing below ``outdir``.

    Raises BatchError if two inputs map to one output or an output would overwrite an input.
    """
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise BatchError(f"{outdir}: the output folder is a file; give a folder (-o OUTDIR)")
    pairs, ignored = discover_inputs(inputs)
    if not pairs:
        raise BatchError("no input files; give TIFF files, folders or globs")
    jobs, seen = [], {}
    inputs_resolved = {p.resolve() for p, _ in pairs}
    inodes = {_inode(p) for p, _ in pairs} - {None}
    root = outdir.resolve()
    for path, rel in pairs:
        out = root / output_name(rel)  # not resolved: a link at the name is never followed
        if out in seen:
            raise BatchError(f"{path} and {seen[out]} would both be written to {out}; give them "
                             "from their folder (their relative paths keep them apart) or "
                             "correct them in separate runs")
        seen[out] = path
        if out.resolve() in inputs_resolved or (out.exists() and _inode(out) in inodes):
            raise BatchError(f"the output for {path} would overwrite the input {out}; hsiffc "
                             "correct never writes over an input: choose another output folder "
                             "(-o) or move that input")
        jobs.append(Job(str(path.resolve()), PurePath(rel).as_posix(), str(out)))
    return jobs, ignored


def _inode(path: Path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


# -- the pipeline -----------------------------------------------------------------------------
def default_pipeline(calibration, *, threshold_percent: float = 12.0,
                     linearise: bool = False) -> Pipeline:
    """The pipeline ``hsiffc correct`` applies without ``--pipeline``: it needs no training frames.

    ``dark`` (the calibration's dark level plus dark current times the exposure), ``mask``
    (``alpha_mask``: alpha per pixel, LEAKAGE above ``threshold_percent``, OUT_OF_DOMAIN and the
    calibration's pixel flags) and, with ``linearise``, ``linearise`` (leakage inversion).
    ``calibration`` is a saved Calibration (or its path).
    """
    cal = calibration if isinstance(calibration, Calibration) else Calibration.load(calibration)
    steps = [("dark", create("dark", calibration=cal).fit([])),
             ("mask", create("alpha_mask", calibration=cal,
                             threshold_percent=float(threshold_percent)).fit([]))]
    if linearise:
        steps.append(("linearise", create("linearise", calibration=cal).fit([])))
    return Pipeline(steps)


def load_pipeline(path, calibration: Calibration, notes: list | None = None) -> Pipeline:
    """A fitted pipeline file whose stages use ``calibration``.

    A stage's own calibration must have the same identity (else BatchError); when the file it
    names cannot be found (as given, or beside the pipeline file) ``calibration`` is used and a
    note is appended to ``notes``.
    """
    path = Path(path)
    notes = [] if notes is None else notes
    if path.suffix != ".npz":
        raise BatchError(f"{path}: --pipeline takes a fitted pipeline (.npz from 'hsiffc fit'); "
                         "fit a TOML description first")
    pipe = Pipeline.load(path, calibration=calibration)  # same identity: no file read
    for name, stage in pipe.steps:
        if stage.name == "reconstruct":
            raise BatchError(f"{path}: step {name!r} reconstructs cubes; hsiffc correct writes "
                             "corrected mosaic frames (H, W): fit a pipeline without it")
        if not stage.is_fitted():
            raise BatchError(f"{path}: step {name!r} is not fitted; fit it with 'hsiffc fit'")
        ref = stage.get_params().get("calibration")
        if ref is None:
            continue
        other = ref if isinstance(ref, Calibration) else _find_cal(ref, path)
        if other is None:
            # the file the pipeline names is not here (moved, or a path relative to where it
            # was fitted): the stage gets --calibration, which the provenance records
            notes.append(f"step {name!r}: its calibration {ref} is not found; "
                         f"--calibration {calibration.identity} is used")
        elif other.identity != calibration.identity:
            raise BatchError(f"{path}: step {name!r} uses calibration {other.identity} ({ref}) "
                             f"but --calibration is {calibration.identity}: pass the calibration "
                             "the pipeline was fitted with, or fit the pipeline again")
        stage.set_params(calibration=calibration)  # loaded once, not per frame
    return pipe


def _find_cal(ref, pipeline_path: Path) -> Calibration | None:
    ref = Path(ref)
    for cand in (ref, pipeline_path.parent / ref, pipeline_path.parent / ref.name):
        if cand.is_file():
            try:
                return Calibration.load(cand)
            except DataFormatError as exc:
                raise BatchError(f"{pipeline_path}: the calibration {cand} it names cannot be "
                                 f"read: {exc}") from exc
    return None


@dataclass(frozen=True)
class Settings:
    """Everything a task needs besides its Job (plain values, sent to the workers)."""

    calibration: str
    calibration_identity: str
    pipeline: str | None = None
    threshold_percent: float = 12.0
    linearise: bool = False
    overwrite: bool = False
    nan: str = "flag"
    hash_inputs: bool = True


@dataclass
class _Context:
    calibration: Calibration
    identity: str  # the calibration's (a content hash: computed once)
    pipeline: Pipeline
    info: dict


_CONTEXTS: dict = {}


def _context(settings: Settings, calibration: Calibration | None = None) -> _Context:
    """The calibration and pipeline of these settings, built once per process (from
    ``calibration`` when it is already loaded)."""
    key = (settings.calibration, settings.calibration_identity, settings.pipeline,
           settings.threshold_percent, settings.linearise)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        cal = calibration if calibration is not None else Calibration.load(settings.calibration)
        if calibration is None and cal.identity != settings.calibration_identity:
            raise BatchError(f"{settings.calibration}: the calibration changed since the batch "
                             f"started (identity {cal.identity}, expected "
                             f"{settings.calibration_identity})")
        if settings.pipeline:
            notes: list = []
            pipe = load_pipeline(settings.pipeline, cal, notes)
            info = {"kind": "file", "path": settings.pipeline,
                    "sha256": _sha256(settings.pipeline), "notes": notes}
        else:
            pipe = default_pipeline(cal, threshold_percent=settings.threshold_percent,
                                    linearise=settings.linearise)
            info = {"kind": "default", "path": None, "sha256": None, "notes": []}
        steps = [{"name": s["name"], "stage": s["stage"], "params": s["params"]}
                 for s in pipe.manifest()["steps"]]
        identity = settings.calibration_identity
        norm = [{**s, "params": {k: (f"identity:{identity}" if k == "calibration" and v
                                     else v) for k, v in s["params"].items()}} for s in steps]
        info["steps"] = steps
        info["fingerprint"] = hashlib.sha256(json.dumps(
            {"steps": norm, "file": info["sha256"]}, sort_keys=True).encode()).hexdigest()[:16]
        info["alpha_computed"] = any(s["stage"] == "alpha_mask" for s in steps)
        ctx = _Context(cal, identity, pipe, info)
        if len(_CONTEXTS) > 4:
            _CONTEXTS.clear()
        _CONTEXTS[key] = ctx
    return ctx


def _sha256(path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


# -- one file ---------------------------------------------------------------------------------
def _read_header(tf, path: Path, size: int) -> dict:
    """Validate an open input TIFF (without reading pixel data) and return its frame facts."""
    try:
        pages = list(tf.pages)
    except Exception as exc:  # tifffile raises many types on broken files
        raise DataFormatError(f"the TIFF's page list cannot be read ({type(exc).__name__}: "
                              f"{exc}); the file may be truncated - copy or write it again",
                              path=path) from exc
    if not pages:
        raise DataFormatError("the TIFF holds no image page; rewrite it", path=path)
    description = pages[0].description or ""
    if CORRECTED_FORMAT in description[:200]:
        raise DataFormatError("this is an output of hsiffc correct, not raw frames; give the raw "
                              "input", path=path)
    doc = _parse_document(description, path)
    n = len(pages)
    declared = doc.get("n_frames")
    if declared is not None and declared != n:
        raise DataFormatError(f"the metadata declares {declared} frames but only {n} pages could "
                              "be read; the file is probably truncated - copy or write it again",
                              path=path)
    shapes, dtypes = set(), set()
    for k, page in enumerate(pages):
        end = max(_ifd_end(tf, page), max((int(o) + int(c) for o, c in
                                           zip(page.dataoffsets, page.databytecounts)), default=0))
        if end > size:
            raise DataFormatError(f"file is truncated: page {k} needs bytes up to {end} but the "
                                  f"file has {size}; copy or write the file again", path=path)
        shapes.add(tuple(page.shape))
        dtypes.add(np.dtype(page.dtype).str)
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise DataFormatError(f"pages must all be single-channel images of one shape, found "
                              f"shapes {sorted(shapes)}; write one (H, W) frame per page", path=path)
    dtype = np.dtype(next(iter(dtypes))) if len(dtypes) == 1 else None
    if dtype is None or dtype.kind not in "uif":
        raise DataFormatError(f"pages must share one integer or float dtype, found {sorted(dtypes)}",
                              path=path)
    if doc.get("exposure") is None:
        raise DataFormatError("the hsiffc metadata has no 'exposure'; add the exposure time of "
                              "each frame (see the hsiffc TIFF format in the README)", path=path)
    if "exposure_unit" not in doc:
        raise DataFormatError("the hsiffc metadata has no 'exposure_unit'; add \"exposure_unit\": "
                              "\"ms\" (or s, us, ns)", path=path)
    exposure = _per_frame(doc, "exposure", n, path, _floats, required=True)
    exposure_ms = np.broadcast_to(exposure_to_ms(exposure, doc["exposure_unit"], path=path), (n,))
    if np.any(~np.isfinite(exposure_ms) | (exposure_ms < 0)):
        raise DataFormatError("'exposure' must be finite numbers >= 0; fix the JSON", path=path)
    bits = doc.get("bit_depth")
    if not isinstance(bits, int) or isinstance(bits, bool) or not 1 <= bits <= 32:
        raise DataFormatError(f"'bit_depth' must be a whole number 1..32, got {bits!r}; add the "
                              "ADC bit depth to the metadata", path=path)
    kind = np.broadcast_to(np.asarray(_per_frame(doc, "kind", n, path, _strings, "light"),
                                      dtype=object), (n,))
    bad = sorted(set(kind.tolist()) - set(FRAME_KINDS))
    if bad:
        raise DataFormatError(f"'kind' values {bad} are not one of {list(FRAME_KINDS)}", path=path)
    illum = np.broadcast_to(np.asarray(_per_frame(doc, "illumination", n, path, _strings, ""),
                                       dtype=object), (n,))
    mosaic = None
    if doc.get("mosaic") is not None:
        try:
            md = dict(doc["mosaic"])
            if md.get("wavelengths_nm") is None and doc.get("wavelengths_nm") is not None:
                md["wavelengths_nm"] = doc["wavelengths_nm"]
            mosaic = Mosaic.from_dict(md)
        except (TypeError, ValueError) as exc:
            raise DataFormatError(f"invalid 'mosaic' ({exc}); fix the JSON", path=path) from exc
    return {"pages": pages, "n": n, "shape": next(iter(shapes)), "dtype": dtype,
            "exposure_ms": [float(e) for e in exposure_ms], "kind": [str(k) for k in kind],
            "illumination": [str(i) for i in illum], "bit_depth": bits, "mosaic": mosaic}


def _stats_rows(shape, mosaic) -> np.ndarray:
    """Rows (whole tile rows, evenly spaced) on which uniformity is estimated."""
    h, w = shape
    th = mosaic.tile_shape[0] if mosaic is not None else 1
    blocks = h // th
    if blocks == 0 or h * w <= _STATS_PIXELS:
        return np.arange(h)
    step = max(1, blocks // max(1, _STATS_PIXELS // (w * th)))
    return (np.arange(0, blocks, step)[:, None] * th + np.arange(th)[None, :]).ravel()


def _mean_bands(rows) -> list:
    """Per band mean over frames (None entries are bands without a value)."""
    v = np.array([[np.nan if x is None else x for x in r] for r in rows], float)
    ok = np.isfinite(v)
    mean = np.where(ok, v, 0.0).sum(0) / np.maximum(ok.sum(0), 1)
    return [float(m) if c else None for m, c in zip(mean, ok.any(0))]


def _stale_reason(out: Path, job: Job, ctx: _Context, nan: str = "flag") -> str | None:
    """None when ``out`` is complete and was made from this input, calibration and pipeline."""
    try:
        prov = read_provenance(out)
    except DataFormatError as exc:
        return f"is not a complete corrected file ({exc})"
    st = os.stat(job.input)
    src = prov.get("input") or {}
    if src.get("size") != st.st_size or src.get("mtime_ns") != st.st_mtime_ns:
        return "was made from another version of the input (size or modification time differ)"
    if (prov.get("calibration") or {}).get("identity") != ctx.identity:
        return "was made with another calibration"
    if (prov.get("pipeline") or {}).get("fingerprint") != ctx.info["fingerprint"]:
        return "was made with another pipeline or other parameters"
    if nan == "fail" and any((prov.get("frames") or {}).get("nonfinite_pixels") or ()):
        return "holds NaN/inf pixels flagged under --nan flag"
    return None


def _reason(exc: BaseException, path: str) -> str:
    text = str(exc)
    if text.startswith(path + ": "):
        text = text[len(path) + 2:]
    if isinstance(exc, HsiffcError):
        return text
    return f"{type(exc).__name__}: {text}"


def correct_file(job: Job, settings: Settings, on_frame=None) -> dict:
    """Correct one input file; never raises for a bad input (the result says why it failed).

    Returns a dict: ``input``, ``rel``, ``output``, ``status`` ("done", "skipped" or
    "failed"), ``reason``, ``warnings``, ``frames``, ``bytes`` (input size), ``seconds`` and
    per band ``uniformity_before``/``uniformity_after`` (mean over the light frames, %)
    with ``light_frames``. ``on_frame(nbytes)`` is called after each frame (in-process only).
    """
    t0 = time.perf_counter()
    res = {"input": job.input, "rel": job.rel, "output": job.output, "status": "failed",
           "reason": "", "warnings": [], "frames": 0, "bytes": 0, "seconds": 0.0,
           "uniformity_before": None, "uniformity_after": None, "light_frames": 0}
    try:
        res["bytes"] = os.stat(job.input).st_size
        ctx = _context(settings)
        out = Path(job.output)
        if out.is_symlink() and not settings.overwrite:
            raise BatchError(f"the output {out} is a symbolic link; hsiffc never writes through "
                             "a link: remove it, or pass --overwrite to replace the link itself "
                             "(its target is kept)")
        if out.exists() and not settings.overwrite and not is_corrected_file(out):
            raise BatchError(f"the output {out} exists and is not an output of hsiffc correct; "
                             "move it, or pass --overwrite to replace it")
        if out.exists() and not settings.overwrite:
            why = _stale_reason(out, job, ctx, settings.nan)
            if why is None:
                res.update(status="skipped", reason="output complete and up to date")
                return res
            res["warnings"].append(f"existing output redone: it {why}")
        _correct(job, settings, ctx, res, on_frame)
        res["status"] = "done"
    except Exception as exc:  # one bad input must not stop the batch
        res.update(status="failed", reason=_reason(exc, job.input), frames=0)
    finally:
        res["seconds"] = time.perf_counter() - t0
    return res


def _remove_leftovers(out: Path) -> None:
    """Temporary files of an earlier, interrupted attempt at this output."""
    for stale in out.parent.glob(f".{glob.escape(out.name)}.*.part"):
        stale.unlink(missing_ok=True)


def _correct(job: Job, settings: Settings, ctx: _Context, res: dict, on_frame) -> None:
    path = Path(job.input)
    st = os.stat(path)
    hasher = _Background(_sha256, path) if settings.hash_inputs else None
    tlog = logging.getLogger("tifffile")
    collect = _CollectLog()
    tlog.addFilter(collect)
    try:
        try:
            tf = tifffile.TiffFile(path)
        except Exception as exc:
            extra = f" ({'; '.join(collect.messages[:3])})" if collect.messages else ""
            raise DataFormatError(f"not a readable TIFF file ({type(exc).__name__}: {exc}){extra}; "
                                  "the file may be truncated or not a TIFF", path=path) from exc
        with tf:
            head = _read_header(tf, path, st.st_size)
            ctx.calibration.check_compatible(frame_shape=head["shape"], bit_depth=head["bit_depth"],
                                             mosaic=head["mosaic"], what=path.name)
            _stream(tf, head, job, settings, ctx, res, on_frame, st, hasher)
    finally:
        tlog.removeFilter(collect)
        if hasher is not None:
            hasher.wait(raise_error=False)


class _Background:
    """``fn(*args)`` on a thread (hashing releases the GIL: it overlaps the correction)."""

    def __init__(self, fn, *args):
        self.value, self.error = None, None
        self._thread = threading.Thread(target=self._run, args=(fn, args), daemon=True)
        self._thread.start()

    def _run(self, fn, args):
        try:
            self.value = fn(*args)
        except BaseException as exc:  # handed to the caller in wait()
            self.error = exc

    def wait(self, raise_error: bool = True):
        self._thread.join()
        if self.error is not None and raise_error:
            raise self.error
        return self.value


def _band_uniformity(values, band, good, n_bands: int) -> list:
    """Eq. (6) per band, ``100 std / mean`` over the good pixels (two passes, as
    :func:`hsiffc.ffc.uniformity_per_band`; None where a band has fewer than 2 good pixels)."""
    good = good & np.isfinite(values)
    b = band[good]
    v = values[good].astype(np.float64)
    n = np.bincount(b, minlength=n_bands)
    mean = np.bincount(b, weights=v, minlength=n_bands) / np.maximum(n, 1)
    dev = v - mean[b]
    std = np.sqrt(np.bincount(b, weights=dev * dev, minlength=n_bands) / np.maximum(n, 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 100.0 * std / mean
    return [float(f"{x:.4g}") if c >= 2 and np.isfinite(x) else None for x, c in zip(u, n)]


def _provenance(job, settings, ctx, head, st) -> dict:
    cal, mosaic = ctx.calibration, head["mosaic"]
    return {"input": {"path": job.input, "relative": job.rel, "size": st.st_size,
                      "mtime_ns": st.st_mtime_ns, "sha256": None},
            "calibration": {"identity": ctx.identity, "path": settings.calibration,
                            "method": cal.method, "fitted_on": cal.fitted_on.get("source")},
            "pipeline": ctx.info, "alpha_computed": ctx.info["alpha_computed"],
            "hsiffc_version": __version__, "exposure_unit": "ms",
            "exposure": head["exposure_ms"], "kind": head["kind"],
            "illumination": head["illumination"], "bit_depth": head["bit_depth"],
            "mosaic": None if mosaic is None else mosaic.to_dict(),
            "input_dtype": head["dtype"].name, "nan_policy": settings.nan}


def _read_frame(page, k, head, path, settings) -> tuple[Frame, int]:
    """Page ``k`` as a Frame (as Frame.list_from_sweep makes it) and its count of NaN/inf."""
    bits = head["bit_depth"]
    try:
        raw = page.asarray()
    except Exception as exc:  # a damaged strip, an unsupported codec...
        raise DataFormatError(f"frame {k} cannot be read ({type(exc).__name__}: {exc}); copy "
                              "or write the file again", path=path) from exc
    if raw.dtype.kind in "ui" and raw.size and int(raw.max()) > 2 ** bits - 1:
        raise DataFormatError(f"frame {k}: data exceed the stated bit depth (maximum "
                              f"{int(raw.max())} DN > {2 ** bits - 1} DN = 2**{bits}-1); fix "
                              "'bit_depth' in the metadata", path=path)
    frame = Frame.from_raw(raw, exposure_ms=head["exposure_ms"][k], bit_depth=bits,
                           mosaic=head["mosaic"], kind=head["kind"][k],
                           illumination=head["illumination"][k], source=str(path))
    bad = 0
    if raw.dtype.kind == "f":
        bad = int(np.count_nonzero(frame.dq & np.uint32(DQ.NONFINITE)))
        if bad and settings.nan == "fail":
            raise DataFormatError(f"frame {k} holds {bad} NaN/inf pixels (--nan fail); fix the "
                                  "input or use --nan flag", path=path)
    return frame, bad


def _stream(tf, head, job, settings, ctx, res, on_frame, st, hasher) -> None:
    path, out = Path(job.input), Path(job.output)
    n, shape, mosaic = head["n"], head["shape"], head["mosaic"]
    rows = _stats_rows(shape, mosaic)
    band_rows = (mosaic.band_map(shape) if mosaic is not None else np.zeros(shape, np.int64))[rows]
    n_bands = int(band_rows.max()) + 1
    prov = _provenance(job, settings, ctx, head, st)
    nonfinite, flagged, before, after = [], [], [], []
    t0 = time.perf_counter()
    _remove_leftovers(out)
    with atomic_path(out, overwrite=True) as tmp:
        with CorrectedWriter(tmp, prov, n_frames=n, frame_shape=shape,
                             reserve_per_frame=96 + 20 * n_bands) as writer:
            sink = BackgroundWriter(writer)
            try:
                for k, page in enumerate(head["pages"]):
                    frame, bad = _read_frame(page, k, head, path, settings)
                    result = ctx.pipeline.transform(frame)
                    if result.data.shape != tuple(shape):
                        raise ValueError(f"the pipeline turned a {shape} frame into "
                                         f"{result.data.shape}; hsiffc correct writes (H, W) "
                                         "frames")
                    sink.write(result.data, result.dq, result.alpha)
                    nonfinite.append(bad)
                    flagged.append(round(np.count_nonzero(result.dq) / result.dq.size, 6))
                    light = frame.kind == "light"
                    before.append(_band_uniformity(frame.data[rows], band_rows,
                                                   frame.dq[rows] == 0, n_bands) if light else None)
                    after.append(_band_uniformity(result.data[rows], band_rows,
                                                  result.dq[rows] == 0, n_bands) if light else None)
                    del frame, result
                    res["frames"] = k + 1
                    if on_frame is not None:
                        on_frame(res["bytes"] / n)
            except BaseException:
                sink.close(cancel=True)
                raise
            sink.close()
            light = [b for b in before if b is not None]
            if light:
                res["light_frames"] = len(light)
                res["uniformity_before"] = _mean_bands(light)
                res["uniformity_after"] = _mean_bands([a for a in after if a is not None])
            stats = {"nonfinite_pixels": nonfinite, "flagged_fraction": flagged,
                     "uniformity_before": before, "uniformity_after": after,
                     "uniformity_rows": "all" if len(rows) == shape[0] else len(rows)}
            sha = hasher.wait() if hasher is not None else None
            writer.finish({"input": {**prov["input"], "sha256": sha}, "frames": stats,
                           "seconds": round(time.perf_counter() - t0, 3),
                           "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    if sum(nonfinite):
        res["warnings"].append(f"{sum(nonfinite)} NaN/inf pixels in "
                               f"{sum(1 for b in nonfinite if b)} frames flagged NONFINITE "
                               "(set to 0 DN)")


# -- the batch --------------------------------------------------------------------------------
@dataclass
class BatchSummary:
    """What a batch did: one result dict per input (see :func:`correct_file`)."""

    results: list
    seconds: float
    outdir: str
    calibration: dict
    pipeline: dict
    ignored: list = field(default_factory=list)

    def _with(self, status):
        return [r for r in self.results if r["status"] == status]

    @property
    def done(self):
        return self._with("done")

    @property
    def skipped(self):
        return self._with("skipped")

    @property
    def failed(self):
        return self._with("failed")

    @property
    def exit_status(self) -> int:
        """0 when every file is done or skipped, 1 when any failed."""
        return 1 if self.failed else 0

    def uniformity(self):
        """Per band (before, after) non-uniformity, mean over the light frames of done files."""
        rows = [r for r in self.done if r["uniformity_before"] is not None
                and r["uniformity_after"] is not None]
        if not rows:
            return None
        w = np.array([r["light_frames"] for r in rows], float)[:, None]
        out = []
        for key in ("uniformity_before", "uniformity_after"):
            v = np.array([[np.nan if x is None else x for x in r[key]] for r in rows], float)
            ok = np.isfinite(v)
            total = (np.where(ok, v, 0.0) * w).sum(0)
            weight = (ok * w).sum(0)
            out.append(np.where(weight > 0, total / np.maximum(weight, 1e-300), np.nan))
        return out[0], out[1]

    def to_dict(self) -> dict:
        u = self.uniformity()
        return json_safe({"outdir": self.outdir, "seconds": self.seconds,
                          "counts": {s: len(self._with(s)) for s in ("done", "skipped", "failed")},
                          "exit_status": self.exit_status, "calibration": self.calibration,
                          "pipeline": self.pipeline, "ignored": [str(p) for p in self.ignored],
                          "uniformity_before": None if u is None else u[0],
                          "uniformity_after": None if u is None else u[1],
                          "results": self.results})

    def to_text(self) -> str:
        done = self.done
        frames = sum(r["frames"] for r in done)
        mb = sum(r["bytes"] for r in done) / 1e6
        t = max(self.seconds, 1e-9)
        lines = [f"{len(self.results)} files: {len(done)} done, {len(self.skipped)} skipped, "
                 f"{len(self.failed)} failed; {frames} frames corrected in {self.seconds:.1f} s "
                 f"({frames / t:.2f} frames/s, {mb / t:.1f} MB/s of input)"]
        lines += [f"note: {n}" for n in self.pipeline.get("notes", [])]
        if self.ignored:
            lines.append(f"ignored {len(self.ignored)} files named *{SUFFIX} (outputs of "
                         "hsiffc correct)")
        u = self.uniformity()
        if u is not None:
            lines.append("non-uniformity per band (eq. 6, %, good pixels, mean over light "
                         "frames): before -> after")
            lines += [f"  band {i + 1}: {b:7.3f} -> {a:7.3f}" for i, (b, a) in enumerate(zip(*u))]
        warned = [r for r in self.results if r["warnings"]]
        if warned:
            lines.append("warnings:")
            lines += [f"  {r['rel']}: {w}" for r in warned for w in r["warnings"]]
        if self.failed:
            lines.append("failed:")
            lines += [f"  {r['rel']}: {r['reason']}" for r in self.failed]
        lines.append(f"outputs in {self.outdir}")
        return "\n".join(lines)


class _Progress:
    """A rich progress bar on stderr: files, frames and input throughput."""

    def __init__(self, n_files: int):
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._p = Progress(TextColumn("correct"), BarColumn(), MofNCompleteColumn(),
                           TextColumn("files  {task.fields[frames]} frames  "
                                      "{task.fields[rate]:.1f} MB/s  {task.fields[failed]} failed"),
                           TimeElapsedColumn(), TimeRemainingColumn(),
                           console=Console(stderr=True))
        self._t0 = time.perf_counter()
        self._frames, self._bytes, self._failed = 0, 0.0, 0
        self._task = self._p.add_task("correct", total=n_files, frames=0, rate=0.0, failed=0)
        self._p.start()

    def _update(self, **kw):
        rate = self._bytes / max(time.perf_counter() - self._t0, 1e-9) / 1e6
        self._p.update(self._task, frames=self._frames, rate=rate, failed=self._failed, **kw)

    def frame(self, nbytes: float):
        self._frames += 1
        self._bytes += nbytes
        self._update()

    def file(self, res: dict, counted_frames: bool):
        if not counted_frames and res["status"] == "done":
            self._frames += res["frames"]
            self._bytes += res["bytes"]
        self._failed += res["status"] == "failed"
        self._update(advance=1)

    def close(self):
        self._p.stop()


def correct_batch(inputs, outdir, calibration, *, pipeline=None, threshold_percent: float = 12.0,
                  linearise: bool = False, workers: int = 1, scheduler: str | None = None,
                  overwrite: bool = False, nan: str = "flag", hash_inputs: bool = True,
                  progress: bool = False, wait_s: float = 0.0) -> BatchSummary:
    """Correct every input (files, folders, globs) into ``outdir``; see ``hsiffc correct``.

    Parameters
    ----------
    calibration : path
        Calibration file (.npz); required (the default pipeline is built from it; with
        ``pipeline`` it must be the calibration the pipeline was fitted with).
    pipeline : path, optional
        Fitted pipeline (.npz from ``hsiffc fit``); default: :func:`default_pipeline`.
    workers : int
        1: in this process. More: a local Dask cluster of that many single-threaded processes.
    scheduler : str, optional
        Address of a Dask distributed scheduler (``tcp://host:8786``); the workers must see the
        inputs, the calibration and OUTDIR at the same absolute paths.
    overwrite : bool
        Redo outputs that are complete and up to date (otherwise skipped).
    nan : "flag" or "fail"
        NaN/inf pixels in float inputs: flag them NONFINITE (set to 0 DN) and warn, or fail
        the file.
    hash_inputs : bool
        Record each input's sha256 in the provenance (one extra read of the input).
    wait_s : float
        Seconds to wait when another run holds OUTDIR's lock (default: refuse at once).

    Raises
    ------
    BatchError, DataFormatError
        Before any file is processed: bad options, missing inputs, unreadable calibration or
        pipeline, or an output that would overwrite an input.
    hsiffc.atomic.FolderLockedError
        Another run is writing into ``outdir`` (the message names its pid, host and start).
    """
    t0 = time.perf_counter()
    if nan not in NAN_POLICIES:
        raise BatchError(f"nan must be one of {NAN_POLICIES}, got {nan!r}")
    if int(workers) < 1:
        raise BatchError(f"--workers must be at least 1, got {workers}")
    if scheduler and int(workers) > 1:
        raise BatchError("give either --workers (a local cluster) or --scheduler, not both")
    if not (0 < float(threshold_percent) < float("inf")):
        raise BatchError(f"--threshold must be a positive percentage, got {threshold_percent}")
    cal_path = Path(calibration).resolve()
    cal = Calibration.load(cal_path)
    settings = Settings(calibration=str(cal_path), calibration_identity=cal.identity,
                        pipeline=None if pipeline is None else str(Path(pipeline).resolve()),
                        threshold_percent=float(threshold_percent), linearise=bool(linearise),
                        overwrite=bool(overwrite), nan=nan, hash_inputs=bool(hash_inputs))
    if settings.pipeline and not Path(settings.pipeline).is_file():
        raise BatchError(f"{pipeline}: pipeline file not found")
    ctx = _context(settings, cal)  # validates the pipeline here, before any file is touched
    del cal
    jobs, ignored = plan_jobs(inputs, outdir)
    protect_inputs([j.input for j in jobs] + [cal_path, settings.pipeline])
    with folder_lock(outdir, wait_s=wait_s, what="hsiffc correct"):
        results = _run(jobs, settings, progress, workers, scheduler)
    cal_info = {"path": str(cal_path), "identity": ctx.identity}
    return BatchSummary([results[i] for i in sorted(results)], time.perf_counter() - t0,
                        str(Path(outdir).resolve()), cal_info,
                        {k: v for k, v in ctx.info.items() if k != "steps"} | {
                            "steps": [s["name"] for s in ctx.info["steps"]]},
                        ignored)


def _run(jobs, settings, progress, workers, scheduler) -> dict:
    bar = _Progress(len(jobs)) if progress else None
    results: dict[int, dict] = {}
    try:
        if scheduler or int(workers) > 1:
            _run_dask(jobs, settings, results, bar, workers=int(workers), scheduler=scheduler)
        else:
            for i, job in enumerate(jobs):
                results[i] = correct_file(job, settings, on_frame=bar.frame if bar else None)
                if bar:
                    bar.file(results[i], counted_frames=True)
    finally:
        if bar:
            bar.close()
    return results


def _local_cluster(workers: int):
    """A local cluster of single-threaded worker processes.

    Its workers start without distributed's default ``MALLOC_TRIM_THRESHOLD_``: setting it
    turns off glibc's adaptive mmap threshold, so every large numpy temporary is mapped and
    page-faulted afresh (twice the time per frame here); memory stays bounded without it.
    """
    import dask
    from distributed import LocalCluster

    key = "distributed.nanny.pre-spawn-environ"
    environ = {k: v for k, v in (dask.config.get(key, default=None) or {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({key: environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None, silence_logs=logging.ERROR)


def _run_dask(jobs, settings, results, bar, *, workers: int, scheduler: str | None) -> None:
    from distributed import Client, as_completed

    cluster = None
    if scheduler:
        client = Client(scheduler, timeout="30s")
    else:
        cluster = _local_cluster(workers)
        client = Client(cluster)
    try:
        futures = {client.submit(correct_file, job, settings, pure=False,
                                 key=f"hsiffc-correct-{i}-{os.getpid()}-{time.time_ns()}"): i
                   for i, job in enumerate(jobs)}
        for fut in as_completed(list(futures)):
            i = futures[fut]
            try:
                res = fut.result()
            except Exception as exc:  # e.g. KilledWorker: the worker died on this file
                res = {**asdict(jobs[i]), "status": "failed", "warnings": [], "frames": 0,
                       "bytes": 0, "seconds": 0.0, "uniformity_before": None,
                       "uniformity_after": None, "light_frames": 0,
                       "reason": f"the worker failed on this file ({type(exc).__name__}: {exc}); "
                                 "run again to retry it"}
            results[i] = res
            if bar:
                bar.file(res, counted_frames=False)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
