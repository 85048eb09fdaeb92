"""TIFF: hsiffc's TIFF format (a stack of raw frames, one TIFF page per frame, plus one JSON
document) and plain single- or multi-page TIFFs read as frame stacks.

File layout
-----------
* Page ``k`` holds frame ``k`` of the sweep as a single-channel (H, W) image, in acquisition
  order, in the frames' own dtype (``uint8`` / ``uint16`` raw DN, or ``float32`` for averaged or
  processed frames; ``uint32``, signed ``int8``/``int16``/``int32`` and ``float64`` are also
  written as they are, e.g. by ``hsiffc import`` of a signed camera file). Values are never
  rescaled, clipped or wrapped, neither on writing nor on reading.
* The ImageDescription tag of the first page holds one JSON object (the *document*)::

      {"format": "hsiffc", "format_version": 1, "content": "frames", "n_frames": 200,
       "exposure_unit": "ms", "exposure": [0.04, 0.04, ...],        # one per frame, or one number
       "kind": ["light", ...],                                      # or "light" / "dark"
       "illumination": ["2900K", ...],                              # or one string; "" = unknown
       "photons": [18.25, ..., null] or null,                       # photons per pixel per frame
       "step": [0, 0, 1, 1, ...] or null,                           # acquisition step per frame
       "bit_depth": 10,                                             # ADC bits; full scale 2**b-1
       "mosaic": {"pattern": [[0, 1], [2, 3]], "wavelengths_nm": [...], "offset": [0, 0]} or null,
       "wavelengths_nm": [...] or null,                             # band centres in nm
       "source": "...", "meta": {...}}

  Required on reading: ``format`` (= "hsiffc"), ``exposure``, ``exposure_unit`` (one of "s",
  "ms", "us", "ns"; converted to milliseconds) and ``bit_depth``. ``kind`` defaults to "light",
  ``illumination`` to "", ``photons`` to unknown (NaN), ``step`` to "consecutive frames with the
  same settings share a step". ``n_frames`` (written by hsiffc, optional by hand) lets the reader
  detect a truncated file.

Floating-point frames may contain NaN or inf: that is not an error when reading (the values are
kept as they are); the data-quality stage flags such pixels later.

Reading any TIFF (:func:`open_tiff`)
------------------------------------
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
byte (10, 12, 14 bits). hsiffc TIFFs carry everything in their JSON document (above).

The JSON document is checked by :func:`parse_document` (one error per problem naming the file,
the key and the fix) and turned into the metadata fields of a frame source by
:func:`document_fields` (exposure in milliseconds, kinds, bit depth, mosaic, ...).

The examples of :func:`write_sweep` and :func:`read_sweep_tiff` write and read such files.
"""

from __future__ import annotations

import json
import logging
import re
import struct
from pathlib import Path

import numpy as np
import tifffile

from ..data.mosaic import Mosaic
from ..data.sweep import FRAME_KINDS, Sweep
from ..errors import DataFormatError
from ..files.atomic import atomic_path
from ..files.jsonsafe import json_safe
from ..files.limits import ReadLimits, default_limits
from ..files.parsers import load_json
from ._layout import FileLayout

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "EXPOSURE_UNITS_MS", "MINIMAL_DOCUMENT",
           "exposure_to_ms", "parse_document", "document_fields", "is_hsiffc_document",
           "write_sweep", "read_sweep_tiff", "TIFF_SUFFIXES", "WRITABLE_DTYPES", "open_tiff",
           "CORRECTED_MARK"]


# --- The JSON document of an hsiffc TIFF ------------------------------------------------------

FORMAT_NAME = "hsiffc"
FORMAT_VERSION = 1
#: Milliseconds per unit, for every exposure unit hsiffc accepts in files.
EXPOSURE_UNITS_MS = {"s": 1e3, "ms": 1.0, "us": 1e-3, "ns": 1e-6}
MINIMAL_DOCUMENT = ('{"format": "hsiffc", "exposure": 10.0, "exposure_unit": "ms", '
                    '"bit_depth": 12, "kind": "light"}')
_KNOWN = {"format", "format_version", "content", "n_frames", "exposure_unit", "exposure",
          "kind", "illumination", "photons", "step", "bit_depth", "mosaic", "wavelengths_nm",
          "source", "meta"}


def exposure_to_ms(values, unit: str, *, path=None, what: str = "exposure_unit") -> np.ndarray:
    """Convert exposure times given in ``unit`` ("s", "ms", "us" or "ns") to milliseconds.

    Parameters
    ----------
    values : array_like
        Exposure times in ``unit``.
    unit : {"s", "ms", "us", "ns"}
        Their unit.
    path : str or Path, optional
        File they came from (for the message).
    what : str
        Name of the unit field (for the message).

    Returns
    -------
    ndarray of float64, ms

    Raises
    ------
    DataFormatError
        Unknown unit.

    Examples
    --------
    >>> exposure_to_ms([1500.0, 250.0], "us").tolist()
    [1.5, 0.25]
    """
    if unit not in EXPOSURE_UNITS_MS:
        raise DataFormatError(
            f"unknown {what} {unit!r}; use one of {sorted(EXPOSURE_UNITS_MS)} "
            "(seconds, milliseconds, microseconds, nanoseconds)", path=path)
    return np.asarray(values, dtype=np.float64) * EXPOSURE_UNITS_MS[unit]


def is_hsiffc_document(description: str) -> bool:
    """True when a TIFF description looks like an hsiffc JSON document (cheap test).

    Parameters
    ----------
    description : str
        ImageDescription of the first page.

    Returns
    -------
    bool
    """
    text = description.lstrip()[:400]
    return text.startswith("{") and '"format"' in text and f'"{FORMAT_NAME}"' in text


def parse_document(description: str, path) -> dict:
    """The hsiffc JSON document in ``description``, checked (format, version, content).

    Parameters
    ----------
    description : str
        ImageDescription of the first page.
    path : str or Path
        The file (for the messages).

    Returns
    -------
    dict
        The parsed document.

    Raises
    ------
    DataFormatError
        Not JSON, another format or version, or invalid content (with the fix).
    """
    hint = ("add a JSON document to the ImageDescription of the first page, at least "
            f"{MINIMAL_DOCUMENT} (see 'The hsiffc TIFF format' in docs/reference/formats.md), "
            "or write the file with hsiffc.io.write_sweep")
    text = description.strip()
    if not text.startswith("{"):
        raise DataFormatError(f"plain TIFF without hsiffc metadata; {hint}", path=path)
    doc = load_json(text, path=path, what="ImageDescription", hint=hint)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise DataFormatError('plain TIFF without hsiffc metadata (its ImageDescription JSON '
                              f'lacks "format": "hsiffc"); {hint}', path=path)
    version = doc.get("format_version", FORMAT_VERSION)
    if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
        raise DataFormatError(
            f"format_version {version!r} is not supported (this hsiffc reads up to "
            f"{FORMAT_VERSION}); upgrade hsiffc or write format_version {FORMAT_VERSION}", path=path)
    content = doc.get("content", "frames")
    if content != "frames":
        raise DataFormatError(f'the file holds "content": {content!r}, not raw frames; read it '
                              'with the matching hsiffc reader or set "content": "frames"',
                              path=path)
    return doc


def per_frame_field(doc, key, n, path, convert, default=None, *, required=False):
    """A per-frame field: a list of n values or one value for all frames."""
    if key not in doc or doc[key] is None:
        if required:
            raise DataFormatError(
                f"the hsiffc metadata has no {key!r}; add it to the JSON in the first page's "
                f"ImageDescription, e.g. {MINIMAL_DOCUMENT}", path=path)
        return default
    value = doc[key]
    if isinstance(value, list) and len(value) != n:
        raise DataFormatError(
            f"{key!r} has {len(value)} entries but the file has {n} pages (frames); give one "
            f"entry per page or a single value for all (a shorter page count may mean a "
            "truncated file)", path=path)
    try:
        return convert(value)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{key!r} = {value!r} is not valid ({exc}); see 'The hsiffc TIFF "
                              "format' in docs/reference/formats.md", path=path) from exc


def as_floats(value):
    if isinstance(value, list):
        return np.array([np.nan if v is None else float(v) for v in value], dtype=np.float64)
    return np.float64(np.nan if value is None else float(value))


def as_strings(value):
    values = value if isinstance(value, list) else [value]
    if not all(isinstance(v, str) for v in values):
        raise TypeError("expected text")
    return np.array(values, dtype=object) if isinstance(value, list) else value


def as_ints(value):
    values = value if isinstance(value, list) else [value]
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise TypeError("expected whole numbers")
    return np.asarray(value, dtype=np.int64)


def _mosaic(doc, path):
    wavelengths = doc.get("wavelengths_nm")
    if doc.get("mosaic") is None:
        return None
    try:
        md = dict(doc["mosaic"])
        if md.get("wavelengths_nm") is None and wavelengths is not None:
            md["wavelengths_nm"] = wavelengths
        mosaic = Mosaic.from_dict(md)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"invalid 'mosaic' ({exc}); fix the JSON", path=path) from exc
    if (wavelengths is not None and mosaic.wavelengths_nm is not None
            and not np.allclose(wavelengths, mosaic.wavelengths_nm)):
        raise DataFormatError("'wavelengths_nm' and 'mosaic.wavelengths_nm' differ; keep one "
                              "of them", path=path)
    return mosaic


def document_fields(doc: dict, n: int, path) -> tuple[dict, dict]:
    """Metadata fields and extra ``meta`` of an hsiffc document for a file of ``n`` pages.

    Parameters
    ----------
    doc : dict
        From :func:`parse_document`.
    n : int
        Number of pages (frames) of the file.
    path : str or Path
        The file (for the messages).

    Returns
    -------
    fields : dict
        ``exposure_ms`` (float or (n,) float, milliseconds), ``kind``, ``illumination``,
        ``photons``, ``step`` (each a scalar or an (n,) array; absent when not in the file),
        ``bit_depth`` (int) and ``mosaic`` (Mosaic or None).
    meta : dict
        The document's ``meta`` plus ``wavelengths_nm`` (without a mosaic),
        ``source_in_file`` and ``extra_fields`` (unknown top-level keys).

    Raises
    ------
    DataFormatError
        A missing ``exposure``/``exposure_unit``/``bit_depth``, a declared frame count that
        differs from ``n``, or a value of the wrong type or range.
    """
    declared = doc.get("n_frames")
    if declared is not None and declared != n:
        raise DataFormatError(
            f"the metadata declares {declared} frames but only {n} pages could be read; the file "
            "is probably truncated - copy or write it again", path=path)
    if "exposure" not in doc or doc["exposure"] is None:
        raise DataFormatError(
            "the hsiffc metadata has no 'exposure'; add the exposure time of each frame, e.g. "
            f"{MINIMAL_DOCUMENT}", path=path)
    if "exposure_unit" not in doc:
        raise DataFormatError(
            "the hsiffc metadata has no 'exposure_unit'; add \"exposure_unit\": \"ms\" (or s, "
            "us, ns)", path=path)
    exposure = per_frame_field(doc, "exposure", n, path, as_floats, required=True)
    exposure_ms = exposure_to_ms(exposure, doc["exposure_unit"], path=path)
    if np.any(~np.isfinite(exposure_ms) | (exposure_ms < 0)):
        raise DataFormatError("'exposure' must be finite numbers >= 0; fix the JSON", path=path)
    bits = doc.get("bit_depth")
    if bits is None:
        raise DataFormatError(
            "the hsiffc metadata has no 'bit_depth'; add the ADC bit depth, e.g. "
            "\"bit_depth\": 12", path=path)
    if not isinstance(bits, int) or isinstance(bits, bool) or not 1 <= bits <= 32:
        raise DataFormatError(f"'bit_depth' must be a whole number 1..32, got {bits!r}",
                              path=path)
    kind = per_frame_field(doc, "kind", n, path, as_strings, None)
    bad = [] if kind is None else sorted(set(np.atleast_1d(kind).tolist()) - set(FRAME_KINDS))
    if bad:
        raise DataFormatError(f"'kind' values {bad} are not one of {list(FRAME_KINDS)}; fix the "
                              "JSON", path=path)
    fields = {"exposure_ms": exposure_ms, "kind": kind, "bit_depth": bits,
              "illumination": per_frame_field(doc, "illumination", n, path, as_strings, None),
              "photons": per_frame_field(doc, "photons", n, path, as_floats, None),
              "step": per_frame_field(doc, "step", n, path, as_ints, None),
              "mosaic": _mosaic(doc, path)}
    meta = doc.get("meta") or {}
    if not isinstance(meta, dict):
        raise DataFormatError(f"'meta' must be a JSON object, got {type(meta).__name__}",
                              path=path)
    meta = dict(meta)
    if fields["mosaic"] is None and doc.get("wavelengths_nm") is not None:
        meta["wavelengths_nm"] = doc["wavelengths_nm"]
    source = doc.get("source") or ""
    if source and source != str(path):
        meta["source_in_file"] = source
    extra = {k: v for k, v in doc.items() if k not in _KNOWN}
    if extra:
        meta["extra_fields"] = extra
    return {k: v for k, v in fields.items() if v is not None}, meta


# --- Writing and reading hsiffc TIFFs ---------------------------------------------------------

#: the frame dtypes an hsiffc TIFF stores as they are
WRITABLE_DTYPES = (np.uint8, np.uint16, np.uint32, np.int8, np.int16, np.int32, np.float32,
                    np.float64)


# -- writing --------------------------------------------------------------------------------------
def _document(sweep: Sweep) -> dict:
    photons = sweep.photons
    mosaic = sweep.mosaic
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "content": "frames",
        "n_frames": sweep.n_frames,
        "exposure_unit": "ms",
        "exposure": sweep.exposure_ms.tolist(),
        "kind": sweep.kind.tolist(),
        "illumination": sweep.illumination.tolist(),
        "photons": None if np.all(np.isnan(photons)) else json_safe(photons),
        "step": sweep.step.tolist(),
        "bit_depth": sweep.bit_depth,
        "mosaic": None if mosaic is None else json_safe(mosaic.to_dict()),
        "wavelengths_nm": None if mosaic is None or mosaic.wavelengths_nm is None
        else list(mosaic.wavelengths_nm),
        "source": sweep.source,
        "meta": json_safe(sweep.meta, strict=True, what="sweep.meta"),
    }


def write_sweep(path, sweep: Sweep, *, overwrite: bool = False, compression=None) -> Path:
    """Write a sweep as an hsiffc TIFF (one page per frame, metadata as JSON), atomically.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.tif`` or ``.tiff``. A missing folder is created, as every
        hsiffc writer does.
    sweep : Sweep
        Frames (``uint8``, ``uint16``, ``uint32``, ``int8``, ``int16``, ``int32``, ``float32``
        or ``float64``; kept as they are, negative values included) and metadata. Exposure
        times are written in milliseconds. ``sweep.meta`` must be JSON-serialisable; NaN/inf
        inside it are written as ``null``.
    overwrite : bool
        Replace an existing file. Without it an existing ``path`` is left untouched and
        ``FileExistsError`` is raised.
    compression : str, optional
        Passed to :func:`tifffile.imwrite` (e.g. ``"zlib"``); lossless codecs only.

    Returns
    -------
    Path
        The file written.

    Notes
    -----
    The file is written to a hidden temporary file in the same folder, flushed to disk
    (``fsync``) and renamed onto ``path`` with :func:`os.replace`, so ``path`` never holds a
    partial file; the temporary file is removed if anything fails.

    Examples
    --------
    Write a two-frame 10-bit sweep and read it back:

    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> from hsiffc import Sweep
    >>> from hsiffc.io import read_sweep_tiff, write_sweep
    >>> tmp = tempfile.TemporaryDirectory()
    >>> sweep = Sweep(np.full((2, 4, 6), 300, np.uint16), exposure_ms=[1.0, 2.0], kind="light",
    ...               bit_depth=10)
    >>> path = write_sweep(Path(tmp.name) / "sweep.tif", sweep)
    >>> again = read_sweep_tiff(path)
    >>> again.exposure_ms.tolist(), again.bit_depth, bool((again.data == sweep.data).all())
    ([1.0, 2.0], 10, True)
    >>> tmp.cleanup()
    """
    path = Path(path)
    if not isinstance(sweep, Sweep):
        raise TypeError(f"write_sweep needs a hsiffc.Sweep, got {type(sweep).__name__}")
    if path.suffix.lower() not in TIFF_SUFFIXES:
        raise DataFormatError(f"hsiffc TIFF files must end in .tif or .tiff, got {path.suffix!r}; "
                              "rename the output", path=path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; give a file name ending in .tif")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) to replace it "
                              "(the existing file was left unchanged)")
    data = np.ascontiguousarray(sweep.data)
    if data.dtype.type not in WRITABLE_DTYPES:
        raise DataFormatError(
            f"cannot write frames of dtype {data.dtype}: an hsiffc TIFF stores (u)int8/16/32 or "
            "float32/64 frames and hsiffc does not change values to fit; convert the frames "
            "first if their values fit one of those (e.g. sweep.data.astype(np.float64))",
            path=path)
    if np.issubdtype(data.dtype, np.integer) and data.size and int(data.max()) > sweep.full_scale_dn:
        raise DataFormatError(
            f"data exceed the stated bit depth: maximum {int(data.max())} DN > "
            f"{sweep.full_scale_dn} DN (2**{sweep.bit_depth}-1); fix bit_depth", path=path)
    description = json.dumps(_document(sweep), allow_nan=False)

    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            tifffile.imwrite(fh, data, photometric="minisblack", description=description,
                             metadata=None, compression=compression)
    return path


# -- reading --------------------------------------------------------------------------------------
def read_sweep_tiff(path) -> Sweep:
    """Read an hsiffc TIFF into a :class:`~hsiffc.Sweep`.

    Plain TIFFs (without the hsiffc JSON document) are refused here; read them with
    :func:`hsiffc.io.read_sweep` or :func:`hsiffc.io.open_source`, which take their metadata
    from tags, a sidecar or keyword arguments.

    Parameters
    ----------
    path : str or Path
        A ``.tif``/``.tiff`` file written by :func:`write_sweep` or by hand (see the module
        docstring for the JSON document it must carry).

    Returns
    -------
    Sweep
        ``data`` (N, H, W) in the file's dtype (DN are never rescaled), ``exposure_ms`` in
        milliseconds (converted from the file's ``exposure_unit``), and the per-frame kind,
        illumination, photons and step. ``source`` is the file path; a different ``source``
        stored in the file is kept in ``meta["source_in_file"]``. Unknown top-level JSON keys
        are kept in ``meta["extra_fields"]``.

    Raises
    ------
    DataFormatError
        Missing file, not a TIFF, truncated file, no or invalid hsiffc metadata, per-frame list
        lengths that do not match the page count, pages of different shapes or dtypes, missing
        bit depth, integer data above ``2**bit_depth - 1``, or a header over the size limits
        (:mod:`hsiffc.files.limits`). Each message names the file, the problem and the fix.
        NaN/inf in float frames are *not* an error here.

    Examples
    --------
    Any TIFF writer makes an hsiffc TIFF: the frames as pages, the JSON document as the first
    page's description (exposure here in microseconds):

    >>> import json, tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import read_sweep_tiff
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "by_hand.tif"
    >>> doc = {"format": "hsiffc", "exposure": [40000, 80000], "exposure_unit": "us",
    ...        "bit_depth": 12}
    >>> tifffile.imwrite(path, np.zeros((2, 4, 6), np.uint16), description=json.dumps(doc),
    ...                  metadata=None)
    >>> sweep = read_sweep_tiff(path)
    >>> sweep.exposure_ms.tolist(), sweep.bit_depth, sweep.kind.tolist()
    ([40.0, 80.0], 12, ['light', 'light'])
    >>> tmp.cleanup()
    """
    from ._metadata import Overrides
    from .source import FrameSource

    path = Path(path)
    if not path.exists():
        raise DataFormatError("file not found; check the path", path=path)
    if path.is_dir():
        raise DataFormatError("is a folder, not a TIFF file; give the .tif file", path=path)
    limits = default_limits()
    layout = open_tiff(path, limits)
    if not layout.strict:
        layout.close()
        parse_document(layout.meta.get("tiff_description", ""), path)  # raises the hint
    if len(layout.shape) != 2:
        layout.close()
        raise DataFormatError(f"pages must all be single-channel images of one shape, found "
                              f"{layout.shape}; write one (H, W) frame per page", path=path)
    with FrameSource([layout], Overrides(), limits, label=str(path)) as src:
        return src.to_sweep()


# --- TIFF files as frame stacks (hsiffc and plain TIFFs) --------------------------------------

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
