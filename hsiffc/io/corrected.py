"""The corrected-cube layout written by ``hsiffc correct``: one TIFF per input, three pages per frame.

File layout
-----------
* Pages come in groups of three (two for a cube without alpha: ``"pages_per_frame"``), one
  group per input frame, in the input's order (format 2 also holds cubes: each page then is
  ``(H, W, B)``, the bands as samples of each pixel, and ``"frame_shape"`` has three
  entries; pages may be compressed, ``"compression"``)::

      page 3k + 0   data   float32 (H, W)   corrected frame k (DN)
      page 3k + 1   dq     uint32  (H, W)   hsiffc.data.dq.DQ bits of frame k
      page 3k + 2   alpha  float32 (H, W)   leakage percentage alpha of frame k (NaN when the
                                            pipeline computes no alpha: "alpha_computed": false)

  The three planes differ in a property tifffile groups pages by (dtype, or strip layout for
  alpha), so ``tifffile`` sees three series: ``series=0`` data, ``1`` dq, ``2`` alpha, each
  ``(N, H, W)``. Slicing pages (``key=slice(j, None, 3)``) works with any TIFF reader.
* The ImageDescription of the first page holds the provenance as one JSON object (ASCII):
  ``"format": "hsiffc-corrected"``, ``"format_version"``, ``"status": "complete"``, ``"planes"``,
  ``"n_frames"``, ``"frame_shape"``, ``"dq_bits"`` (the DQ bit table: name, value, bit,
  meaning, so the DQ plane is decoded with the file alone), the input (path, size, mtime_ns, sha256), the calibration
  (identity, path), the pipeline (steps with parameters, fingerprint), ``"hsiffc_version"``,
  per-frame ``"exposure"`` (ms), ``"kind"``, ``"illumination"``, per-frame statistics and
  timing. It is written as a padded placeholder with ``"status": "incomplete"`` before the
  frames and overwritten once the last frame is written (the completion marker).

Reading::

    import tifffile
    data = tifffile.imread("cube.corrected.tif", series=0)     # (N, H, W) float32
    dq = tifffile.imread("cube.corrected.tif", series=1)       # (N, H, W) uint32
    alpha = tifffile.imread("cube.corrected.tif", series=2)    # (N, H, W) float32

    from hsiffc.io.corrected import read_corrected
    cube = read_corrected("cube.corrected.tif")                # .data .dq .alpha .provenance

This module holds the whole layout: its names and numbers (:data:`FORMAT`,
:data:`FORMAT_VERSION`, :data:`PLANES`, :data:`SUFFIX`), the reader (:func:`read_corrected`,
:func:`iter_corrected`, :func:`read_provenance`) and the writers (:class:`CorrectedWriter`,
:class:`BackgroundWriter`).
"""

from __future__ import annotations

import json
import os
import queue
import stat
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from ..data.dq import TABLE_VERSION as DQ_TABLE_VERSION, table as dq_table
from ..errors import DataFormatError, ParameterError
from ..files.limits import default_limits
from ..files.jsonsafe import json_safe
from ..files.parsers import load_json
from .tiff import TiffLog

__all__ = ["FORMAT", "FORMAT_VERSION", "PLANES", "PLANE_DTYPES", "SUFFIX", "BackgroundWriter",
           "Corrected", "CorrectedWriter", "is_corrected_file", "iter_corrected", "read_corrected",
           "read_provenance"]


# --- The layout's names and numbers -----------------------------------------------------------

FORMAT = "hsiffc-corrected"
#: 1: mosaic frames (H, W), three pages per frame. 2: also cubes (H, W, B) (one page per plane
#: and frame, the bands as samples), files without alpha pages and compressed pages.
FORMAT_VERSION = 2
PLANES = ("data", "dq", "alpha")
PLANE_DTYPES = {"data": np.float32, "dq": np.uint32, "alpha": np.float32}
#: name of an output: ``<input stem>.corrected.tif``
SUFFIX = ".corrected.tif"


# --- Reading ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Corrected:
    """A corrected cube read back (:func:`read_corrected`).

    Parameters
    ----------
    data : ndarray of float32, (N, H, W) or (N, H, W, B)
        Corrected values (DN as the pipeline produced them); cubes when the pipeline's last
        step reconstructs (band order and wavelengths in ``provenance["cube"]``).
    dq : ndarray of uint32, same shape
        DQ bits (their names and values: ``provenance["dq_bits"]``).
    alpha : ndarray of float32, same shape, percent
        Leakage percentage (NaN where the pipeline computed none).
    provenance : dict
        The file's provenance JSON.
    """

    data: np.ndarray
    dq: np.ndarray
    alpha: np.ndarray
    provenance: dict

    @property
    def n_frames(self) -> int:
        """Number of frames read."""
        return int(self.data.shape[0])

    @property
    def exposure_ms(self) -> np.ndarray:
        """(N,) exposure of every frame read, in ms (from the provenance)."""
        return np.asarray(self.provenance.get("exposure", []), np.float64)


def _open_checked(tf, path: Path) -> dict:
    """The provenance of an open corrected file, after checking it is complete."""
    pages = tf.pages
    if len(pages) == 0:
        raise DataFormatError("the TIFF holds no page; not an hsiffc corrected file", path=path)
    text = (pages[0].description or "").strip()
    try:
        doc = load_json(text, path=path, what="description") if text.startswith("{") else None
    except DataFormatError:
        doc = None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise DataFormatError(f'not an hsiffc corrected file (no "format": "{FORMAT}" in the '
                              "first page's description); it was not written by hsiffc correct",
                              path=path)
    version = doc.get("format_version")
    if not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise DataFormatError(f"corrected-file format_version {version!r} is not supported (this "
                              f"hsiffc reads up to {FORMAT_VERSION}); upgrade hsiffc", path=path)
    if doc.get("status") != "complete":
        raise DataFormatError("the file is marked incomplete (it was not finished); run "
                              "hsiffc correct again to redo it", path=path)
    n = doc.get("n_frames")
    per = doc.get("pages_per_frame", len(PLANES))
    if not isinstance(n, int) or len(pages) != n * per:
        raise DataFormatError(f"the file has {len(pages)} pages but its provenance declares "
                              f"{n} frames x {per} planes; it is truncated or damaged: redo it "
                              "(hsiffc correct --overwrite)", path=path)
    last = pages[len(pages) - 1]
    size = os.path.getsize(path)
    end = max((int(o) + int(c) for o, c in zip(last.dataoffsets, last.databytecounts)),
              default=0)
    if end > size:
        raise DataFormatError(f"the file is truncated (its last page needs {end} bytes, the file "
                              f"has {size}); redo it (hsiffc correct --overwrite)", path=path)
    return doc


def _open(path) -> tifffile.TiffFile:
    from ..files.atomic import require_regular_input

    path = Path(path)
    require_regular_input(path, what="corrected file")  # a FIFO is never opened
    try:
        return tifffile.TiffFile(path)
    except Exception as exc:  # tifffile raises many types on broken files
        raise DataFormatError(f"not a readable TIFF ({type(exc).__name__}: {exc})",
                              path=path) from exc


def is_corrected_file(path) -> bool:
    """Whether ``path`` is a TIFF written by ``hsiffc correct`` (complete or not): its first
    page's description declares ``"format": "hsiffc-corrected"``. Reads the header only.

    Parameters
    ----------
    path : str or Path
        Any file.

    Returns
    -------
    bool
    """
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block the probe
            return False
    except OSError:
        return False
    try:  # tifffile logs what it finds wrong with a file; a probe keeps that quiet
        with TiffLog(), tifffile.TiffFile(path) as tf:
            text = (tf.pages[0].description or "") if len(tf.pages) else ""
    except Exception:  # not a TIFF at all, or unreadable
        return False
    return f'"format": "{FORMAT}"' in text[:200]


def read_provenance(path) -> dict:
    """The provenance JSON of a corrected file, after checking that it is complete.

    Parameters
    ----------
    path : str or Path
        A file written by ``hsiffc correct``.

    Returns
    -------
    dict
        The provenance document (pipeline, calibration identity, inputs, frames).

    Raises
    ------
    DataFormatError
        Not a corrected file, unsupported version, marked incomplete, or fewer pages or bytes
        than the provenance declares.
    """
    with _open(path) as tf:
        return _open_checked(tf, Path(path))


def iter_corrected(path):
    """Yield ``(k, data, dq, alpha)`` for every frame, one frame in memory at a time.

    Parameters
    ----------
    path : str or Path
        A complete corrected file.

    Yields
    ------
    k : int
        Frame index.
    data : ndarray of float32, (H, W)
    dq : ndarray of uint32, (H, W)
    alpha : ndarray of float32, (H, W), percent
    """
    path = Path(path)
    with _open(path) as tf:
        doc = _open_checked(tf, path)
        per = doc.get("pages_per_frame", len(PLANES))
        shape = tuple(doc["frame_shape"])
        for k in range(doc["n_frames"]):
            data, dq = (tf.pages[per * k + j].asarray().reshape(shape) for j in range(2))
            alpha = (tf.pages[per * k + 2].asarray().reshape(shape) if per > 2
                     else np.full(shape, np.nan, np.float32))
            yield k, data, dq, alpha


def read_corrected(path, frames=None) -> Corrected:
    """Read a corrected file written by ``hsiffc correct``.

    Parameters
    ----------
    path : str or Path
    frames : int, slice or sequence of int, optional
        Which frames to read (default: all).

    Returns
    -------
    Corrected
        ``data``, ``dq``, ``alpha`` as (N, H, W) arrays and ``provenance`` (dict).

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> from hsiffc.io import read_corrected
    >>> from hsiffc.io.corrected import CorrectedWriter
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frames.corrected.tif"
    >>> writer = CorrectedWriter(path, {"source": "example"}, n_frames=2, frame_shape=(4, 6))
    >>> for k in range(2):
    ...     writer.write(np.full((4, 6), 10.0 * k, np.float32), np.zeros((4, 6), np.uint32))
    >>> _ = writer.finish()
    >>> cube = read_corrected(path)
    >>> cube.data.shape, cube.dq.dtype.name, float(cube.data[1, 0, 0]), cube.provenance["status"]
    ((2, 4, 6), 'uint32', 10.0, 'complete')
    >>> tmp.cleanup()
    """
    path = Path(path)
    with _open(path) as tf:
        doc = _open_checked(tf, path)
        per = doc.get("pages_per_frame", len(PLANES))
        n = doc["n_frames"]
        index = np.arange(n)
        if frames is not None:
            try:
                index = np.atleast_1d(index[frames])
            except IndexError:
                raise ParameterError(f"frames {frames!r} out of range: the file holds {n} "
                                     f"frames (0..{n - 1})") from None
        shape = tuple(doc["frame_shape"])
        limits = default_limits()  # the header's sizes, before any plane is allocated
        limits.check_frames(path=path, n_frames=max(len(index), 1), shape=shape, itemsize=4)
        limits.check_bytes(path=path, nbytes=len(index) * 12 * int(np.prod(shape)),
                           what=f"{len(index)} frames of data, DQ and alpha planes")
        out = [np.empty((len(index),) + shape, PLANE_DTYPES[p]) for p in PLANES]
        for i, k in enumerate(index):
            for j in range(min(per, 3)):
                out[j][i] = tf.pages[per * int(k) + j].asarray().reshape(shape)
        if per < 3:  # a cube file without alpha pages
            out[2].fill(np.nan)
    return Corrected(out[0], out[1], out[2], doc)


# --- Writing ----------------------------------------------------------------------------------

_PAD_PER_FRAME = 256  # bytes reserved in the placeholder for each frame's statistics
_PAD_FIXED = 4096
_BIGTIFF_ABOVE = 2 ** 32 - 2 ** 26  # classic TIFF offsets are 32-bit
_SYNC_BYTES = 1 << 25  # BackgroundWriter starts the disk's write-back every 32 MiB


def _dumps(doc: dict) -> str:
    return json.dumps(json_safe(doc), allow_nan=False, ensure_ascii=True, sort_keys=False)


class CorrectedWriter:
    """Write corrected frames or cubes page by page (one page per plane and frame) to ``path``.

    ``path`` is normally the temporary file of :func:`hsiffc.files.atomic.atomic_path`; this class
    does not rename anything. Call :meth:`write` once per frame, then :meth:`finish` with the
    final provenance (it replaces the placeholder description and sets ``"status":
    "complete"``). Memory: one frame at a time (plus one NaN plane when alpha is missing).

    Parameters
    ----------
    path : str or Path
        File to write (normally a temporary file).
    document : dict
        Provenance fields written now (the file is marked incomplete until :meth:`finish`).
    n_frames : int
        Frames that will be written (>= 1).
    frame_shape : (int, int) or (int, int, int)
        (H, W) of every plane (mosaic frames), or (H, W, B) (cubes: one page per plane, the
        B bands as samples of each pixel, as the pipeline's cube holds them in memory).
    reserve_per_frame : int
        Bytes reserved in the description per frame for the final provenance.
    alpha : bool
        Write alpha pages (a NaN plane where a frame has none). Cubes without alpha leave
        them out (``"planes": ["data", "dq"]``); mosaic files always hold them (format 1).
    compression : str or dict, optional
        TIFF compression of every page (``"zlib"``, ``"zstd"``, ``"lzma"``: imagecodecs), or
        per plane (``{"dq": "zstd"}``: the DQ pages only; a plane not named is not
        compressed). Recorded as given in the provenance's ``"compression"``.
    """

    def __init__(self, path, document: dict, *, n_frames: int, frame_shape,
                 reserve_per_frame: int = _PAD_PER_FRAME, alpha: bool = True,
                 compression: str | dict | None = None):
        self.path = Path(path)
        self.n_frames = int(n_frames)
        self.frame_shape = tuple(int(s) for s in frame_shape)
        if len(self.frame_shape) not in (2, 3) or min(self.frame_shape) < 1:
            raise ValueError(f"frames must be (H, W) or cubes (H, W, B), got {self.frame_shape}")
        if self.n_frames < 1:
            raise ValueError("a corrected file holds at least one frame")
        self.planes = PLANES if (alpha or len(self.frame_shape) == 2) else PLANES[:2]
        self.compression = compression
        h = self.frame_shape[0]
        self._doc = self._base(document)
        placeholder = _dumps({**self._doc, "status": "incomplete"})
        self._description = placeholder + " " * (_PAD_FIXED + int(reserve_per_frame) * self.n_frames)
        volume = self.n_frames * int(np.prod(self.frame_shape)) * 4 * len(self.planes) + \
            len(self._description)
        self._tw = tifffile.TiffWriter(self.path, bigtiff=volume > _BIGTIFF_ABOVE)
        self._alpha_rows = max(1, (h + 1) // 2) if h > 1 else 1  # tells alpha from data pages
        self._nan = None
        self._mark = self._last = 0  # byte ranges handed to the disk by sync()
        self.written = 0
        self._closed = False

    def _base(self, document: dict) -> dict:
        v1 = len(self.frame_shape) == 2 and self.compression is None
        return {"format": FORMAT, "format_version": 1 if v1 else FORMAT_VERSION,
                "status": "incomplete", "planes": list(self.planes),
                "plane_dtypes": [np.dtype(PLANE_DTYPES[p]).name for p in self.planes],
                "n_frames": self.n_frames, "frame_shape": list(self.frame_shape),
                "pages_per_frame": len(self.planes), "compression": self.compression,
                "dq_bits": dq_table(), "dq_table_version": DQ_TABLE_VERSION, **document}

    def write(self, data, dq, alpha=None) -> None:
        """Append frame ``written``: its corrected data, DQ plane and alpha (or None).

        Parameters
        ----------
        data : (H, W) array_like
            Corrected values (stored as float32, in the unit of the pipeline's output, DN).
        dq : (H, W) array_like
            DQ bits (stored as uint32).
        alpha : (H, W) array_like, optional
            Leakage percentage (stored as float32; NaN plane when None).

        Raises
        ------
        ValueError
            The writer is finished, all frames are written, or a plane has another shape.
        """
        if self._closed:
            raise ValueError("the writer is finished")
        if self.written >= self.n_frames:
            raise ValueError(f"all {self.n_frames} frames are already written")
        planes = []
        for name, arr in (("data", data), ("dq", dq), ("alpha", alpha))[:len(self.planes)]:
            if arr is None:
                if self._nan is None:
                    self._nan = np.full(self.frame_shape, np.nan, np.float32)
                arr = self._nan
            arr = np.ascontiguousarray(arr, dtype=PLANE_DTYPES[name])
            if arr.shape != self.frame_shape:
                raise ValueError(f"{name} of frame {self.written} has shape {arr.shape}; this file "
                                 f"holds frames of shape {self.frame_shape}")
            planes.append(arr)
        h = self.frame_shape[0]
        first = self.written == 0
        # uncompressed: one strip per page (the fastest to write and read); compressed:
        # strips of about 1 MiB, so tifffile compresses them on several threads
        codecs = [self._codec(name) for name in self.planes]
        row_bytes = int(np.prod(self.frame_shape[1:])) * 4
        strip = max(1, min(h, (1 << 20) // max(row_bytes, 1)))
        rows = [(h if k < 2 else self._alpha_rows) if codec is None else
                (max(1, strip - 1) if k == 2 and strip > 1 else strip)
                for k, codec in enumerate(codecs)]
        options = {"photometric": "minisblack", "metadata": None}
        if len(self.frame_shape) == 3 and self.frame_shape[2] > 1:  # the bands as samples of
            options["planarconfig"] = "contig"  # each pixel, as in memory
        elif len(self.frame_shape) == 3:  # one band: tifffile refuses an (H, W, 1) page; the
            planes = [p.reshape(self.frame_shape[:2]) for p in planes]  # (H, W) page is read
            # back with the frame_shape (H, W, 1) of the provenance
        for k, plane in enumerate(planes):
            self._tw.write(plane, rowsperstrip=rows[k], compression=codecs[k],
                           description=self._description if first and k == 0 else None,
                           **options)
        self.written += 1

    def _codec(self, plane: str):
        """The compression of ``plane``'s pages (None: none)."""
        if isinstance(self.compression, dict):
            return self.compression.get(plane)
        return self.compression

    def sync(self) -> None:
        """Start writing what is written so far to the disk, without waiting for it.

        On Linux, ``posix_fadvise(DONTNEED)`` starts the write-back of the new part and drops
        the part written back before it from the page cache: the disk works while the next
        frames are corrected, the final ``fsync`` has little left to do, and a large batch
        does not fill the page cache with its outputs. Elsewhere it does nothing.
        """
        if not hasattr(os, "posix_fadvise"):
            return
        fh = self._tw.filehandle
        fh.flush()
        end = fh.tell()
        if end > self._mark:
            os.posix_fadvise(fh.fileno(), self._mark, end - self._mark, os.POSIX_FADV_DONTNEED)
        self._mark, self._last = self._last, end

    def finish(self, document: dict | None = None) -> dict:
        """Close the file and write the final provenance with ``"status": "complete"``.

        Parameters
        ----------
        document : dict, optional
            Provenance fields to add or replace (JSON-able).

        Returns
        -------
        dict
            The provenance document written into the file.
        """
        if self.written != self.n_frames:
            raise ValueError(f"only {self.written} of {self.n_frames} frames were written")
        self.close()
        final = {**self._doc, **(document or {}), "status": "complete"}
        text = _dumps(final)
        with tifffile.TiffFile(self.path, mode="r+b") as tf:
            tf.pages[0].tags["ImageDescription"].overwrite(text)
        return final

    def close(self) -> None:
        """Close the file without finishing it (it stays marked incomplete)."""
        if not self._closed:
            self._closed = True
            self._tw.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class BackgroundWriter:
    """Runs :meth:`CorrectedWriter.write` on one thread while the caller corrects the next frame.

    At most ``depth`` frames wait in the queue (memory stays at a few frames); every
    ``sync_bytes`` written it calls :meth:`CorrectedWriter.sync`. An error in the thread is
    raised in the caller at the next :meth:`write` or at :meth:`close`.

    Parameters
    ----------
    writer : CorrectedWriter
        The writer that writes the frames.
    depth : int
        Frames that may wait in the queue.
    sync_bytes : int
        Bytes written between two calls of :meth:`CorrectedWriter.sync`.
    """

    def __init__(self, writer: CorrectedWriter, depth: int = 1, sync_bytes: int = _SYNC_BYTES):
        self._writer = writer
        self._sync_bytes = sync_bytes
        self._pending = 0
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._cancelled = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while (item := self._queue.get()) is not None:
            if self._error is None and not self._cancelled:
                try:
                    self._writer.write(*item)
                    self._pending += sum(a.nbytes for a in item if a is not None)
                    if self._sync_bytes and self._pending >= self._sync_bytes:
                        self._writer.sync()
                        self._pending = 0
                except BaseException as exc:  # raised again in the caller's thread
                    self._error = exc

    def write(self, data, dq, alpha=None) -> None:
        """Queue one frame for :meth:`CorrectedWriter.write` (blocks while ``depth`` frames
        wait; raises an error of the writing thread).

        Parameters
        ----------
        data, dq, alpha : (H, W) arrays
            As for :meth:`CorrectedWriter.write` (not copied: do not modify them afterwards).
        """
        if self._error is not None:
            raise self._error
        self._queue.put((data, dq, alpha))

    def close(self, *, cancel: bool = False) -> None:
        """Wait until every queued frame is written (``cancel``: drop them).

        Parameters
        ----------
        cancel : bool
            Drop the queued frames instead of writing them (after an error).
        """
        self._cancelled = self._cancelled or cancel
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        if self._error is not None and not cancel:
            raise self._error
