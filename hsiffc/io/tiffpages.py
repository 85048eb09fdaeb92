"""TIFF files as frame stacks: hsiffc TIFFs and plain single- or multi-page TIFFs.

One page is one frame. The header (every page's IFD) is parsed once and checked before any
pixel is decoded:

* size: frame size, frame count and bytes against :class:`~hsiffc.files.limits.ReadLimits`;
* codec: a compression this Python cannot decode is named, with the package that provides it
  (``imagecodecs``), instead of a vague "cannot read";
* structure: every page's IFD and strips must lie inside the file, the last page must not point
  to a further page beyond the end of the file, and a frame count the file declares (hsiffc
  ``n_frames``, tifffile's ``{"shape": [...]}`` description, ImageJ ``images=``) must match the
  pages found. A multi-page TIFF cut short is reported as truncated, never read as fewer frames.

Metadata found in the file (plain TIFFs): ``exposure_ms`` from the EXIF ``ExposureTime`` tag
(seconds, in the EXIF IFD or the image IFD) or from Micro-Manager's per-page JSON
(``"Exposure-ms"``, tag 51123); ``bit_depth`` from ``BitsPerSample`` when it is not a whole
byte (10, 12, 14 bits). hsiffc TIFFs carry everything in their JSON document
(:mod:`hsiffc.io.document`).
"""

from __future__ import annotations

import logging
import re
import struct
from pathlib import Path

import numpy as np
import tifffile

from ..errors import DataFormatError
from .document import document_fields, is_hsiffc_document, parse_document
from .layout import FileLayout
from ..files.limits import ReadLimits
from ..files.parsers import load_json

__all__ = ["open_tiff", "TIFF_SUFFIXES", "CORRECTED_MARK"]

TIFF_SUFFIXES = (".tif", ".tiff")
#: Text in the first page's description of an output of ``hsiffc correct``.
CORRECTED_MARK = "hsiffc-corrected"
_IMAGEJ_IMAGES = re.compile(r"^images=(\d+)", re.MULTILINE)


class TiffLog(logging.Filter):
    """Swallow tifffile's log records while reading, keeping their text for error messages."""

    def __init__(self):
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record):
        self.messages.append(record.getMessage())
        return False

    def __enter__(self):
        logging.getLogger("tifffile").addFilter(self)
        return self

    def __exit__(self, *exc):
        logging.getLogger("tifffile").removeFilter(self)


def _unreadable(path, exc, log) -> DataFormatError:
    extra = f" ({'; '.join(log.messages[:3])})" if log.messages else ""
    return DataFormatError(
        f"not a readable TIFF file ({type(exc).__name__}: {exc}){extra}; the file may be "
        "truncated or not a TIFF - check it opens in an image viewer or write it again",
        path=path)


def ifd_ends(tf, page) -> tuple[int, int]:
    """(end of the page's IFD and tag values, next-IFD offset) as the file declares them."""
    fmt = tf.tiff
    fh = tf.filehandle
    fh.seek(page.offset)
    raw = fh.read(fmt.tagnosize)
    if len(raw) < fmt.tagnosize:
        return page.offset + fmt.tagnosize, 0
    ntags = struct.unpack(fmt.tagnoformat, raw)[0]
    next_at = page.offset + fmt.tagnosize + ntags * fmt.tagsize
    end = next_at + fmt.offsetsize
    fh.seek(next_at)
    raw = fh.read(fmt.offsetsize)
    following = struct.unpack(fmt.offsetformat, raw)[0] if len(raw) == fmt.offsetsize else -1
    for tag in page.tags.values():
        if tag.valuebytecount > fmt.tagoffsetthreshold:
            end = max(end, tag.valueoffset + tag.valuebytecount)
    return end, following


def _declared_frames(description: str, page_shape: tuple) -> int | None:
    """Frame count the file states besides its page chain (tifffile shape, ImageJ)."""
    text = description.strip()
    if text.startswith("{") and '"shape"' in text[:200]:
        try:
            shape = load_json(text, what="description").get("shape")
        except (DataFormatError, AttributeError):
            return None
        nd = len(page_shape)
        if (isinstance(shape, list) and all(isinstance(s, int) for s in shape)
                and len(shape) >= nd and tuple(shape[len(shape) - nd:]) == tuple(page_shape)):
            n = 1
            for s in shape[:len(shape) - nd]:
                n *= s
            return n
    match = _IMAGEJ_IMAGES.search(text) if text.startswith("ImageJ") else None
    return int(match.group(1)) if match else None


def _declared_total(pages, description: str) -> int | None:
    """Frames the descriptions declare over the whole page chain. tifffile writes a shape
    description on the first page of each series, so a file written frame by frame (one series
    per page, each ``{"shape": [H, W]}``) declares one frame per page: the counts of every page
    that starts a series add up. ImageJ states its count once, on the first page."""
    first = _declared_frames(description, pages[0].shape)
    if first is None or description.strip().startswith("ImageJ"):
        return first
    total = first
    for page in pages[1:]:
        text = page.description or ""
        if text.strip().startswith("{"):
            more = _declared_frames(text, page.shape)
            if more is not None:
                total += more
    return total


def _frame_shape(page) -> tuple:
    """A page's frame shape, channels last ((C, H, W) planar pages become (H, W, C))."""
    shape = tuple(int(s) for s in page.shape)
    if int(page.planarconfig) == 2 and len(shape) == 3:
        shape = shape[1:] + shape[:1]
    return shape


def _check_codec(page, path) -> None:
    compression = page.compression
    try:
        tifffile.TIFF.DECOMPRESSORS[compression]
    except (KeyError, ValueError, ImportError, NotImplementedError) as exc:
        name = getattr(compression, "name", str(compression))
        raise DataFormatError(
            f"compressed with {name} (TIFF compression {int(compression)}), which this Python "
            f"cannot decode ({exc}); install the codec package: pip install 'imagecodecs>=2023.1'"
            " (it is an hsiffc dependency)", path=path) from None


def _exposure_from_tags(page) -> tuple[float | None, str]:
    """Exposure in ms from EXIF ExposureTime or Micro-Manager JSON, and the tag's name."""
    tags = page.tags
    exif = tags.get("ExifTag")
    candidates = []
    if exif is not None and isinstance(exif.value, dict) and "ExposureTime" in exif.value:
        candidates.append((exif.value["ExposureTime"], "EXIF ExposureTime"))
    if "ExposureTime" in tags:
        candidates.append((tags["ExposureTime"].value, "TIFF tag ExposureTime (33434)"))
    for value, origin in candidates:
        if isinstance(value, tuple) and len(value) == 2 and value[1]:
            value = value[0] / value[1]
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            continue
        if np.isfinite(seconds) and seconds >= 0:
            return seconds * 1e3, origin
    mm = tags.get(51123)
    if mm is not None:
        value = mm.value
        try:
            doc = (load_json(value, what="Micro-Manager metadata")
                   if isinstance(value, (str, bytes)) else value)
            return float(doc["Exposure-ms"]), "Micro-Manager Exposure-ms (tag 51123)"
        except (DataFormatError, ValueError, KeyError, TypeError):
            pass
    return None, ""


def open_tiff(path, limits: ReadLimits) -> FileLayout:
    """Parse a TIFF's header and return its :class:`FileLayout` (no pixel decoded).

    Parameters
    ----------
    path : str or Path
        A ``.tif``/``.tiff`` file (plain or hsiffc).
    limits : ReadLimits
        Size limits checked against the header.

    Returns
    -------
    FileLayout

    Raises
    ------
    DataFormatError
        Empty, unreadable, truncated or inconsistent file; frames larger than ``limits``;
        missing codec; an output of ``hsiffc correct``; an invalid hsiffc document.
    """
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise DataFormatError("file is empty (0 bytes), probably truncated while copying or "
                              "writing; copy or write it again", path=path)
    with TiffLog() as log:
        try:
            tf = tifffile.TiffFile(path)
        except Exception as exc:  # tifffile raises many types on broken files
            raise _unreadable(path, exc, log) from exc
        try:
            layout = _layout(tf, path, size, limits, log)
        except DataFormatError:
            tf.close()
            raise
        except Exception as exc:
            tf.close()
            raise _unreadable(path, exc, log) from exc
    return layout


def _layout(tf, path: Path, size: int, limits: ReadLimits, log: TiffLog) -> FileLayout:
    tf.filehandle.lock = True  # frames may be decoded on several threads (seek + read locked)
    pages = list(tf.pages)
    if not pages:
        raise DataFormatError("the TIFF holds no image page; rewrite it", path=path)
    first = pages[0]
    description = first.description or ""
    if CORRECTED_MARK in description[:200]:
        raise DataFormatError("this is an output of hsiffc correct, not raw frames; give the raw "
                              "input (read corrected files with hsiffc.io.read_corrected)",
                              path=path)
    hsiffc_doc = parse_document(description, path) if is_hsiffc_document(description) else None
    separate = int(first.planarconfig) == 2 and len(first.shape) == 3
    shapes = sorted({_frame_shape(p) for p in pages})
    dtypes = sorted({np.dtype(p.dtype).str for p in pages})
    n = len(pages)
    # limits before anything else: nothing has been decoded so far
    limits.check_frames(path=path, n_frames=n, shape=max(shapes, key=np.prod),
                        itemsize=max(np.dtype(d).itemsize for d in dtypes))
    if len(shapes) != 1:
        raise DataFormatError(f"pages must all be images of one shape, found shapes {shapes}; "
                              "write one (H, W) frame per page", path=path)
    if len(dtypes) != 1 or np.dtype(dtypes[0]).kind not in "uif":
        raise DataFormatError(f"pages must share one integer or float dtype, found {dtypes}",
                              path=path)
    for k, page in enumerate(pages):
        end, following = ifd_ends(tf, page)
        end = max(end, max((int(o) + int(c) for o, c in
                            zip(page.dataoffsets, page.databytecounts)), default=0))
        if end > size:
            raise DataFormatError(
                f"file is truncated: page {k} needs bytes up to {end} but the file has "
                f"{size}; copy or write the file again", path=path)
        if k == n - 1 and following != 0:
            raise DataFormatError(
                f"file is truncated: after page {k} the page chain points to byte {following} "
                f"but the file has {size}; copy or write the file again", path=path)
    if any("invalid page offset" in m for m in log.messages):
        raise DataFormatError(f"file is truncated or damaged: the page chain breaks after page "
                              f"{n - 1} ({log.messages[0]}); copy or write the file again",
                              path=path)
    declared = None if hsiffc_doc is not None else _declared_total(pages, description)
    if declared is not None and declared != n:
        raise DataFormatError(
            f"the file declares {declared} frames but holds {n} pages; it is probably truncated "
            "- copy or write it again", path=path)
    _check_codec(first, path)

    state = {"tf": tf, "pages": pages}

    def read(k: int) -> np.ndarray:
        if state["tf"] is None:  # closed after an earlier pass: open again
            state["tf"] = tifffile.TiffFile(path)
            state["tf"].filehandle.lock = True
            state["pages"] = list(state["tf"].pages)
        try:
            data = state["pages"][k].asarray()
            return np.moveaxis(data, 0, -1) if separate else data
        except Exception as exc:  # a damaged strip, a codec error...
            raise DataFormatError(f"frame {k} cannot be decoded ({type(exc).__name__}: {exc}); "
                                  "copy or write the file again", path=path) from exc

    def close() -> None:
        if state["tf"] is not None:
            state["tf"].close()
            state["tf"], state["pages"] = None, []

    layout = FileLayout(path=path, format="hsiffc-tiff" if hsiffc_doc else "tiff",
                        n_frames=n, shape=shapes[0], dtype=np.dtype(dtypes[0]), read=read,
                        close=close, strict=hsiffc_doc is not None)
    if hsiffc_doc is not None:
        fields, meta = document_fields(hsiffc_doc, n, path)
        for name, value in fields.items():
            layout.give(name, value, "file (hsiffc JSON)")
        layout.meta.update(meta)
        return layout
    exposures = [_exposure_from_tags(p) for p in pages]
    if all(e is not None for e, _ in exposures):
        values = np.array([e for e, _ in exposures])
        layout.give("exposure_ms", values[0] if np.all(values == values[0]) else values,
                    f"file ({exposures[0][1]})")
    bits = int(first.bitspersample)
    if bits % 8 and bits < 32:
        layout.give("bit_depth", bits, "file (TIFF BitsPerSample)")
    if separate:
        layout.meta["channel_hint"] = (
            "; if the planes are separate frames (tifffile stores a (3, H, W) array as planar "
            "RGB unless told otherwise), write them with photometric='minisblack'")
    if description.strip():
        layout.meta["tiff_description"] = description.strip()[:2000]
    return layout
