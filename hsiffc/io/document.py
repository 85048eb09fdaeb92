"""The JSON document of an hsiffc TIFF (ImageDescription of the first page): parse and check.

The layout of the document is described in :mod:`hsiffc.io.tiff`. :func:`parse_document`
checks that a description is an hsiffc document; :func:`document_fields` turns it into the
metadata fields of a frame source (exposure in milliseconds, kinds, bit depth, mosaic, ...),
with one error per problem naming the file, the key and the fix.
"""

from __future__ import annotations


import numpy as np

from ..errors import DataFormatError
from ..data.mosaic import Mosaic
from ..data.sweep import FRAME_KINDS

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "EXPOSURE_UNITS_MS", "MINIMAL_DOCUMENT",
           "exposure_to_ms", "parse_document", "document_fields", "is_hsiffc_document"]

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
    from ..files.parsers import load_json

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
