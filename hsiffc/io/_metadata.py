"""Where a frame's metadata come from: the command line, the file, or a sidecar, in that order.

For every field (exposure, kind, illumination, bit depth, mosaic, bit shift, photons, step)
:func:`resolve_fields` takes the first of

1. command-line options / keyword arguments (:class:`Overrides`): what the user says
   explicitly wins (a wrong exposure in a file's header can be corrected with
   ``--exposure-ms``); the origin then names what it overrode (``hsiffc info`` shows it);
2. the file itself (hsiffc JSON document, EMVA 1288 descriptor, ENVI header, FITS header,
   TIFF tags such as EXIF ``ExposureTime``);
3. a sidecar next to the data (``hsiffc.toml`` / ``hsiffc.csv``, :mod:`hsiffc.io._sidecar`).

A sidecar value that disagrees with the file's is reported with a
:class:`MetadataConflictWarning` (the file's own record wins; fix the file or the sidecar).
Defaults: ``kind`` "light", ``illumination`` "" (unknown), ``photons`` unknown; the bit depth
is inferred later from the values or the dtype (with a warning). A missing exposure time is an
error that names the file and the three ways to give it.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, fields as dc_fields
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, HsiffcWarning
from ..data.mosaic import Mosaic
from ..data.sweep import FRAME_KINDS
from ._layout import FileLayout, PER_FRAME_FIELDS

__all__ = ["Overrides", "ActiveArea", "MetadataConflictWarning", "parse_mosaic",
           "resolve_fields", "missing_field_error", "missing_origin", "HOW_TO_GIVE"]

#: How to give each field: (sidecar key and example, command-line option and example).
HOW_TO_GIVE = {
    "exposure_ms": ("exposure_ms = 10.0", "--exposure-ms 10"),
    "kind": ('kind = "dark"', "--kind dark"),
    "bit_depth": ("bit_depth = 12", "--bit-depth 12"),
    "mosaic": ('mosaic = "5x5"', "--mosaic 5x5"),
    "illumination": ('illumination = "halogen"', "--illumination halogen"),
    "bit_shift": ("bit_shift = 4", "--bit-shift 4"),
    "photons": ("photons = 1000.0", "(no option)"),
}
_TILE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


class MetadataConflictWarning(HsiffcWarning):
    """A sidecar disagrees with a value the file itself gives (the file wins).

    Examples
    --------
    >>> import tempfile, warnings, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import MetadataConflictWarning, open_source
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frame.tif"            # its EXIF ExposureTime tag: 1/100 s
    >>> tifffile.imwrite(path, np.zeros((4, 6), np.uint16),
    ...                  extratags=[(33434, 5, 1, (1, 100), True)])
    >>> _ = (Path(tmp.name) / "hsiffc.toml").write_text("[defaults]\\nexposure_ms = 50.0\\n")
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     with open_source(path, bit_depth=12) as src:
    ...         exposure = src.exposure_ms.tolist()
    >>> exposure, [w.category.__name__ for w in caught]       # the file wins
    ([10.0], ['MetadataConflictWarning'])
    >>> tmp.cleanup()
    """


@dataclass(frozen=True)
class ActiveArea:
    """The part of the sensor covered by the filter mosaic, in pixels (from an IMEC XML).

    Parameters
    ----------
    row, col : int
        First row and column of the area.
    height, width : int
        Its size.
    """

    row: int
    col: int
    height: int
    width: int

    def crop(self, frame: np.ndarray) -> np.ndarray:
        """The active area of a full-sensor frame (a view).

        Parameters
        ----------
        frame : (H, W) ndarray
            Full-sensor frame.

        Returns
        -------
        ndarray, (height, width)
        """
        return frame[self.row:self.row + self.height, self.col:self.col + self.width]


@dataclass(frozen=True)
class Overrides:
    """Metadata given on the command line or as keyword arguments (lowest priority).

    Parameters
    ----------
    exposure_ms : float, optional
    bit_depth : int, optional
    kind : {"light", "dark"}, optional
    mosaic : str or Mosaic, optional
        ``"4x4"``, ``"5x5"``, ``"WxH"`` or the path of an IMEC sensor calibration XML.
    illumination : str, optional
    bit_shift : int, optional
        Right shift for data left-aligned in 16-bit words (0 turns detection off).
    sidecar : path, optional
        Sidecar to use instead of the ``hsiffc.toml``/``hsiffc.csv`` next to each file.

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import Overrides, open_source
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frames.tif"
    >>> tifffile.imwrite(path, np.zeros((2, 8, 8), np.uint16), photometric="minisblack")
    >>> given = Overrides(exposure_ms=20.0, bit_depth=10, mosaic="4x4")
    >>> with open_source(path, overrides=given) as src:  # = open_source(path, exposure_ms=20.0, ...)
    ...     src.exposure_ms.tolist(), src.mosaic.n_bands, src.origins["bit_depth"]
    ([20.0, 20.0], 16, '--bit-depth')
    >>> tmp.cleanup()
    """

    exposure_ms: float | None = None
    bit_depth: int | None = None
    kind: str | None = None
    mosaic: object = None
    illumination: str | None = None
    bit_shift: int | None = None
    sidecar: object = None

    def __post_init__(self):
        if self.exposure_ms is not None and not (np.isfinite(self.exposure_ms)
                                                 and self.exposure_ms >= 0):
            raise DataFormatError(f"exposure_ms must be a finite number >= 0 ms, got "
                                  f"{self.exposure_ms!r}")
        if self.bit_depth is not None and not 1 <= int(self.bit_depth) <= 32:
            raise DataFormatError(f"bit_depth must be a whole number 1..32, got {self.bit_depth!r}")
        if self.bit_shift is not None and not 0 <= int(self.bit_shift) <= 15:
            raise DataFormatError(f"bit_shift must be a whole number 0..15, got {self.bit_shift!r}")
        if self.kind is not None and self.kind not in FRAME_KINDS:
            raise DataFormatError(f"kind must be one of {list(FRAME_KINDS)}, got {self.kind!r}")

    def given(self) -> dict:
        """The metadata fields given (not None), sidecar excluded.

        Returns
        -------
        dict
            Field name -> value.
        """
        return {f.name: getattr(self, f.name) for f in dc_fields(self)
                if f.name != "sidecar" and getattr(self, f.name) is not None}


def parse_mosaic(spec, *, base=None, path=None, frame_shape=None, origin: str = "",
                 sources: list | None = None) -> tuple[Mosaic, ActiveArea | None]:
    """A mosaic from ``"4x4"``, ``"5x5"``, ``"WxH"`` (tile width x height) or an IMEC XML path.

    Parameters
    ----------
    spec : str, Path or Mosaic
        The mosaic as given (a Mosaic passes through).
    base : Path, optional
        Folder a relative XML path is relative to (a sidecar's folder).
    path : str or Path, optional
        The data file (for the messages).
    frame_shape : tuple of int, optional
        (H, W) of the frames: a tile larger than the frame is refused before the tile's
        pattern is built (a "100000x100000" tile would take 80 GB).
    origin : str
        Where the value came from ("sidecar x.toml", "--mosaic"), for the messages.
    sources : list, optional
        The IMEC XML read is appended here (a metadata source whose content the batch's resume
        check compares).

    Returns
    -------
    mosaic : Mosaic
        For an IMEC XML with offset (0, 0): it applies to the cropped frames.
    area : ActiveArea or None
        The active (filter) area to crop frames to (IMEC XML only).

    Raises
    ------
    DataFormatError
        Not a tile size or a readable IMEC XML.
    """
    if isinstance(spec, Mosaic):
        return spec, None
    text = str(spec).strip()
    match = _TILE.match(text)
    if match:
        width, height = int(match.group(1)), int(match.group(2))
        where = f" from {origin}" if origin else ""
        if width < 1 or height < 1:
            raise DataFormatError(f"mosaic {text!r}{where}: tile sizes must be >= 1", path=path)
        check_tile((height, width), frame_shape, what=f"mosaic {text!r}{where}", path=path)
        return Mosaic.rectangular(height, width, name=f"{width}x{height}"), None
    xml = Path(text)
    if base is not None and not xml.is_absolute():
        xml = Path(base) / xml
    if xml.suffix.lower() != ".xml":
        raise DataFormatError(f"mosaic {text!r} is not 4x4, 5x5, WxH (e.g. 5x5) or the path of "
                              "an IMEC sensor calibration .xml", path=path)
    if not xml.exists():
        raise DataFormatError(f"mosaic file {xml} not found; check the path", path=path)
    from ..spectral.imec import read_imec_xml

    cal = read_imec_xml(xml)
    if sources is not None:
        sources.append(xml)
    mosaic = cal.mosaic()
    fa = cal.filter_area
    check_tile(mosaic.tile_shape, (fa.height, fa.width),
               what=f"the IMEC pattern of {xml.name}" + (f" from {origin}" if origin else ""),
               path=path, frames="its filter area")
    check_tile(mosaic.tile_shape, frame_shape,
               what=f"the IMEC pattern of {xml.name}" + (f" from {origin}" if origin else ""),
               path=path)
    area = ActiveArea(fa.offset_y, fa.offset_x, fa.height, fa.width)
    return Mosaic(mosaic.pattern, mosaic.wavelengths_nm, (0, 0), name=mosaic.name,
                  fwhm_nm=mosaic.fwhm_nm), area


def check_tile(tile, frame_shape, *, what: str, path=None, frames: str = "the frames") -> None:
    """Refuse a mosaic tile larger than the frames it tiles (before anything of the tile's
    size is built: a 250 x 250 pattern is 62,500 bands).

    Parameters
    ----------
    tile : (int, int)
        (height, width) of the tile, px.
    frame_shape : (int, int) or None
        (H, W) of the frames (None: not checked).
    what : str
        The mosaic and where it came from, for the message.
    path : str or Path, optional
        The data file.
    frames : str
        What ``frame_shape`` is, for the message.

    Raises
    ------
    DataFormatError
        One line naming the mosaic, both sizes and the fix.
    """
    height, width = (int(t) for t in tile)
    if frame_shape is not None and (height > frame_shape[0] or width > frame_shape[1]):
        raise DataFormatError(
            f"{what}: a tile of {width} x {height} px (W x H) is larger than {frames} "
            f"({frame_shape[1]} x {frame_shape[0]} px); give the filter pattern's tile size "
            "(e.g. 4x4, 5x5) or the sensor's own XML", path=path)


def missing_field_error(path, name: str, *, sidecar=None) -> DataFormatError:
    """The error for a field none of the three sources gives.

    Parameters
    ----------
    path : str or Path
        The data file.
    name : str
        The missing field (a key of ``HOW_TO_GIVE``).
    sidecar : str or Path, optional
        The sidecar that was read, if any.

    Returns
    -------
    DataFormatError
        Naming the file, the field and the three ways to give it (not raised here).
    """
    side, option = HOW_TO_GIVE[name]
    where = f"in {Path(sidecar).name}" if sidecar else "in a sidecar hsiffc.toml next to it"
    return DataFormatError(
        f"no {name} for this file; give it (1) in the file itself (an hsiffc TIFF: "
        f"hsiffc import; ENVI/FITS header; TIFF EXIF ExposureTime), (2) {where} "
        f"([defaults] or a [[files]] entry: {side}), or (3) on the command line ({option})",
        path=path)


def missing_origin(name: str) -> str:
    """The origin shown for a field no source gives, with the ways to give it."""
    side, option = HOW_TO_GIVE[name]
    return (f"MISSING: give it in the file, in a sidecar hsiffc.toml ({side}) or on the "
            f"command line ({option})")


def _same(a, b) -> bool:
    if isinstance(a, Mosaic) or isinstance(b, Mosaic):
        return a == b
    try:
        return bool(np.all(np.asarray(a) == np.asarray(b)))
    except (TypeError, ValueError):
        return False


def _per_frame(layout: FileLayout, name, value, origin):
    arr = np.asarray(value, dtype=object if name in ("kind", "illumination") else None)
    if arr.ndim == 0:
        return value
    if arr.shape != (layout.n_frames,):
        raise DataFormatError(f"{name} from {origin} has {arr.size} values but the file has "
                              f"{layout.n_frames} frames; give one value or one per frame",
                              path=layout.path)
    return arr


def resolve_fields(layout: FileLayout, sidecar, overrides: Overrides, *,
                   missing: list | None = None,
                   sources: list | None = None) -> tuple[dict, dict]:
    """Fields and their origins for one file (overrides, then the file, then the sidecar).

    Parameters
    ----------
    layout : FileLayout
    sidecar : Sidecar or None
    overrides : Overrides
    missing : list, optional
        When given, a missing exposure time is not an error: it becomes NaN, its origin says
        "MISSING" and the field's name is appended here (for ``hsiffc info``).
    sources : list, optional
        Every IMEC XML read for the mosaic is appended here.

    Returns
    -------
    values : dict
        Field -> value; ``mosaic`` is a Mosaic, ``active_area`` an ActiveArea or absent.
    origins : dict
        Field -> where the value came from.
    """
    side = sidecar.fields_for(layout.path) if sidecar is not None else {}
    side_label = f"sidecar {sidecar.path.name}" if sidecar is not None else ""
    given = overrides.given()
    values, origins = {}, {}
    for name in ("exposure_ms", "kind", "illumination", "photons", "step", "bit_depth",
                 "mosaic", "bit_shift"):
        candidates = []
        if name in given:  # explicit beats implicit
            candidates.append((given[name], "--" + name.replace("_", "-")))
        if name in layout.fields:
            candidates.append((layout.fields[name], layout.origins.get(name, "file")))
        if name in side:
            candidates.append((side[name], side_label))
        if not candidates:
            continue
        value, origin = candidates[0]
        if name in given and len(candidates) > 1:
            # what the option replaced, kept in the origin (hsiffc info shows it); no warning:
            # the user asked for it
            origin += " (overrides " + "; ".join(
                f"{o} {_short(v)}" for v, o in candidates[1:]) + ")"
            candidates = candidates[:1]
        if name == "mosaic" and not isinstance(value, Mosaic):
            base = sidecar.path.parent if origin == side_label else None
            value, area = parse_mosaic(value, base=base, path=layout.path,
                                       frame_shape=layout.shape[:2], origin=origin,
                                       sources=sources)
            if area is not None:
                values["active_area"] = area
        elif name == "mosaic":  # a file's own mosaic (an hsiffc TIFF) is checked the same way
            check_tile(value.tile_shape, layout.shape[:2],
                       what=f"mosaic {value.describe()} from {origin}", path=layout.path)
        for other, other_origin in candidates[1:]:
            if name == "mosaic" and not isinstance(other, Mosaic):
                base = sidecar.path.parent if other_origin == side_label else None
                other = parse_mosaic(other, base=base, path=layout.path,
                                     frame_shape=layout.shape[:2], origin=other_origin,
                                     sources=sources)[0]
            if not _same(value, other):
                warnings.warn(f"{layout.path}: {name} from {other_origin} ({_short(other)}) "
                              f"ignored; the {origin} says {_short(value)} and comes first",
                              MetadataConflictWarning, stacklevel=3)
        if name in PER_FRAME_FIELDS:
            value = _per_frame(layout, name, value, origin)
        _check_range(layout, name, value, origin)
        if name == "kind":
            bad = sorted(set(np.atleast_1d(value).tolist()) - set(FRAME_KINDS))
            if bad:
                raise DataFormatError(f"kind {bad} from {origin} is not one of "
                                      f"{list(FRAME_KINDS)}", path=layout.path)
        values[name], origins[name] = value, origin
    if "exposure_ms" not in values:
        if missing is None:
            raise missing_field_error(layout.path, "exposure_ms",
                                      sidecar=None if sidecar is None else sidecar.path)
        values["exposure_ms"], origins["exposure_ms"] = np.nan, missing_origin("exposure_ms")
        missing.append("exposure_ms")
    for name, default in (("kind", "light"), ("illumination", "")):
        if name not in values:
            values[name], origins[name] = default, f"default ({default or 'unknown'})"
    return values, origins


def _check_range(layout: FileLayout, name: str, value, origin: str) -> None:
    """Refuse an exposure time that is not finite and >= 0 ms, or a bit shift outside 0..31,
    whichever source gave it (a file header, a sidecar or an option)."""
    if name == "exposure_ms":
        try:
            ms = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise DataFormatError(f"exposure_ms from {origin} is not a number "
                                  f"({_short(value)}); correct it there",
                                  path=layout.path) from None
        bad = ~np.isfinite(ms) | (ms < 0)
        if np.any(bad):
            first = float(ms[bad].flat[0]) if ms.ndim else float(ms)
            raise DataFormatError(f"exposure_ms {first!r} from {origin} is not a finite time "
                                  ">= 0 ms; correct it there", path=layout.path)
    elif name == "bit_shift":
        try:
            ok = not isinstance(value, bool) and float(value).is_integer()
        except (TypeError, ValueError):
            ok = False
        if not ok or not 0 <= float(value) <= 31:
            raise DataFormatError(f"bit_shift {value!r} from {origin} is not a whole number "
                                  "0..31; correct it there", path=layout.path)


def _short(value) -> str:
    if isinstance(value, Mosaic):
        return value.describe()
    arr = np.asarray(value, dtype=object)
    first = arr.item() if arr.ndim == 0 else arr.flat[0]
    first = first.item() if isinstance(first, np.generic) else first
    return repr(first) if arr.ndim == 0 else f"{arr.size} values from {first!r}"
