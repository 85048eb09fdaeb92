"""Sidecar files: metadata for image files that do not carry their own.

A sidecar is a small text file next to the data, named ``hsiffc.toml`` or ``hsiffc.csv``
(or given with ``--sidecar PATH``). It maps file names or globs (matched against the name of
each data file, relative to the sidecar's folder) to metadata fields:

================  ==================================================================
field             meaning
================  ==================================================================
``exposure_ms``   exposure time in milliseconds (TOML: one number, or one per frame)
``kind``          ``"light"`` or ``"dark"``
``illumination``  label of the light source (``"halogen 3200K"``); "" for darks
``bit_depth``     ADC bits; full scale is ``2**bit_depth - 1`` DN
``bit_shift``     right shift applied to every value (10/12-bit data left-aligned in
                  16-bit words: 6 or 4)
``mosaic``        ``"4x4"``, ``"5x5"``, ``"WxH"`` (tile width x height) or the path of an
                  IMEC sensor calibration XML (relative to the sidecar)
``photons``       mean photons per pixel per frame (if known)
================  ==================================================================

TOML::

    [defaults]            # every file of the folder
    bit_depth = 8
    mosaic = "CMV2K-SSM5x5-600_875-5.5.9.2.xml"

    [[files]]
    match = "dark_*.tif"
    kind = "dark"
    exposure_ms = 20.0

    [[files]]
    match = "white_*.tif"
    kind = "light"
    exposure_ms = 20.0
    illumination = "halogen"

CSV (a header row naming the columns; ``file`` holds a name or glob; empty cells are "not
given")::

    file,kind,exposure_ms,bit_depth
    dark_*.tif,dark,20,8
    white_*.tif,light,20,8

Every entry whose pattern matches a file applies, in the order written ([defaults] first), a
later entry overriding an earlier one. Unknown fields are an error naming the sidecar, and so are
values out of range: an exposure time that is negative, infinite or NaN, a photon count that is
negative or infinite (NaN means unknown), a ``bit_depth`` outside 1..32 or a ``bit_shift``
outside 0..31.
"""

from __future__ import annotations

import csv
import fnmatch
import math
from pathlib import Path

from ..errors import DataFormatError

__all__ = ["Sidecar", "SIDECAR_NAMES", "SIDECAR_FIELDS", "find_sidecar"]

SIDECAR_NAMES = ("hsiffc.toml", "hsiffc.csv")
SIDECAR_FIELDS = {"exposure_ms": float, "kind": str, "illumination": str, "bit_depth": int,
                  "bit_shift": int, "mosaic": str, "photons": float}


def find_sidecar(folder) -> Path | None:
    """The sidecar in ``folder`` (``hsiffc.toml``, else ``hsiffc.csv``), or None.

    Parameters
    ----------
    folder : str or Path
        Folder of the data files.

    Returns
    -------
    Path or None

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     none = find_sidecar(folder)
    ...     _ = (Path(folder) / "hsiffc.csv").write_text("file,exposure_ms\\n")
    ...     print(none, find_sidecar(folder).name)
    None hsiffc.csv
    """
    for name in SIDECAR_NAMES:
        candidate = Path(folder) / name
        if candidate.is_file():
            return candidate
    return None


def _convert(path, where, key, value):
    if key not in SIDECAR_FIELDS:
        raise DataFormatError(f"{where}: unknown field {key!r}; use {sorted(SIDECAR_FIELDS)}",
                              path=path)
    kind = SIDECAR_FIELDS[key]

    def one(v):
        if isinstance(v, (bool, list, dict)):
            raise ValueError
        if kind is str:
            return str(v)
        number = float(v)
        if kind is int and number != int(number):
            raise ValueError
        return kind(number)

    values = value if isinstance(value, list) and key in ("exposure_ms", "photons") else [value]
    what = {str: "text", int: "whole number", float: "number"}[kind]
    try:
        out = [one(v) for v in values]
    except (TypeError, ValueError, OverflowError):
        raise DataFormatError(f"{where}: {key} = {value!r} is not a valid {what}",
                              path=path) from None
    valid, expected = _RANGES.get(key, (None, ""))
    for v in out:
        if valid is not None and not valid(v):
            raise DataFormatError(f"{where}: {key} = {v!r} is out of range; give {expected}",
                                  path=path)
    return out if isinstance(value, list) else out[0]


#: Field -> (test of one value, what a valid value is); values outside are refused on reading.
_RANGES = {
    "exposure_ms": (lambda v: math.isfinite(v) and v >= 0,
                    "a finite exposure time >= 0 in milliseconds"),
    "photons": (lambda v: math.isnan(v) or (math.isfinite(v) and v >= 0),
                "a finite number of photons >= 0 (or leave it out when unknown)"),
    "bit_depth": (lambda v: 1 <= v <= 32, "a whole number of ADC bits 1..32"),
    "bit_shift": (lambda v: 0 <= v <= 31,
                  "a whole number 0..31 (the bits every sample is shifted right by)"),
}


class Sidecar:
    """A parsed sidecar: ordered (pattern, fields) rules.

    Parameters
    ----------
    path : str or Path
        ``.toml`` or ``.csv`` file (see the module docstring).
    """

    def __init__(self, path):
        self.path = Path(path)
        self.rules: list[tuple[str, dict]] = []
        from ..files.atomic import require_regular_input

        require_regular_input(self.path, what="sidecar")  # missing, or a FIFO: never opened
        try:
            text = self.path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise DataFormatError(f"cannot read the sidecar ({exc})", path=self.path) from exc
        if self.path.suffix.lower() == ".csv":
            self._parse_csv(text)
        else:
            self._parse_toml(text)

    def _parse_toml(self, text):
        from ..files.parsers import load_toml

        doc = load_toml(text, path=self.path, what="sidecar", hint="see the sidecar format in "
                        "docs/formats-and-metadata.md")
        unknown = sorted(set(doc) - {"defaults", "files"})
        if unknown:
            raise DataFormatError(f"unknown tables {unknown}; use [defaults] and [[files]] "
                                  "entries", path=self.path)
        defaults = doc.get("defaults", {})
        if not isinstance(defaults, dict):
            raise DataFormatError("[defaults] must be a table", path=self.path)
        self.rules.append(("*", {k: _convert(self.path, "[defaults]", k, v)
                                 for k, v in defaults.items()}))
        entries = doc.get("files", [])
        if not isinstance(entries, list):
            raise DataFormatError("'files' must be [[files]] entries", path=self.path)
        for i, entry in enumerate(entries, start=1):
            where = f"[[files]] entry {i}"
            if not isinstance(entry, dict) or not isinstance(entry.get("match"), str):
                raise DataFormatError(f"{where} needs match = \"<file name or glob>\"",
                                      path=self.path)
            self.rules.append((entry["match"], {k: _convert(self.path, where, k, v)
                                                for k, v in entry.items() if k != "match"}))

    def _parse_csv(self, text):
        rows = list(csv.reader(text.splitlines()))
        rows = [r for r in rows if r and any(c.strip() for c in r)
                and not r[0].lstrip().startswith("#")]
        if not rows or "file" not in [c.strip() for c in rows[0]]:
            raise DataFormatError("the first row must name the columns, one of them 'file' "
                                  "(a file name or glob)", path=self.path)
        header = [c.strip() for c in rows[0]]
        for lineno, row in enumerate(rows[1:], start=2):
            if len(row) != len(header):
                raise DataFormatError(f"row {lineno} has {len(row)} cells but the header has "
                                      f"{len(header)}", path=self.path)
            cells = {h: c.strip() for h, c in zip(header, row) if c.strip()}
            pattern = cells.pop("file", "")
            if not pattern:
                raise DataFormatError(f"row {lineno} has no file name or glob", path=self.path)
            self.rules.append((pattern, {k: _convert(self.path, f"row {lineno}", k, v)
                                         for k, v in cells.items()}))

    def fields_for(self, path) -> dict:
        """The fields that apply to data file ``path`` (later matching rules win).

        Parameters
        ----------
        path : str or Path
            A data file.

        Returns
        -------
        dict
            Field name -> value (exposure in ms, bit depth, kind, ...).
        """
        path = Path(path)
        try:
            rel = path.resolve().relative_to(self.path.parent.resolve()).as_posix()
        except ValueError:
            rel = path.name
        out: dict = {}
        for pattern, fields in self.rules:
            if fnmatch.fnmatchcase(rel, pattern) or fnmatch.fnmatchcase(path.name, pattern):
                out.update(fields)
        return out

    def describe(self, path) -> str:
        """Origin label of values taken from this sidecar.

        Parameters
        ----------
        path : str or Path
            The data file the values apply to.

        Returns
        -------
        str
            E.g. ``"sidecar hsiffc.toml"``.
        """
        return f"sidecar {self.path.name}"
