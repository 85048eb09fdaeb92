"""Reading and writing frames, sweeps and cubes.

* :func:`read_sweep` opens any supported input and returns a :class:`~hsiffc.Sweep`:
  an hsiffc TIFF (``.tif``/``.tiff``, see :mod:`hsiffc.io.tiff`) or an EMVA 1288 measurement
  (its descriptor ``.txt`` or the folder holding it, see :mod:`hsiffc.io.emva`).
* :func:`write_sweep` writes a sweep as an hsiffc TIFF (atomically).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataFormatError
from .emva import read_emva1288
from .tiff import TIFF_SUFFIXES, read_sweep_tiff, write_sweep
from .corrected import read_corrected  # noqa: E402  (outputs of hsiffc correct)

__all__ = ["read_sweep", "read_sweep_tiff", "read_emva1288", "write_sweep", "read_corrected"]

_ACCEPTED = ("an hsiffc TIFF (.tif/.tiff), an EMVA 1288 descriptor (.txt) or a folder holding "
             "one EMVA 1288 descriptor")


def read_sweep(path):
    """Read frames and their metadata from ``path`` into a :class:`~hsiffc.Sweep`.

    Parameters
    ----------
    path : str or Path
        ``.tif``/``.tiff`` -> :func:`read_sweep_tiff`; ``.txt`` or a folder ->
        :func:`read_emva1288` (exposure times in the descriptor taken as ns, the EMVA 1288
        convention; call :func:`read_emva1288` directly to choose another unit).

    Raises
    ------
    DataFormatError
        The path does not exist or is none of the accepted inputs (the message lists them), or
        the file itself is invalid.
    """
    path = Path(path)
    if not path.exists():
        raise DataFormatError(f"not found; give {_ACCEPTED}", path=path)
    if path.is_dir():
        return read_emva1288(path)
    suffix = path.suffix.lower()
    if suffix in TIFF_SUFFIXES:
        return read_sweep_tiff(path)
    if suffix == ".txt":
        return read_emva1288(path)
    raise DataFormatError(f"unsupported input {path.name!r}; give {_ACCEPTED}", path=path)
