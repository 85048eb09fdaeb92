"""The per-file task of a batch: decode -> correct -> encode, one frame at a time.

:func:`correct_file` never raises for a bad input: its result dict says what happened. The
frame loop in :func:`stream_file` is the whole data path (read a frame, run the pipeline, hand
the planes to the writer); everything around it is checks, provenance and statistics.
"""

from __future__ import annotations

import contextvars
import glob
import logging
import os
import queue
import stat
import threading
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .. import __version__
from ..files.atomic import PART_SUFFIX, atomic_path
from ..cubes.product import frame_unit
from ..data.dq import DQ
from ..errors import DataFormatError, HsiffcError, MissingMosaicWarning
from ..data.frame import Frame
from ..io import find_sidecar
from ..stages.contract import check_frames
from ..io.corrected import (
    BackgroundWriter,
    CorrectedWriter,
    is_corrected_file,
)
from ..cubes.stream import (ProductWriter, compression_for, product_files, product_present,
                            read_product)
from ..cubes.export import written_by_hsiffc
from ..files.atomic import FileSet
from .context import Context, Settings, context_for, sha256_file
from .plan import BatchError, Job
from .source import open_input
from .stats import FrameStats
from .warnrec import (FileWarnings, NonFiniteInputWarning, NonFiniteOutputWarning,
                      failing_record)

__all__ = ["correct_file", "empty_result", "settle", "stale_reason", "stream_file"]

log = logging.getLogger(__name__)


def empty_result(job: Job, **fields) -> dict:
    """The result dict of a task that has not done anything yet (status "failed")."""
    return {"input": job.input, "rel": job.rel, "output": job.output, "status": "failed",
            "reason": "", "warnings": [], "redone": None, "frames": 0, "bytes": 0,
            "seconds": 0.0, "uniformity_before": None, "uniformity_after": None,
            "light_frames": 0, **fields}


def correct_file(job: Job, settings: Settings, on_frame=None, commits=None) -> dict:
    """Correct one input file; never raises for a bad input (the result says why it failed).

    Parameters
    ----------
    job : Job
    settings : Settings
    on_frame : callable, optional
        ``on_frame(nbytes)`` after each frame (``nbytes``: the input bytes per frame).
    commits : :class:`~hsiffc.batch.commits.DeferredCommits`, optional
        Leave the output's fsync and rename to this committer's thread (the caller's next
        file then overlaps the disk); the result is final only after :func:`settle`.

    Returns
    -------
    dict
        ``input``, ``rel``, ``output``, ``status`` ("done", "skipped" or "failed"),
        ``reason``, ``warnings`` (one record per warning class given while the file was
        corrected: ``class``, ``message``, ``figures``, ``count``; see
        :mod:`hsiffc.batch.warnrec`), ``redone`` (why an existing output was replaced, or
        None), ``frames``, ``bytes`` (input size), ``seconds`` and per band
        ``uniformity_before``/``uniformity_after`` (mean over the light frames, %) with
        ``light_frames``; for a file done, ``files`` (every file written, in every format)
        and ``bytes_written`` (their size).
    """
    t0 = time.perf_counter()
    res = empty_result(job)
    caught, kept = FileWarnings(), []
    try:
        with caught:
            res["bytes"] = os.stat(job.input).st_size
            ctx = context_for(settings)
            why = _existing_output(Path(job.output), job, settings, ctx)
            if why == "":
                res.update(status="skipped", reason="output complete and up to date")
                kept = _kept_warnings(Path(job.output), settings, res)
                return res
            if why is not None:
                res["redone"] = f"existing output redone: it {why}"
            _correct(job, settings, ctx, res, on_frame, commits, caught)
            res["status"] = "done"
    except LeftOut as why:
        res.update(status="skipped", reason=str(why), left_out="dark", frames=0)
    except Exception as exc:  # one bad input must not stop the batch
        res.update(status="failed", reason=_reason(exc, job.input), frames=0)
    finally:
        res["warnings"] = kept + caught.records()  # also those of a file that failed
        res["seconds"] = time.perf_counter() - t0
    return res


def _kept_warnings(out: Path, settings: Settings, res: dict) -> list:
    """The warnings an up-to-date output recorded when it was made (so that a resumed
    campaign's summary still lists them; marked ``"run": "earlier"``). A class given to
    ``--fail-on-warning`` fails the file, its output kept."""
    try:
        prov = read_product(out, settings.formats[0])
        records = [dict(r, run="earlier") for r in prov.get("warnings") or ()]
    except (DataFormatError, OSError):
        return []
    hit = failing_record(records, settings.fail_on_warning)
    if hit is not None:
        res.update(status="failed", reason=f"{hit['class']} (--fail-on-warning), recorded when "
                   f"the output was made: {hit['message']}; the output is kept: pass "
                   "--overwrite to redo it, or move it")
    return records


class LeftOut(Exception):
    """A file the batch leaves out (its frames are darks, by its own metadata)."""


def _existing_output(out: Path, job: Job, settings: Settings, ctx: Context) -> str | None:
    """None: no output yet (or --overwrite); "": complete and up to date in every format
    asked for (skip); else why the existing output of this command is redone. Raises
    BatchError for a symbolic link or a file that is not an output of ``hsiffc correct``
    (kept unless --overwrite)."""
    if settings.overwrite:
        return None
    whys = []
    for fmt in settings.formats:
        present = product_present(out, fmt)
        if not present:
            whys.append(None)
            continue
        for path in present:
            if path.is_symlink():
                raise BatchError(f"the output {path} is a symbolic link; hsiffc never writes "
                                 "through a link: remove it, or pass --overwrite to replace "
                                 "the link itself (its target is kept)")
        if fmt == "tiff" and not is_corrected_file(out):
            raise BatchError(f"the output {out} exists and is not an output of hsiffc "
                             "correct; move it, or pass --overwrite to replace it")
        if fmt != "tiff":
            foreign = [p for p in present if not written_by_hsiffc(p)]
            if foreign:
                raise BatchError(f"the output {foreign[0]} exists and is not a cube hsiffc "
                                 "wrote; move it, or pass --overwrite to replace it")
        whys.append(stale_reason(out, job, ctx, settings.nan, fmt=fmt,
                                 cube_alpha=settings.cube_alpha) or "")
    if all(w == "" for w in whys):
        return ""
    given = [w for w in whys if w]
    if given:
        return given[0]
    return None if all(w is None for w in whys) else \
        f"lacks the {', '.join(f for f, w in zip(settings.formats, whys) if w is None)} files"


def stale_reason(out: Path, job: Job, ctx: Context, nan: str = "flag", *,
                 fmt: str = "tiff", cube_alpha: bool = False) -> str | None:
    """None when the product of ``out`` in format ``fmt`` is complete and was made from this
    input, calibration and pipeline (and, for a cube format, holds the alpha planes when
    ``cube_alpha`` asks for them); otherwise why it must be redone."""
    try:
        prov = read_product(out, fmt)
    except DataFormatError as exc:
        what = "corrected file" if fmt == "tiff" else f"{fmt} product"
        return f"is not a complete {what} ({exc})"
    st = os.stat(job.input)
    src = prov.get("input") or {}
    if src.get("size") != st.st_size or src.get("mtime_ns") != st.st_mtime_ns:
        return "was made from another version of the input (size or modification time differ)"
    why = _metadata_changed(src, Path(job.input))
    if why:
        return why
    if (prov.get("calibration") or {}).get("identity") != ctx.identity:
        return "was made with another calibration"
    if (prov.get("pipeline") or {}).get("fingerprint") != ctx.info["fingerprint"]:
        return "was made with another pipeline or other parameters"
    if nan == "fail" and any((prov.get("frames") or {}).get("nonfinite_pixels") or ()):
        return "holds NaN/inf pixels flagged under --nan flag"
    wanted = cube_alpha and bool(ctx.info["alpha_computed"])
    if fmt != "tiff" and bool(prov.get("cube_alpha")) != wanted:
        return f"{'lacks' if wanted else 'holds'} the alpha planes (--with-alpha)"
    return None


_DIGESTS: dict = {}  # (path, device, inode, size, mtime_ns) -> sha256: one sidecar or XML
# shared by thousands of inputs is read once per process, not once per input


def _digest(path) -> str | None:
    """sha256 of a regular file's bytes; None when it is gone or not a regular file (a FIFO
    is never opened)."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            return None
        key = (str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
        if key not in _DIGESTS:
            if len(_DIGESTS) > 256:
                _DIGESTS.clear()
            _DIGESTS[key] = sha256_file(path)
        return _DIGESTS[key]
    except OSError:
        return None


def _metadata_sources(src, settings: Settings) -> list:
    """Every file besides the input whose content gave this output's metadata or
    correction (sidecars, IMEC XML, the other file of an ENVI pair, the ``--cube`` correction's
    XML), with the sha256 of its bytes: the resume check compares them."""
    files = [Path(p) for p in src.metadata_files]
    if settings.imec_xml:
        files.append(Path(settings.imec_xml))
    return [{"path": str(p), "sha256": _digest(p)} for p in dict.fromkeys(files)]


def _stat_record(path) -> dict:
    st = os.stat(path)
    return {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _metadata_changed(src: dict, input_path: Path) -> str | None:
    """Why the metadata sources (their content) and the data files besides the input (their
    size and time) recorded in an output's provenance (``src``: its "input") differ from the
    files now on disk, or None."""
    sources = src.get("metadata_sources")
    if not isinstance(sources, list):
        return ("was made by an hsiffc that did not record its metadata sources (sidecar, "
                "IMEC XML)")
    recorded = set()
    for item in sources:
        if not isinstance(item, dict) or not isinstance(item.get("path"), str):
            return "has a damaged provenance (its metadata sources)"
        if _digest(item["path"]) != item.get("sha256"):
            return (f"was made with another version of {Path(item['path']).name} (a metadata "
                    "source: its content differs now, or it is gone)")
        recorded.add(Path(item["path"]).resolve())
    for item in src.get("data_files") or ():
        if not isinstance(item, dict) or not isinstance(item.get("path"), str):
            return "has a damaged provenance (its data files)"
        try:
            st = os.stat(item["path"])
        except OSError:
            st = None
        if st is None or (st.st_size, st.st_mtime_ns) != (item.get("size"),
                                                          item.get("mtime_ns")):
            return (f"was made from another version of its data file {Path(item['path']).name} "
                    "(size or modification time differ, or it is gone)")
    if src.get("sidecar_lookup"):
        side = find_sidecar(input_path.parent)
        if side is not None and side.resolve() not in recorded:
            return f"was made without the sidecar {side.name} now next to the input"
    return None


def _reason(exc: BaseException, path: str) -> str:
    text = str(exc)
    if text.startswith(path + ": "):
        text = text[len(path) + 2:]
    if isinstance(exc, HsiffcError):
        return text
    return f"{type(exc).__name__}: {text}"


def settle(res: dict, commits) -> dict:
    """Wait for the deferred commit of a done result's output (see :func:`correct_file`);
    a commit that failed turns the result into a failure that says why. Returns ``res``."""
    if res["status"] == "done" and commits.pending(res["output"]):
        try:
            commits.wait(res["output"])
        except Exception as exc:
            res.update(status="failed", reason=_reason(exc, res["input"]), frames=0)
    return res


def _correct(job: Job, settings: Settings, ctx: Context, res: dict, on_frame,
             commits=None, caught=None) -> None:
    path = Path(job.input)
    st = os.stat(path)
    hasher = Background(sha256_file, path) if settings.hash_inputs else None
    try:
        with open_input(path, settings.overrides) as src:
            kinds = {str(k) for k in src.kind}
            if kinds == {"dark"} and "kind" not in dict(settings.overrides):
                raise LeftOut("dark frames (the file's metadata says kind dark): left out of "
                              "the scene batch (give --kind to correct them anyway)")
            check_frames(ctx.info.get("fitted_on"), shape=src.frame_shape, mosaic=src.mosaic,
                         bit_depth=src.bit_depth, what=path.name)  # the fit's frame contract
            if ctx.calibration is not None:
                ctx.calibration.check_compatible(frame_shape=src.frame_shape,
                                                 bit_depth=src.bit_depth, mosaic=src.mosaic,
                                                 what=path.name)
                if src.mosaic is None and ctx.calibration.mosaic is not None:
                    # the file's record keeps this first message (the stages' repeats count)
                    warnings.warn(MissingMosaicWarning(
                        "the file gives no mosaic layout but the calibration is for "
                        f"{ctx.calibration.mosaic.describe()}, {ctx.calibration.mosaic.n_bands} "
                        "bands: corrected pixel by pixel, its "
                        "per-band figures are for the whole frame as one band; give the "
                        "layout (--mosaic, or a sidecar hsiffc.toml) to get them by band",
                        figures={"mosaic": ctx.calibration.mosaic.describe(),
                                 "bands": ctx.calibration.mosaic.n_bands}))
            stream_file(src, job, settings, ctx, res,
                        FileRun(on_frame=on_frame, st=st, hasher=hasher, commits=commits,
                                caught=caught))
    finally:
        if hasher is not None:
            hasher.wait(raise_error=False)


class FileRun(NamedTuple):
    """What a task lends :func:`stream_file` for one input (each may be None)."""

    #: ``on_frame(bytes)`` after each frame (the progress display)
    on_frame: object = None
    #: the input's ``os.stat`` taken when the task opened it (else taken now)
    st: object = None
    #: a :class:`Background` computing the input's sha256, or None (not recorded)
    hasher: object = None
    #: the :class:`~hsiffc.batch.commits.DeferredCommits` that fsync and rename finished outputs
    #: (None: committed here)
    commits: object = None
    #: the file's :class:`~hsiffc.batch.warnrec.FileWarnings`
    caught: object = None


class _Output(NamedTuple):
    """One input's products while they are written: the output path, its provenance, the
    files written (renamed into place together), the frame statistics, the input's frame
    shape and whether the cube formats get the alpha planes."""

    path: Path
    prov: dict
    files: FileSet
    stats: FrameStats
    shape: tuple
    cube_alpha: bool


def stream_file(src, job: Job, settings: Settings, ctx: Context, res: dict,
                run: FileRun = FileRun()) -> None:
    """Correct every frame of the open input ``src`` into ``job.output`` (atomically).

    The loop is decode (``src`` yields raw frames, read ahead on a thread by
    :class:`Prefetch`), correct (``ctx.pipeline.transform`` on this thread, compiled kernels
    using every core), encode (a :class:`~hsiffc.io.corrected.BackgroundWriter` writes the
    planes on its own thread while the next frame is corrected): the three overlap, as
    tifffile and imagecodecs release the GIL. Memory: a few frames.

    ``run.caught``: the file's :class:`~hsiffc.batch.warnrec.FileWarnings`; its records go
    into the provenance, and a class in ``settings.fail_on_warning`` fails the file before its
    output is put in place.
    """
    on_frame, st, hasher, commits, caught = run
    out = Path(job.output)
    st = st if st is not None else os.stat(job.input)
    shape = tuple(src.frame_shape)
    stats = FrameStats(shape, src.mosaic)
    prov = _provenance(job, settings, ctx, src, st)
    t0 = time.perf_counter()
    cube_alpha = settings.cube_alpha and bool(ctx.info["alpha_computed"])
    prov["cube_alpha"] = cube_alpha
    for fmt in settings.formats:
        names = product_files(out, fmt, src.n_frames, cube_alpha)
        if fmt != "tiff" and not settings.overwrite:  # frame 0's were checked before
            foreign = [p for p in names if os.path.lexists(p) and (
                p.is_symlink() or not written_by_hsiffc(p))]
            if foreign:
                raise BatchError(f"the output {foreign[0]} exists and is not a cube hsiffc "
                                 "wrote; move it, or pass --overwrite to replace it")
        _remove_leftovers(names)  # of an interrupted earlier run (the folder lock is held)
    files = FileSet()
    writer = sink = None
    try:
        frames = Prefetch(src)
        try:
            for raw, meta in frames:
                frame, bad = _to_frame(raw, meta, src, settings)
                result = ctx.pipeline.transform(frame)
                if writer is None:  # the first frame tells the output's shape (a cube or not)
                    writer = _product_writer(_Output(out, prov, files, stats, shape,
                                                     cube_alpha), settings, ctx, src, result)
                    sink = BackgroundWriter(writer)
                elif result.data.shape != writer.shape:
                    raise ValueError(f"the pipeline turned frame {meta.index} into "
                                     f"{result.data.shape}, the first into "
                                     f"{writer.shape}; one file holds one shape")
                data, dq, lost = _finite(result)
                sink.write(data, dq, result.alpha)
                stats.add(frame, result, bad, lost)
                del frame, result
                res["frames"] = meta.index + 1
                if on_frame is not None:
                    on_frame(res["bytes"] / src.n_frames)
        except BaseException:
            frames.close()
            if sink is not None:
                sink.close(cancel=True)
            raise
        frames.close()
        if sink is not None:
            sink.close()
        if res["frames"] != src.n_frames or writer is None:
            raise DataFormatError(f"only {res['frames']} of {src.n_frames} frames could be read",
                                  path=job.input)
        res.update(stats.file_result())
        _nonfinite_warnings(stats)
        if caught is not None:
            caught.check(settings.fail_on_warning)
        sha = hasher.wait() if hasher is not None else None
        final = {"input": {**prov["input"], "sha256": sha}, "frames": stats.to_dict(),
                 "seconds": round(time.perf_counter() - t0, 3),
                 "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                 "warnings": [] if caught is None else caught.records()}
        if writer.cube is not None:
            final["cube"] = writer.cube
        writer.finish(final)
    except BaseException:
        if writer is not None:
            writer.close()
        files.abort()
        raise
    res["files"] = [str(p) for p in files.paths]
    res["bytes_written"] = sum(os.stat(files.temp(p)).st_size for p in files.paths)
    if commits is not None:  # the fsyncs and renames overlap the next file
        commits.submit(out, contextvars.copy_context().run, files.commit)
    else:
        files.commit()


def _product_writer(output: _Output, settings: Settings, ctx: Context, src,
                    result) -> ProductWriter:
    """The writer of every product format of this input, made when the first frame tells
    the output's shape."""
    out, prov, files, stats, shape, cube_alpha = output
    frame_shape = _output_shape(result, shape)
    cube = cube_description(result)
    tiff = None
    if "tiff" in settings.formats:
        with atomic_path(out, overwrite=True, fileset=files) as tmp:
            tiff = CorrectedWriter(
                tmp, prov, n_frames=src.n_frames, frame_shape=frame_shape,
                reserve_per_frame=96 + 20 * max(stats.n_bands, result.data.shape[-1]),
                alpha=ctx.info["alpha_computed"],
                compression=compression_for("tiff", settings.compression))
    return ProductWriter(out, settings.formats, {**prov, "cube": cube},
                         shape=result.data.shape, n_frames=src.n_frames, fileset=files,
                         compression=settings.compression, alpha=cube_alpha, tiff_writer=tiff)


def _nonfinite_warnings(stats: FrameStats) -> None:
    """The file's NaN/inf counts, in and out, as warnings (recorded with the file's)."""
    bad = [b for b in stats.nonfinite if b]
    if bad:
        warnings.warn(NonFiniteInputWarning(
            f"{sum(bad)} NaN/inf pixels in {len(bad)} frames flagged NONFINITE (set to 0 DN)",
            figures={"pixels": sum(bad), "frames": len(bad)}))
    lost = [b for b in stats.nonfinite_out if b]
    if lost:
        warnings.warn(NonFiniteOutputWarning(
            f"the correction gave {sum(lost)} NaN/inf pixels in {len(lost)} frames (e.g. an "
            "exposure far outside the calibration's range): flagged NONFINITE + DO_NOT_USE and "
            "written as 0 DN", figures={"pixels": sum(lost), "frames": len(lost)}))


def _output_shape(result: Frame, shape: tuple) -> tuple:
    """The shape every frame of this file is written with: the input's (H, W), or the cube
    of a pipeline whose last step reconstructs."""
    if result.is_cube:
        return tuple(result.data.shape)
    if result.data.shape != shape:
        raise ValueError(f"the pipeline turned a {shape} frame into {result.data.shape}; "
                         "hsiffc correct writes (H, W) frames or the cubes of a reconstruct "
                         "step")
    return shape


def cube_description(result: Frame) -> dict | None:
    """What the provenance says of a cube's bands (None for a mosaic frame): wavelengths,
    widths, mosaic positions in the cube's band order (``"band index"``: the pipeline's, not
    sorted; exports sort them by wavelength) and how it was reconstructed."""
    if not result.is_cube:
        return None
    meta = result.meta
    n = result.data.shape[-1]
    return {"shape": list(result.data.shape), "unit": frame_unit(meta),
            "band_order": "band index", "band_index": list(range(n)),
            "wavelengths_nm": meta.get("wavelengths_nm"), "fwhm_nm": meta.get("fwhm_nm"),
            "band_positions": meta.get("band_positions"),
            "reconstruction": meta.get("reconstruction"), "tile_origin": meta.get("tile_origin")}


def _finite(result: Frame):
    """The corrected planes with NaN/inf data set to 0 DN and flagged (outputs are never
    NaN/inf silently); and how many pixels that was."""
    data, dq = result.data, result.dq
    if np.isfinite(np.add.reduce(data, axis=None)):  # one pass, no mask: a NaN/inf anywhere
        return data, dq, 0                          # makes the sum so (overflow: checked below)
    bad = ~np.isfinite(data)
    n = int(np.count_nonzero(bad))
    if n:
        data = np.where(bad, np.float32(0), data)
        dq = dq | np.where(bad, np.uint32(DQ.NONFINITE | DQ.DO_NOT_USE), np.uint32(0))
    return data, dq, n


def _to_frame(raw, meta, src, settings: Settings) -> tuple[Frame, int]:
    """A raw frame as a Frame (as Frame.list_from_sweep makes it) and its count of NaN/inf."""
    frame = Frame.from_raw(raw, exposure_ms=meta.exposure_ms, bit_depth=src.bit_depth,
                           mosaic=src.mosaic, kind=meta.kind, illumination=meta.illumination,
                           source=meta.path)
    bad = 0
    if raw.dtype.kind == "f":
        bad = int(np.count_nonzero(frame.dq & np.uint32(DQ.NONFINITE)))
        if bad and settings.nan == "fail":
            raise DataFormatError(f"frame {meta.index} holds {bad} NaN/inf pixels (--nan fail); "
                                  "fix the input or use --nan flag", path=meta.path)
    return frame, bad


def _remove_leftovers(files) -> None:
    """Temporary files of an earlier, interrupted attempt at these output files."""
    for out in files:
        for stale in out.parent.glob(f".{glob.escape(out.name)}.*{PART_SUFFIX}"):
            stale.unlink(missing_ok=True)


def _provenance(job: Job, settings: Settings, ctx: Context, src, st) -> dict:
    cal, mosaic = ctx.calibration, src.mosaic
    return {"input": {"path": job.input, "relative": job.rel, "size": st.st_size,
                      "mtime_ns": st.st_mtime_ns, "sha256": None,
                      "metadata_sources": _metadata_sources(src, settings),
                      "sidecar_lookup": bool(src.sidecar_lookup),
                      "data_files": [_stat_record(p) for p in src.data_files]},
            "calibration": None if cal is None else {
                "identity": ctx.identity, "path": settings.calibration, "method": cal.method,
                "fitted_on": cal.fitted_on.get("source")},
            "pipeline": ctx.info, "alpha_computed": ctx.info["alpha_computed"],
            "hsiffc_version": __version__, "exposure_unit": "ms",
            "exposure": [float(e) for e in src.exposure_ms], "kind": [str(k) for k in src.kind],
            "illumination": [str(i) for i in src.illumination], "bit_depth": src.bit_depth,
            "mosaic": None if mosaic is None else mosaic.to_dict(),
            "input_dtype": np.dtype(src.dtype).name, "nan_policy": settings.nan}


class Background:
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
        """The result (after the thread ends); re-raises its error unless told not to."""
        self._thread.join()
        if self.error is not None and raise_error:
            raise self.error
        return self.value


class Prefetch:
    """Iterate ``source`` on a thread, ``depth`` items ahead (decoding overlaps the caller's
    work; at most ``depth`` decoded frames wait). An error in the thread is raised in the
    caller when it reaches that item; :meth:`close` stops the thread (call it before the
    source is closed)."""

    _END = object()

    def __init__(self, source, depth: int = 2):
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(source,), daemon=True)
        self._thread.start()

    def _run(self, source):
        try:
            for item in source:
                if self._stop.is_set():
                    return
                self._queue.put((item, None))
        except BaseException as exc:  # raised again in the caller's thread
            self._queue.put((None, exc))
            return
        self._queue.put((self._END, None))

    def __iter__(self):
        while True:
            item, error = self._queue.get()
            if error is not None:
                raise error
            if item is self._END:
                return
            yield item

    def close(self) -> None:
        """Stop reading ahead and wait for the thread (drops frames not yet consumed)."""
        self._stop.set()
        while self._thread.is_alive():
            try:
                self._queue.get(timeout=0.05)
            except queue.Empty:
                pass
        self._thread.join()
