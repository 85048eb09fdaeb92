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

This module reads the layout back; :mod:`hsiffc.io.corrected_writer` writes it
(:class:`CorrectedWriter`, :class:`BackgroundWriter`, both importable from here) and
:mod:`hsiffc.io.corrected_format` holds the constants both use.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from ..errors import DataFormatError
from .corrected_format import FORMAT, FORMAT_VERSION, PLANE_DTYPES, PLANES, SUFFIX
from .corrected_writer import BackgroundWriter, CorrectedWriter
from ..files.parsers import load_json
from .tiffpages import TiffLog

__all__ = ["FORMAT", "FORMAT_VERSION", "PLANES", "SUFFIX", "BackgroundWriter", "Corrected",
           "CorrectedWriter", "is_corrected_file", "iter_corrected", "read_corrected",
           "read_provenance"]


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
    path = Path(path)
    if not path.is_file():
        raise DataFormatError("corrected file not found", path=path)
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
    """
    path = Path(path)
    with _open(path) as tf:
        doc = _open_checked(tf, path)
        per = doc.get("pages_per_frame", len(PLANES))
        index = np.arange(doc["n_frames"])
        if frames is not None:
            index = np.atleast_1d(index[frames])
        shape = tuple(doc["frame_shape"])
        out = [np.empty((len(index),) + shape, PLANE_DTYPES[p]) for p in PLANES]
        for i, k in enumerate(index):
            for j in range(min(per, 3)):
                out[j][i] = tf.pages[per * int(k) + j].asarray().reshape(shape)
        if per < 3:  # a cube file without alpha pages
            out[2].fill(np.nan)
    return Corrected(out[0], out[1], out[2], doc)
