"""The input side of a task: one TIFF opened once, its header checked, frames decoded one by one.

:func:`open_input` returns an object shaped like :class:`hsiffc.io.FrameSource` (the io
package's public streaming reader): ``n_frames``, ``frame_shape``, ``dtype``, ``bit_depth``,
``mosaic``, per-frame ``exposure_ms``/``kind``/``illumination``, and iteration over
``(raw, meta)`` pairs. Until that reader is on main this module parses hsiffc TIFF headers
itself, through helpers of :mod:`hsiffc.io.tiff`; a batch task touches nothing else of the
file format, so the switch is confined here.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from ..errors import DataFormatError
from ..io.corrected import FORMAT as CORRECTED_FORMAT
from ..io.tiff import (
    _CollectLog,
    _floats,
    _ifd_end,
    _parse_document,
    _per_frame,
    _strings,
    exposure_to_ms,
)
from ..mosaic import Mosaic
from ..sweep import FRAME_KINDS

__all__ = ["InputMeta", "open_input"]


@dataclass(frozen=True)
class InputMeta:
    """Metadata of one input frame (the fields of io's FrameMeta a batch uses)."""

    index: int
    exposure_ms: float
    kind: str
    illumination: str
    path: str


class TiffInput:
    """An open hsiffc TIFF whose header was checked (see :func:`open_input`)."""

    def __init__(self, tf, path: Path, head: dict):
        self._tf, self.path = tf, path
        self._pages = head["pages"]
        self.n_frames = head["n"]
        self.frame_shape = tuple(head["shape"])
        self.dtype = head["dtype"]
        self.bit_depth = head["bit_depth"]
        self.mosaic = head["mosaic"]
        self.exposure_ms = np.asarray(head["exposure_ms"], np.float64)
        self.kind = np.asarray(head["kind"], str)
        self.illumination = np.asarray(head["illumination"], str)

    def __iter__(self):
        bits = self.bit_depth
        for k, page in enumerate(self._pages):
            try:
                raw = page.asarray()
            except Exception as exc:  # a damaged strip, an unsupported codec...
                raise DataFormatError(f"frame {k} cannot be read ({type(exc).__name__}: {exc}); "
                                      "copy or write the file again", path=self.path) from exc
            if raw.dtype.kind in "ui" and raw.size and int(raw.max()) > 2 ** bits - 1:
                raise DataFormatError(f"frame {k}: data exceed the stated bit depth (maximum "
                                      f"{int(raw.max())} DN > {2 ** bits - 1} DN = 2**{bits}-1); "
                                      "fix 'bit_depth' in the metadata", path=self.path)
            yield raw, InputMeta(k, float(self.exposure_ms[k]), str(self.kind[k]),
                                 str(self.illumination[k]), str(self.path))

    def close(self) -> None:
        """Close the input file."""
        self._tf.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_input(path) -> TiffInput:
    """Open one input TIFF: parse and check its header (no pixel is decoded).

    Raises
    ------
    DataFormatError
        Not a readable TIFF, truncated, an output of ``hsiffc correct``, pages of different
        shapes or dtypes, or missing or invalid hsiffc metadata.
    """
    path = Path(path)
    size = path.stat().st_size
    tlog = logging.getLogger("tifffile")
    collect = _CollectLog()
    tlog.addFilter(collect)
    try:
        try:
            tf = tifffile.TiffFile(path)
        except Exception as exc:  # tifffile raises many types on broken files
            extra = f" ({'; '.join(collect.messages[:3])})" if collect.messages else ""
            raise DataFormatError(f"not a readable TIFF file ({type(exc).__name__}: {exc}){extra}; "
                                  "the file may be truncated or not a TIFF", path=path) from exc
        try:
            return TiffInput(tf, path, _read_header(tf, path, size))
        except BaseException:
            tf.close()
            raise
    finally:
        tlog.removeFilter(collect)


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

