"""Which reader opens which file: suffix -> format module, and the image files of a folder."""

from __future__ import annotations

from pathlib import Path

from ..errors import DataFormatError
from .layout import FileLayout
from .limits import ReadLimits

__all__ = ["open_layout", "list_folder", "IMAGE_SUFFIXES", "ACCEPTED"]

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
    """Image files directly in ``folder`` sorted by name; or its EMVA 1288 descriptor."""
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
    """Parse the header of one file with the reader its suffix names."""
    path = Path(path)
    if not path.exists():
        raise DataFormatError("file not found; check the path", path=path)
    if path.is_dir():
        raise DataFormatError("is a folder; give a file (folders are expanded by open_source)",
                              path=path)
    suffix = path.suffix.lower()
    if suffix in TIFF:
        from .tiffpages import open_tiff
        return open_tiff(path, limits)
    if suffix in PNG:
        from .images import open_png
        return open_png(path, limits)
    if suffix in ENVI_HEADER or (suffix in ENVI_DATA and path.with_suffix(".hdr").is_file()):
        from .envi import open_envi
        return open_envi(path, limits)
    if suffix in FITS:
        from .fits import open_fits
        return open_fits(path, limits)
    if suffix == ".txt":
        from .emva import open_emva1288
        return open_emva1288(path, limits)
    raise DataFormatError(f"unsupported input {path.name!r}; give {ACCEPTED}", path=path)
