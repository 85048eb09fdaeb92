"""Which reader opens which file: suffix -> format module, and the image files of a folder."""

from __future__ import annotations

import glob as globmod
from pathlib import Path

from ..errors import DataFormatError
from ._layout import FileLayout
from ..files.limits import ReadLimits

__all__ = ["open_layout", "list_folder", "expand_inputs", "IMAGE_SUFFIXES", "ACCEPTED"]

TIFF = (".tif", ".tiff")
PNG = (".png",)
ENVI_HEADER = (".hdr",)
ENVI_DATA = (".img", ".raw", ".dat", ".bsq", ".bil", ".bip", "")
FITS = (".fits", ".fit", ".fts")
#: Suffixes of files a folder contributes to a stack (ENVI pairs through their ``.hdr``).
IMAGE_SUFFIXES = TIFF + PNG + ENVI_HEADER + FITS
ACCEPTED = ("TIFF (.tif/.tiff), PNG, ENVI (.hdr + data), FITS (.fits), an EMVA 1288 "
            "descriptor (.txt), or a folder of them")


def list_folder(folder: Path) -> list[Path]:
    """Image files directly in ``folder`` sorted by name; or its EMVA 1288 descriptor.

    Parameters
    ----------
    folder : Path
        The folder.

    Returns
    -------
    list of Path
    """
    from .emva import find_emva_descriptor, has_emva_descriptor

    if has_emva_descriptor(folder):
        return [find_emva_descriptor(folder)]
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DataFormatError(f"no image file in this folder; it must hold {ACCEPTED}",
                              path=folder)
    return files


def open_layout(path, limits: ReadLimits) -> FileLayout:
    """Parse the header of one file with the reader its suffix names.

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
    from ..files.atomic import require_regular_input

    path = Path(path)
    if not path.exists():
        raise DataFormatError("file not found; check the path", path=path)
    if path.is_dir():
        raise DataFormatError("is a folder; give a file (folders are expanded by open_source)",
                              path=path)
    require_regular_input(path)  # a FIFO or device is refused before anything opens it
    suffix = path.suffix.lower()
    if suffix in TIFF:
        from .tiff import open_tiff
        return open_tiff(path, limits)
    if suffix in PNG:
        from ._images import open_png
        return open_png(path, limits)
    if suffix in ENVI_HEADER or (suffix in ENVI_DATA and path.with_suffix(".hdr").is_file()):
        from .envi import open_envi
        return open_envi(path, limits)
    if suffix in FITS:
        from ._fits import open_fits
        return open_fits(path, limits)
    if suffix == ".txt":
        from .emva import open_emva1288
        return open_emva1288(path, limits)
    raise DataFormatError(f"unsupported input {path.name!r}; give {ACCEPTED}", path=path)


def expand_inputs(inputs) -> list[Path]:
    """Files named by ``inputs`` (paths, folders, globs), in order; folders sorted by name.

    A folder that holds an EMVA 1288 descriptor stands for itself (the descriptor is read).

    Parameters
    ----------
    inputs : str, Path or sequence of them
        Files, folders or glob patterns.

    Returns
    -------
    list of Path
        Files in order (an empty list when nothing matches).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from hsiffc.io import expand_inputs
    >>> tmp = tempfile.TemporaryDirectory()
    >>> for name in ("b.tif", "a.tif", "notes.txt"):
    ...     _ = (Path(tmp.name) / name).write_bytes(b"")
    >>> [p.name for p in expand_inputs(tmp.name)]            # a folder: its image files by name
    ['a.tif', 'b.tif']
    >>> [p.name for p in expand_inputs(str(Path(tmp.name) / "b*.tif"))]   # a glob
    ['b.tif']
    >>> tmp.cleanup()
    """
    items = [inputs] if isinstance(inputs, (str, Path)) else list(inputs)
    out: list[Path] = []
    for item in items:
        text = str(item)
        if not Path(text).exists() and any(c in text for c in "*?["):
            matches = sorted(Path(m) for m in globmod.glob(text))
            if not matches:
                raise DataFormatError(f"no file matches the pattern {text!r}; check it (quote "
                                      "it so the shell does not expand it)")
            out.extend(m for m in matches if m.is_file())
            continue
        path = Path(text)
        if not path.exists():
            raise DataFormatError(f"not found; check the path (give {ACCEPTED})", path=path)
        out.extend(list_folder(path) if path.is_dir() else [path])
    return out
