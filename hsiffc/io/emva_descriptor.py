"""The descriptor of an EMVA 1288 measurement: finding it in a folder, parsing its lines, and
the image files it names (the format is described in :mod:`hsiffc.io.emva`, whose reader
builds the sweep from what this module parses)."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import numpy as np

from ..errors import DataFormatError

__all__ = ["DEFAULT_DESCRIPTOR_NAME", "emva_files", "find_emva_descriptor",
           "has_emva_descriptor", "image_path", "parse_descriptor"]

DEFAULT_DESCRIPTOR_NAME = "EMVA1288_Data.txt"
_VERSION_LINE = re.compile(r"^\s*v\s+\S", re.MULTILINE)


def has_emva_descriptor(folder) -> bool:
    """True when ``folder`` holds exactly one EMVA 1288 descriptor.

    Parameters
    ----------
    folder : str or Path
        Any folder.

    Returns
    -------
    bool
    """
    try:
        find_emva_descriptor(folder)
    except DataFormatError:
        return False
    return True


def find_emva_descriptor(folder) -> Path:
    """The descriptor of an EMVA 1288 measurement folder.

    ``EMVA1288_Data.txt`` if present, otherwise the only ``*.txt`` file that has a ``v`` line.

    Parameters
    ----------
    folder : str or Path
        The measurement folder.

    Returns
    -------
    Path

    Raises
    ------
    DataFormatError
        No descriptor, or several candidates (the message lists them).
    """
    folder = Path(folder)
    named = folder / DEFAULT_DESCRIPTOR_NAME
    if named.is_file():
        return named
    found = []
    for txt in sorted(folder.glob("*.txt")):
        try:
            if not stat.S_ISREG(os.stat(txt).st_mode):
                continue  # a FIFO, device or socket named *.txt is never opened (it may block)
            text = txt.read_text(errors="replace")
        except OSError:
            continue
        if _VERSION_LINE.search(text):
            found.append(txt)
    if len(found) == 1:
        return found[0]
    if not found:
        raise DataFormatError(
            f"no EMVA 1288 descriptor in this folder (looked for {DEFAULT_DESCRIPTOR_NAME} or a "
            "*.txt file with a 'v <version>' line); give the descriptor file itself", path=folder)
    raise DataFormatError(
        f"several EMVA 1288 descriptors in this folder ({', '.join(p.name for p in found)}); "
        "give the one to read as a file path", path=folder)


class _Step:
    __slots__ = ("kind", "exposure", "photons", "line", "images")

    def __init__(self, kind, exposure, photons, line):
        self.kind, self.exposure, self.photons, self.line = kind, exposure, photons, line
        self.images: list[tuple[str, int]] = []  # (path text, line number)


def _numbers(parts, count, descriptor, lineno, line, usage):
    if len(parts) - 1 not in count:
        raise DataFormatError(f"line {lineno}: malformed {parts[0]!r} line {line!r}; expected "
                              f"{usage!r}", path=descriptor)
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError:
        raise DataFormatError(f"line {lineno}: {line!r} holds a value that is not a number; "
                              f"expected {usage!r}", path=descriptor) from None
    if not all(np.isfinite(values)) or any(v < 0 for v in values):
        raise DataFormatError(f"line {lineno}: {line!r} holds a negative or non-finite value; "
                              f"expected {usage!r}", path=descriptor)
    return values


def emva_files(path) -> list[Path]:
    """The files of an EMVA 1288 measurement: its descriptor and every image its ``i`` lines
    name (whether or not they exist), as :func:`open_emva1288` would read them; the command
    line protects them all from being written.

    Parameters
    ----------
    path : str or Path
        The descriptor ``.txt`` or its folder.

    Raises
    ------
    DataFormatError
        No descriptor, or an invalid descriptor line.
    """
    path = Path(path)
    descriptor = find_emva_descriptor(path) if path.is_dir() else path
    _, steps = parse_descriptor(descriptor)
    return [descriptor] + [descriptor.parent / image_path(name) for s in steps
                           for name, _ in s.images]


def image_path(name: str) -> str:
    """An ``i`` line's image path, relative to the descriptor's folder (``\\`` as ``/``)."""
    return name.replace("\\", "/")


def parse_descriptor(descriptor: Path):
    from ..files.atomic import require_regular_input

    require_regular_input(descriptor, what="EMVA 1288 descriptor")
    try:
        text = descriptor.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DataFormatError(f"cannot read the descriptor ({exc}); check the file permissions",
                              path=descriptor) from exc
    header = {"version": None, "bits": None, "width": None, "height": None, "comments": []}
    steps: list[_Step] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            header["comments"].append(line[1:].strip())
            continue
        parts = line.split()
        tag = parts[0]
        if tag == "v":
            if len(parts) != 2:
                raise DataFormatError(f"line {lineno}: malformed version line {line!r}; expected "
                                      "'v <version>'", path=descriptor)
            header["version"] = parts[1]
        elif tag == "n":
            usage = "n <bits> <width> <height>"
            values = _numbers(parts, (3,), descriptor, lineno, line, usage)
            if not all(v == int(v) for v in values):
                raise DataFormatError(f"line {lineno}: {line!r} must hold whole numbers; expected "
                                      f"{usage!r}", path=descriptor)
            bits, width, height = (int(v) for v in values)
            if not 1 <= bits <= 16:
                raise DataFormatError(f"line {lineno}: unknown bit depth {bits} in {line!r}; "
                                      "EMVA 1288 images have 1..16 bits", path=descriptor)
            if width < 1 or height < 1:
                raise DataFormatError(f"line {lineno}: image size must be positive in {line!r}",
                                      path=descriptor)
            if header["bits"] is not None and (bits, width, height) != (
                    header["bits"], header["width"], header["height"]):
                raise DataFormatError(f"line {lineno}: second 'n' line {line!r} contradicts the "
                                      "first; keep one", path=descriptor)
            header.update(bits=bits, width=width, height=height)
        elif tag == "b":
            exposure, photons = _numbers(parts, (2,), descriptor, lineno, line,
                                         "b <exposure> <photons>")
            steps.append(_Step("light", exposure, photons, lineno))
        elif tag == "d":
            values = _numbers(parts, (1, 2), descriptor, lineno, line, "d <exposure>")
            if len(values) == 2 and values[1] != 0:
                raise DataFormatError(f"line {lineno}: a dark step cannot have photons "
                                      f"({line!r}); use 'd <exposure>'", path=descriptor)
            steps.append(_Step("dark", values[0], np.nan, lineno))
        elif tag == "i":
            name = line[1:].strip()
            if not name:
                raise DataFormatError(f"line {lineno}: 'i' line without an image path",
                                      path=descriptor)
            if not steps:
                raise DataFormatError(f"line {lineno}: image {name!r} comes before any 'b' or "
                                      "'d' step line; put it after the step it belongs to",
                                      path=descriptor)
            steps[-1].images.append((name, lineno))
        else:
            raise DataFormatError(f"line {lineno}: malformed line {line!r}; EMVA 1288 descriptor "
                                  "lines start with #, v, n, b, d or i", path=descriptor)
    if header["bits"] is None:
        raise DataFormatError("unknown bit depth: the descriptor has no 'n <bits> <width> "
                              "<height>' line; add it before the steps", path=descriptor)
    if not steps:
        raise DataFormatError("the descriptor has no 'b' or 'd' step; nothing to read",
                              path=descriptor)
    for s in steps:
        if not s.images:
            raise DataFormatError(f"line {s.line}: the step on this line has no 'i' image lines; "
                                  "add its images or remove the step", path=descriptor)
    return header, steps
