"""Writing a corrected cube: :class:`CorrectedWriter` and :class:`BackgroundWriter`.

The file layout (three pages per frame, the provenance JSON written as an incomplete
placeholder first and completed at the end) is described in :mod:`hsiffc.io.corrected`, which
reads it back and re-exports both writers.
"""

from __future__ import annotations

import json
import os
import queue
import threading
from pathlib import Path

import numpy as np
import tifffile

from ..data.dq import TABLE_VERSION as DQ_TABLE_VERSION
from ..data.dq import table as dq_table
from ..files.jsonsafe import json_safe
from .corrected_format import FORMAT, FORMAT_VERSION, PLANE_DTYPES, PLANES

__all__ = ["BackgroundWriter", "CorrectedWriter"]

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
    compression : str, optional
        TIFF compression of every page (``"zlib"``, ``"zstd"``, ``"lzma"``: imagecodecs).
    """

    def __init__(self, path, document: dict, *, n_frames: int, frame_shape,
                 reserve_per_frame: int = _PAD_PER_FRAME, alpha: bool = True,
                 compression: str | None = None):
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
        if self.compression is None:
            rows = [h, h, self._alpha_rows]
        else:
            row_bytes = int(np.prod(self.frame_shape[1:])) * 4
            strip = max(1, min(h, (1 << 20) // max(row_bytes, 1)))
            rows = [strip, strip, max(1, strip - 1) if strip > 1 else strip]
        options = {"photometric": "minisblack", "metadata": None,
                   "compression": self.compression}
        if len(self.frame_shape) == 3:  # the bands as samples of each pixel, as in memory
            options["planarconfig"] = "contig"
        for k, plane in enumerate(planes):
            self._tw.write(plane, rowsperstrip=rows[k],
                           description=self._description if first and k == 0 else None,
                           **options)
        self.written += 1

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
