"""ENVI raster files, read and written: a text header ``NAME.hdr`` beside a raw binary data file.

Header (the ENVI header format): a first line ``ENVI``, then ``key = value`` lines; a value in
braces ``{...}`` is a list and may span lines; ``;`` starts a comment line. Keys read:

* ``samples`` (columns), ``lines`` (rows), ``bands``; ``header offset`` (bytes before the data);
* ``data type``: 1 uint8, 2 int16, 3 int32, 4 float32, 5 float64, 12 uint16, 13 uint32,
  14 int64, 15 uint64 (complex types are refused);
* ``interleave``: ``bsq`` (band after band), ``bil`` (bands interleaved by line) or ``bip``
  (by pixel); ``byte order``: 0 little-endian, 1 big-endian (any other value is refused);
  ``samples``, ``lines`` and ``bands`` must be >= 1 and ``header offset`` >= 0;
* ``wavelength`` (with ``wavelength units``: nm, um/micrometers) -> mosaic band centres;
* not in the core spec but written by camera software, read when present: exposure as
  ``exposure time``, ``integration time``, ``tint``, ``shutter`` or ``exposure_ms`` (milliseconds,
  or the unit in ``exposure time units`` / ``exposure units``; one value or one per band),
  ``gain`` (kept in ``meta``), ``bit depth`` / ``data bit depth``.

The data file is ``NAME`` (the header name without ``.hdr``) or ``NAME`` with one of ``.img``,
``.raw``, ``.dat``, ``.bsq``, ``.bil``, ``.bip``. As raw input each band is one (lines x
samples) frame, so a single-band file is one frame. A header whose ``wavelength`` list has one
entry per band (``bands`` > 1) describes a spectral cube, not raw frames, and is refused by the
frame reader (read it with :func:`read_envi`).

Writing (:func:`write_envi`; a corrected file's cubes: :mod:`hsiffc.cubes.export`) gives ``NAME.hdr`` + ``NAME.img`` for
users whose next tool is ENVI or SPy. The header holds ``samples``, ``lines``, ``bands``,
``header offset = 0``, ``file type = ENVI Standard``, ``data type``, ``interleave``,
``byte order = 0`` (little-endian), ``wavelength units = Nanometers`` and ``wavelength = {...}``
when wavelengths are known, ``band names``, ``description`` and any extra ``key = value`` pairs
given. Both files are written atomically, the data first, the header last (a reader that finds
the header finds complete data).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from ..files.atomic import atomic_path
from ..files.limits import ReadLimits, default_limits
from ._layout import FileLayout

__all__ = ["parse_envi_header", "open_envi", "read_envi", "envi_paths", "ENVI_DTYPES", "write_envi"]


# --- Reading ----------------------------------------------------------------------------------

ENVI_DTYPES = {1: "u1", 2: "i2", 3: "i4", 4: "f4", 5: "f8", 12: "u2", 13: "u4", 14: "i8",
               15: "u8"}
_DATA_SUFFIXES = ("", ".img", ".raw", ".dat", ".bsq", ".bil", ".bip")
_EXPOSURE_KEYS = ("exposure_ms", "exposure time", "integration time", "tint", "shutter",
                  "exposure")
_UNITS_MS = {"s": 1e3, "sec": 1e3, "seconds": 1e3, "ms": 1.0, "msec": 1.0, "milliseconds": 1.0,
             "us": 1e-3, "usec": 1e-3, "microseconds": 1e-3, "ns": 1e-6, "nanoseconds": 1e-6}


def parse_envi_header(path, limits: ReadLimits | None = None) -> dict:
    """``key -> value`` of an ENVI header (keys lower-case; lists as lists of strings).

    The header must be a regular file no larger than ``limits.max_header_bytes`` (checked from
    its ``stat`` before it is read); parsing takes time linear in its size.

    Parameters
    ----------
    path : str or Path
        The ``.hdr`` file.
    limits : ReadLimits, optional
        Default: :func:`~hsiffc.files.limits.default_limits`.

    Returns
    -------
    dict
        Values as strings, ``{...}`` lists as lists of strings.

    Raises
    ------
    DataFormatError
        Unreadable, not a regular file, larger than the limit, or its first line is not
        ``ENVI``.
    """
    from ..files.atomic import require_regular_input

    path = Path(path)
    limits = limits or default_limits()
    st = require_regular_input(path, what="ENVI header")
    limits.check_header_bytes(path=path, nbytes=st.st_size, what="ENVI header")
    try:
        with open(path, "rb") as fh:
            raw = fh.read(limits.max_header_bytes + 1)
    except OSError as exc:
        raise DataFormatError(f"cannot read the ENVI header ({exc})", path=path) from exc
    limits.check_header_bytes(path=path, nbytes=len(raw), what="ENVI header")  # it grew
    lines = raw.decode("utf-8", errors="replace").splitlines()
    if not lines or lines[0].strip() != "ENVI":
        raise DataFormatError("not an ENVI header (the first line must be 'ENVI')", path=path)
    out: dict = {}
    i = 1
    while i < len(lines):
        line = lines[i]
        i += 1
        if not line.strip() or line.lstrip().startswith(";"):
            continue
        key, eq, value = line.partition("=")
        key, value = key.strip().lower(), value.strip()
        if not eq:
            raise DataFormatError(f"line {i}: {line.strip()[:60]!r} is not 'key = value'",
                                  path=path)
        if value.startswith("{"):
            parts = [value]  # each line is searched for "}" once: linear in the header's size
            while "}" not in parts[-1] and i < len(lines):
                parts.append(lines[i])
                i += 1
            if "}" not in parts[-1]:
                raise DataFormatError(f"the value of {key!r} opens '{{' but never closes it; "
                                      "the header is truncated", path=path)
            parts[-1] = parts[-1][:parts[-1].index("}")]
            inner = " ".join(parts)[1:]
            value = [v.strip() for v in inner.split(",")] if inner.strip() else []
        out[key] = value
    return out


def envi_paths(path) -> tuple[Path, Path]:
    """(header, data file) for an ENVI header or data file path.

    Parameters
    ----------
    path : str or Path
        The ``.hdr`` or the data file.

    Returns
    -------
    (Path, Path)

    Raises
    ------
    DataFormatError
        Header or data file not found.
    """
    path = Path(path)
    if path.suffix.lower() == ".hdr":
        header = path
        base = path.with_suffix("")
    else:
        header, base = path.with_suffix(".hdr"), path.with_suffix("")
        if not header.is_file():
            header = path.with_name(path.name + ".hdr")
        if path.is_file() and header.is_file():
            return header, path
    if not header.is_file():
        raise DataFormatError("ENVI header not found; give the .hdr file", path=path)
    for suffix in _DATA_SUFFIXES:
        candidate = base.with_name(base.name + suffix)
        if candidate.is_file() and candidate != header:
            return header, candidate
    raise DataFormatError(f"the data file of this ENVI header is missing (looked for "
                          f"{base.name} with {', '.join(s or 'no suffix' for s in _DATA_SUFFIXES)}"
                          "); copy it next to the header", path=header)


def _int(head, key, path, default=None):
    value = head.get(key, default)
    try:
        return int(str(value))
    except (TypeError, ValueError):
        raise DataFormatError(f"the header needs a whole number for {key!r}, got {value!r}",
                              path=path) from None


def _floats(values, key, path):
    try:
        return [float(v) for v in (values if isinstance(values, list) else [values])]
    except ValueError:
        raise DataFormatError(f"{key!r} holds a value that is not a number", path=path) from None


def _geometry(header: Path, head: dict, data: Path, limits: ReadLimits):
    for key in ("samples", "lines", "bands", "data type"):
        if key not in head:
            raise DataFormatError(f"the header has no {key!r}; it is not a complete ENVI header",
                                  path=header)
    samples, lines, bands = (_int(head, k, header) for k in ("samples", "lines", "bands"))
    for key, value in (("samples", samples), ("lines", lines), ("bands", bands)):
        if value < 1:
            raise DataFormatError(f"{key} = {value} in the header: an ENVI raster needs at least "
                                  f"1; the header is damaged, fix {key!r}", path=header)
    code = _int(head, "data type", header)
    if code not in ENVI_DTYPES:
        raise DataFormatError(f"data type {code} is not supported (complex or unknown); hsiffc "
                              f"reads {sorted(ENVI_DTYPES)}", path=header)
    order = _int(head, "byte order", header, 0)
    if order not in (0, 1):
        raise DataFormatError(f"byte order = {order} in the header is neither 0 (little-endian) "
                              "nor 1 (big-endian); fix 'byte order'", path=header)
    dtype = np.dtype(ENVI_DTYPES[code]).newbyteorder(">" if order == 1 else "<")
    interleave = str(head.get("interleave", "bsq")).lower()
    if interleave not in ("bsq", "bil", "bip"):
        raise DataFormatError(f"interleave {interleave!r} is not bsq, bil or bip", path=header)
    offset = _int(head, "header offset", header, 0)
    if offset < 0:
        raise DataFormatError(f"header offset = {offset} in the header is negative; it is the "
                              "number of bytes before the data (0 or more): fix "
                              "'header offset'", path=header)
    limits.check_frames(path=header, n_frames=bands, shape=(lines, samples),
                        itemsize=dtype.itemsize)
    need = offset + samples * lines * bands * dtype.itemsize
    size = data.stat().st_size
    if size < need:
        raise DataFormatError(f"data file {data.name} is truncated: the header needs {need} "
                              f"bytes but the file has {size}; copy it again", path=header)
    shape = {"bsq": (bands, lines, samples), "bil": (lines, bands, samples),
             "bip": (lines, samples, bands)}[interleave]
    return shape, dtype, offset, interleave, (lines, samples, bands)


def _wavelengths_nm(head, header):
    if "wavelength" not in head:
        return None
    values = _floats(head["wavelength"], "wavelength", header)
    units = str(head.get("wavelength units", "nm")).lower()
    scale = {"nm": 1.0, "nanometers": 1.0, "um": 1e3, "micrometers": 1e3, "microns": 1e3}.get(units)
    if scale is None:
        raise DataFormatError(f"wavelength units {units!r} are not nm or micrometers",
                              path=header)
    return [v * scale for v in values]


def open_envi(path, limits: ReadLimits) -> FileLayout:
    """Parse an ENVI header and return the :class:`FileLayout` of its bands as frames.

    Parameters
    ----------
    path : str or Path
        The file.
    limits : ReadLimits
        Size limits checked against the header before anything is decoded.

    Returns
    -------
    FileLayout
        Frame count, stored shape and dtype, the metadata the file states (with their
        origins) and a ``read(k)`` that decodes frame k on demand.

    Raises
    ------
    DataFormatError
        Unreadable, truncated or unsupported file, or a header over the limits.
    """
    header, data = envi_paths(path)
    head = parse_envi_header(header, limits)
    shape, dtype, offset, interleave, (lines, samples, bands) = _geometry(header, head, data,
                                                                          limits)
    wavelengths = _wavelengths_nm(head, header)
    if wavelengths is not None and bands > 1 and len(wavelengths) == bands:
        raise DataFormatError(f"holds a spectral cube ({bands} bands with one wavelength each), "
                              "not raw mosaic frames; the commands that take frames read "
                              "raw frames (one band per frame) - describe or draw a cube with "
                              "hsiffc info / hsiffc quicklook, read it with hsiffc.read_cube",
                              path=header)
    state = {"map": None}

    def read(k: int) -> np.ndarray:
        if state["map"] is None:
            state["map"] = np.memmap(data, dtype=dtype, mode="r", offset=offset, shape=shape)
        m = state["map"]
        frame = m[k] if interleave == "bsq" else (m[:, k, :] if interleave == "bil" else m[:, :, k])
        return np.ascontiguousarray(frame, dtype=dtype.newbyteorder("="))

    def close():
        state["map"] = None

    layout = FileLayout(path=header, format="envi", n_frames=bands, shape=(lines, samples),
                        dtype=dtype.newbyteorder("="), read=read, close=close)
    for key in _EXPOSURE_KEYS:
        if key in head:
            values = _floats(head[key], key, header)
            unit = str(head.get(f"{key} units", head.get("exposure units", "ms"))).lower()
            if unit not in _UNITS_MS:
                raise DataFormatError(f"unknown unit {unit!r} for {key!r}; use s, ms, us or ns",
                                      path=header)
            ms = np.array(values) * _UNITS_MS[unit]
            layout.give("exposure_ms", ms[0] if ms.size == 1 else ms,
                        f"file (ENVI header '{key}')")
            break
    for key in ("bit depth", "data bit depth"):
        if key in head:
            bits = _int(head, key, header)
            most = 8 * dtype.itemsize if dtype.kind in "ui" else 32
            if not 1 <= bits <= min(most, 32):
                raise DataFormatError(f"header field '{key}' = {head[key]!r} is not a bit depth "
                                      f"1..{min(most, 32)} (the data are {dtype.name}); correct "
                                      "the header", path=header)
            layout.give("bit_depth", bits, f"file (ENVI header '{key}')")
    if wavelengths is not None:
        layout.meta["wavelengths_nm"] = wavelengths
    for key in ("gain", "description", "sensor type", "band names"):
        if key in head:
            layout.meta[key.replace(" ", "_")] = head[key]
    layout.meta["envi_interleave"] = interleave
    return layout


def read_envi(path, *, limits: ReadLimits | None = None) -> tuple[np.ndarray, dict]:
    """A whole ENVI raster as ``(lines, samples, bands)`` (channels last) and its header.

    Parameters
    ----------
    path : str or Path
        The ``.hdr`` or the data file.
    limits : ReadLimits, optional

    Returns
    -------
    cube : (H, W, B) ndarray in the file's sample type (native byte order)
    header : dict
        The parsed header (:func:`parse_envi_header`), plus ``wavelengths_nm`` (floats, nm)
        when the header has wavelengths.
    """
    limits = limits or default_limits()
    header, data = envi_paths(path)
    head = parse_envi_header(header, limits)
    shape, dtype, offset, interleave, (lines, samples, bands) = _geometry(header, head, data,
                                                                          limits)
    limits.check_bytes(path=header, nbytes=lines * samples * bands * dtype.itemsize,
                       what="the cube")
    raw = np.fromfile(data, dtype=dtype, count=lines * samples * bands, offset=offset)
    raw = raw.reshape(shape)
    axes = {"bsq": (1, 2, 0), "bil": (0, 2, 1), "bip": (0, 1, 2)}[interleave]
    cube = np.ascontiguousarray(raw.transpose(axes), dtype=dtype.newbyteorder("="))
    wavelengths = _wavelengths_nm(head, header)
    if wavelengths is not None:
        head["wavelengths_nm"] = wavelengths
    return cube, head


# --- Writing ----------------------------------------------------------------------------------

_CODES = {np.dtype(v).newbyteorder("<"): k for k, v in ENVI_DTYPES.items()}


def _value(value) -> str:
    """``value`` as ENVI header text: a list in braces; a scalar as it is, which may hold braces
    but not start with one (a reader would take it for a list) nor hold a line break, and must
    be UTF-8 (a file name that is not is refused here, before any file is written)."""
    if isinstance(value, (list, tuple, np.ndarray)):
        items = [f"{v:.6g}" if isinstance(v, (float, np.floating)) else str(v) for v in value]
        for item in items:
            if any(c in item for c in "{}\n\r"):
                raise DataFormatError(f"ENVI header list item {item[:40]!r} may not contain "
                                      "braces or line breaks")
        return "{" + ", ".join(items) + "}"
    text = str(value)
    if any(c in text for c in "\n\r") or text.lstrip().startswith("{"):
        raise DataFormatError(f"ENVI header value {text[:40]!r} may not contain line breaks or "
                              "start with '{'; rename the file")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise DataFormatError(f"ENVI header value {text[:40]!r} is not UTF-8 text (a file name "
                              "in another encoding?); rename the file") from None
    return text


def check_header_values(*values) -> None:
    """Raise the :class:`DataFormatError` :func:`write_envi` would raise for any of ``values``
    (before a set of ENVI files is written, so none is left without the others)."""
    for value in values:
        _value(value)


def write_envi(path, cube, *, wavelengths_nm=None, band_names=None, description: str = "",
               interleave: str = "bsq", extra: dict | None = None,
               overwrite: bool | None = None, fileset=None) -> tuple[Path, Path]:
    """Write an (H, W, bands) cube (or an (H, W) image) as an ENVI header + data pair.

    Parameters
    ----------
    path : str or Path
        ``NAME.hdr``, ``NAME.img`` or ``NAME``; the pair ``NAME.hdr`` + ``NAME.img`` is written.
    cube : (H, W) or (H, W, B) ndarray
        Samples kept as they are (uint8/16/32, int16/32/64, float32/64), little-endian.
    wavelengths_nm : sequence of B floats, optional
        Band centres, written as ``wavelength`` with ``wavelength units = Nanometers``.
    band_names : sequence of B str, optional
    description : str
    interleave : {"bsq", "bil", "bip"}
    extra : dict, optional
        More header entries (``key -> value``; lists are written in braces), e.g.
        ``{"exposure time": 20.0, "data ignore value": 0}``.
    overwrite : bool, optional
        Replace existing files (default: the command's write policy; refuse).
    fileset : hsiffc.files.atomic.FileSet, optional
        Leave both files in this set, renamed with the rest of it (a cube's companions).

    Returns
    -------
    (header path, data path)
    """
    path = Path(path)
    base = path.with_suffix("") if path.suffix.lower() in (".hdr", ".img") else path
    header, data = base.with_name(base.name + ".hdr"), base.with_name(base.name + ".img")
    cube = np.asarray(cube)
    if cube.ndim == 2:
        cube = cube[:, :, None]
    if cube.ndim != 3:
        raise DataFormatError(f"an ENVI cube is (H, W) or (H, W, bands), got shape {cube.shape}",
                              path=header)
    dtype = cube.dtype.newbyteorder("<")
    if dtype not in _CODES:
        raise DataFormatError(f"samples of dtype {cube.dtype} cannot be written to ENVI; convert "
                              "to float32 or uint16", path=header)
    lines, samples, bands = cube.shape
    if interleave not in ("bsq", "bil", "bip"):
        raise ValueError(f"interleave must be bsq, bil or bip, got {interleave!r}")
    axes = {"bsq": (2, 0, 1), "bil": (0, 2, 1), "bip": (0, 1, 2)}[interleave]
    entries = {"description": _value(description or "written by hsiffc"),
               "samples": samples, "lines": lines, "bands": bands, "header offset": 0,
               "file type": "ENVI Standard", "data type": _CODES[dtype],
               "interleave": interleave, "byte order": 0}
    if wavelengths_nm is not None:
        wavelengths = [float(w) for w in wavelengths_nm]
        if len(wavelengths) != bands:
            raise DataFormatError(f"{len(wavelengths)} wavelengths for {bands} bands", path=header)
        entries["wavelength units"] = "Nanometers"
        entries["wavelength"] = _value(wavelengths)
    if band_names is not None:
        entries["band names"] = _value(list(band_names))
    for key, value in (extra or {}).items():
        entries[str(key).lower()] = _value(value)
    text = "ENVI\n" + "".join(f"{k} = {v if isinstance(v, str) else _value(v)}\n"
                              for k, v in entries.items())
    # the header first: a pair is judged by its header (whether hsiffc wrote it, from what), so
    # a kill or a full disk between the two writes leaves a header that says whose it is, never
    # a data file nothing vouches for (a rerun stopped at such an .img without --overwrite)
    with atomic_path(header, overwrite=overwrite, fileset=fileset) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    with atomic_path(data, overwrite=overwrite, fileset=fileset) as tmp:
        with open(tmp, "wb") as fh:
            np.ascontiguousarray(cube.transpose(axes), dtype=dtype).tofile(fh)
    return header, data
