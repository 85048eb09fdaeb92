"""hsiffc's TIFF format: a stack of raw frames, one TIFF page per frame, plus one JSON document.

File layout
-----------
* Page ``k`` holds frame ``k`` of the sweep as a single-channel (H, W) image, in acquisition
  order, in the frames' own dtype (``uint8`` / ``uint16`` raw DN, or ``float32`` for averaged or
  processed frames). Values are never rescaled, neither on writing nor on reading.
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

Examples
--------
Write and read back a two-frame 10-bit sweep::

    import numpy as np
    from hsiffc import Sweep
    from hsiffc.io import write_sweep, read_sweep_tiff

    frames = np.zeros((2, 4, 6), dtype=np.uint16)
    sweep = Sweep(frames, exposure_ms=[1.0, 2.0], kind="light", bit_depth=10)
    write_sweep("sweep.tif", sweep)
    again = read_sweep_tiff("sweep.tif")
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
import tifffile

from .._json import json_safe
from ..atomic import atomic_path
from ..errors import DataFormatError
from ..mosaic import Mosaic
from ..sweep import FRAME_KINDS, Sweep

__all__ = ["write_sweep", "read_sweep_tiff", "FORMAT_NAME", "FORMAT_VERSION", "EXPOSURE_UNITS_MS"]

FORMAT_NAME = "hsiffc"
FORMAT_VERSION = 1
#: Milliseconds per unit, for every exposure unit hsiffc accepts in files.
EXPOSURE_UNITS_MS = {"s": 1e3, "ms": 1.0, "us": 1e-3, "ns": 1e-6}
TIFF_SUFFIXES = (".tif", ".tiff")
_WRITABLE_DTYPES = (np.uint8, np.uint16, np.uint32, np.float32, np.float64)
_MINIMAL_DOC = ('{"format": "hsiffc", "exposure": 10.0, "exposure_unit": "ms", "bit_depth": 12, '
                '"kind": "light"}')


def exposure_to_ms(values, unit: str, *, path=None, what: str = "exposure_unit") -> np.ndarray:
    """Convert exposure times given in ``unit`` ("s", "ms", "us" or "ns") to milliseconds."""
    if unit not in EXPOSURE_UNITS_MS:
        raise DataFormatError(
            f"unknown {what} {unit!r}; use one of {sorted(EXPOSURE_UNITS_MS)} "
            "(seconds, milliseconds, microseconds, nanoseconds)", path=path)
    return np.asarray(values, dtype=np.float64) * EXPOSURE_UNITS_MS[unit]


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
        Output file; must end in ``.tif`` or ``.tiff``. Its folder must exist.
    sweep : Sweep
        Frames (``uint8``, ``uint16``, ``uint32``, ``float32`` or ``float64``; kept as they
        are) and metadata. Exposure times are written in milliseconds. ``sweep.meta`` must be
        JSON-serialisable; NaN/inf inside it are written as ``null``.
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
    """
    path = Path(path)
    if not isinstance(sweep, Sweep):
        raise TypeError(f"write_sweep needs a hsiffc.Sweep, got {type(sweep).__name__}")
    if path.suffix.lower() not in TIFF_SUFFIXES:
        raise DataFormatError(f"hsiffc TIFF files must end in .tif or .tiff, got {path.suffix!r}; "
                              "rename the output", path=path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist; create it first")
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; give a file name ending in .tif")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) to replace it "
                              "(the existing file was left unchanged)")
    data = np.ascontiguousarray(sweep.data)
    if data.dtype.type not in _WRITABLE_DTYPES:
        raise DataFormatError(
            f"cannot write frames of dtype {data.dtype}; use uint8/uint16 for raw DN or float32 "
            "for processed frames (e.g. sweep.data.astype(np.float32))", path=path)
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
class _CollectLog(logging.Filter):
    """Swallow tifffile's log records while reading, keeping their text for error messages."""

    def __init__(self):
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record):
        self.messages.append(record.getMessage())
        return False


def _ifd_end(tf, page) -> int:
    """End (byte offset) of a page's IFD and of its tag values, as the file declares them."""
    fmt = tf.tiff
    fh = tf.filehandle
    fh.seek(page.offset)
    raw = fh.read(fmt.tagnosize)
    if len(raw) < fmt.tagnosize:
        return page.offset + fmt.tagnosize
    ntags = struct.unpack(fmt.tagnoformat, raw)[0]
    end = page.offset + fmt.tagnosize + ntags * fmt.tagsize + fmt.offsetsize
    for tag in page.tags.values():
        if tag.valuebytecount > fmt.tagoffsetthreshold:
            end = max(end, tag.valueoffset + tag.valuebytecount)
    return end


def _read_pages(path: Path):
    """(description of page 0, list of page arrays) or DataFormatError."""
    log = logging.getLogger("tifffile")
    collect = _CollectLog()
    log.addFilter(collect)
    try:
        size = path.stat().st_size
        if size == 0:
            raise DataFormatError("file is empty (0 bytes), probably truncated while copying or "
                                  "writing; copy or write it again", path=path)
        with tifffile.TiffFile(path) as tf:
            pages = list(tf.pages)
            if not pages:
                raise DataFormatError("the TIFF holds no image page; rewrite it", path=path)
            description = pages[0].description or ""
            arrays = []
            for k, page in enumerate(pages):
                end = max(_ifd_end(tf, page), max(
                    (int(o) + int(c) for o, c in zip(page.dataoffsets, page.databytecounts)),
                    default=0))
                if end > size:
                    raise DataFormatError(
                        f"file is truncated: page {k} needs bytes up to {end} but the file has "
                        f"{size}; copy or write the file again", path=path)
                arrays.append(page.asarray())
    except DataFormatError:
        raise
    except Exception as exc:  # tifffile raises many types on broken files
        extra = f" ({'; '.join(collect.messages[:3])})" if collect.messages else ""
        raise DataFormatError(
            f"not a readable TIFF file ({type(exc).__name__}: {exc}){extra}; the file may be "
            "truncated or not a TIFF - check it opens in an image viewer or write it again",
            path=path) from exc
    finally:
        log.removeFilter(collect)
    return description, arrays, collect.messages


def _per_frame(doc, key, n, path, convert, default=None, *, required=False):
    """A per-frame field: a list of n values or one value for all frames."""
    if key not in doc or doc[key] is None:
        if required:
            raise DataFormatError(
                f"the hsiffc metadata has no {key!r}; add it to the JSON in the first page's "
                f"ImageDescription, e.g. {_MINIMAL_DOC}", path=path)
        return default
    value = doc[key]
    if isinstance(value, list):
        if len(value) != n:
            raise DataFormatError(
                f"{key!r} has {len(value)} entries but the file has {n} pages (frames); give one "
                f"entry per page or a single value for all (a shorter page count may mean a "
                "truncated file)", path=path)
    try:
        return convert(value)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{key!r} = {value!r} is not valid ({exc}); see the hsiffc TIFF "
                              "format in the README", path=path) from exc


def _floats(value):
    if isinstance(value, list):
        return np.array([np.nan if v is None else float(v) for v in value], dtype=np.float64)
    return np.float64(np.nan if value is None else float(value))


def _strings(value):
    values = value if isinstance(value, list) else [value]
    if not all(isinstance(v, str) for v in values):
        raise TypeError("expected text")
    return np.array(values, dtype=object) if isinstance(value, list) else value


def _ints(value):
    values = value if isinstance(value, list) else [value]
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise TypeError("expected whole numbers")
    return np.asarray(value, dtype=np.int64)


def _parse_document(description: str, path: Path) -> dict:
    hint = ("add a JSON document to the ImageDescription of the first page, at least "
            f"{_MINIMAL_DOC} (see the hsiffc TIFF format in the README), or write the file "
            "with hsiffc.io.write_sweep")
    text = description.strip()
    if not text.startswith("{"):
        raise DataFormatError(f"plain TIFF without hsiffc metadata; {hint}", path=path)
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise DataFormatError(f"the ImageDescription is not valid JSON ({exc}); {hint}",
                              path=path) from exc
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


def read_sweep_tiff(path) -> Sweep:
    """Read an hsiffc TIFF into a :class:`~hsiffc.Sweep`.

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
        bit depth, or integer data above ``2**bit_depth - 1``. Each message names the file, the
        problem and the fix. NaN/inf in float frames are *not* an error here.
    """
    path = Path(path)
    if not path.exists():
        raise DataFormatError("file not found; check the path", path=path)
    if path.is_dir():
        raise DataFormatError("is a folder, not a TIFF file; give the .tif file", path=path)
    description, arrays, _ = _read_pages(path)
    doc = _parse_document(description, path)

    n = len(arrays)
    declared = doc.get("n_frames")
    if declared is not None and declared != n:
        raise DataFormatError(
            f"the metadata declares {declared} frames but only {n} pages could be read; the file "
            "is probably truncated - copy or write it again", path=path)
    shapes = sorted({a.shape for a in arrays})
    if len(shapes) != 1 or len(shapes[0]) != 2:
        raise DataFormatError(
            f"pages must all be single-channel images of one shape, found shapes {shapes}; "
            "write one (H, W) frame per page", path=path)
    dtypes = sorted({a.dtype.str for a in arrays})
    if len(dtypes) != 1:
        raise DataFormatError(f"pages have different dtypes {dtypes}; write all frames with "
                              "one dtype", path=path)
    data = np.stack(arrays)

    if "exposure" not in doc or doc["exposure"] is None:
        raise DataFormatError(
            "the hsiffc metadata has no 'exposure'; add the exposure time of each frame, e.g. "
            f"{_MINIMAL_DOC}", path=path)
    if "exposure_unit" not in doc:
        raise DataFormatError(
            "the hsiffc metadata has no 'exposure_unit'; add \"exposure_unit\": \"ms\" (or s, "
            "us, ns)", path=path)
    exposure = _per_frame(doc, "exposure", n, path, _floats, required=True)
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
    if np.issubdtype(data.dtype, np.integer) and data.size and int(data.max()) > 2 ** bits - 1:
        raise DataFormatError(
            f"data exceed the stated bit depth: maximum {int(data.max())} DN > {2 ** bits - 1} DN "
            f"(2**{bits}-1); fix 'bit_depth' in the metadata", path=path)

    kind = _per_frame(doc, "kind", n, path, _strings, "light")
    bad = sorted(set(np.atleast_1d(kind).tolist()) - set(FRAME_KINDS))
    if bad:
        raise DataFormatError(f"'kind' values {bad} are not one of {list(FRAME_KINDS)}; fix the "
                              "JSON", path=path)
    illumination = _per_frame(doc, "illumination", n, path, _strings, "")
    photons = _per_frame(doc, "photons", n, path, _floats, None)
    step = _per_frame(doc, "step", n, path, _ints, None)

    mosaic = None
    wavelengths = doc.get("wavelengths_nm")
    if doc.get("mosaic") is not None:
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

    meta = doc.get("meta") or {}
    if not isinstance(meta, dict):
        raise DataFormatError(f"'meta' must be a JSON object, got {type(meta).__name__}",
                              path=path)
    meta = dict(meta)
    if mosaic is None and wavelengths is not None:
        meta["wavelengths_nm"] = wavelengths
    source = doc.get("source") or ""
    if source and source != str(path):
        meta["source_in_file"] = source
    known = {"format", "format_version", "content", "n_frames", "exposure_unit", "exposure",
             "kind", "illumination", "photons", "step", "bit_depth", "mosaic", "wavelengths_nm",
             "source", "meta"}
    extra = {k: v for k, v in doc.items() if k not in known}
    if extra:
        meta["extra_fields"] = extra
    try:
        return Sweep(data=data, exposure_ms=exposure_ms, kind=kind, bit_depth=bits, step=step,
                     photons=photons, illumination=illumination, mosaic=mosaic,
                     source=str(path), meta=meta)
    except ValueError as exc:
        raise DataFormatError(f"inconsistent metadata: {exc}", path=path) from exc
