"""The product file base: one versioned ``.npz`` of arrays plus a JSON manifest, no pickle.

Calibrations and fitted pipelines are both products (Rubin's calibration products are the
model): a ``format`` name (the product type), a ``format_version`` (schema), the hsiffc version
that wrote it, named arrays and a JSON manifest stored as a uint8 array ``manifest.json``.
Files are written atomically (never replacing an existing file unless asked) and read with
``allow_pickle=False``: no code is ever executed from a product file. Each product validates
itself against the data it is applied to (e.g. :meth:`hsiffc.calibrate.Calibration.check_compatible`).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from . import __version__
from .jsonsafe import json_safe
from .atomic import atomic_path
from .errors import DataFormatError

MANIFEST = "manifest.json"


def write_product(path, *, format: str, format_version: int, manifest: dict, arrays: dict,
                  overwrite: bool = False) -> Path:
    """Write a product file atomically.

    Parameters
    ----------
    path : path-like, ending in ``.npz``
    format, format_version : str, int
        Product type and schema version, stored first in the manifest.
    manifest : dict
        Description: plain values, numpy scalars or arrays and paths (converted by
        :func:`hsiffc.jsonsafe.json_safe`; non-finite floats become null).
    arrays : dict of str to ndarray
        Names must not be ``manifest.json``.
    overwrite : bool
        Replace an existing file (else FileExistsError, the file left unchanged).
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"{format} files end in .npz, got {path.name!r}")
    head = {"format": format, "format_version": int(format_version),
            "hsiffc_version": __version__}
    text = json.dumps(json_safe({**head, **manifest}, strict=True, what=f"the {format} manifest"),
                      indent=1).encode()
    payload = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    payload[MANIFEST] = np.frombuffer(text, dtype=np.uint8)
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)
    return path


def read_product(path, *, format: str, format_version: int, remedy: str) -> tuple[dict, dict]:
    """Read and check a product file.

    Parameters
    ----------
    path : path-like
    format, format_version : str, int
        The expected product type, and the newest schema version this hsiffc reads.
    remedy : str
        How to make a good file (ends the "not found" and "unreadable" messages).

    Returns
    -------
    manifest : dict
    arrays : dict of str to ndarray

    Raises
    ------
    DataFormatError
        Missing, unreadable or truncated file, no or invalid manifest, another product type or
        a newer schema; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{format} file not found; {remedy}", path=path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DataFormatError(f"not a readable {format} file ({exc}); it may be truncated: "
                              f"{remedy}", path=path) from exc
    if MANIFEST not in arrays:
        raise DataFormatError(f"no {MANIFEST} inside: not an hsiffc {format} file", path=path)
    try:
        manifest = json.loads(arrays.pop(MANIFEST).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataFormatError(f"the {MANIFEST} is not valid JSON: {exc}", path=path) from exc
    if not isinstance(manifest, dict) or manifest.get("format") != format:
        found = manifest.get("format") if isinstance(manifest, dict) else manifest
        raise DataFormatError(f"format is {found!r}, expected {format!r}", path=path)
    version = manifest.get("format_version", 0)
    if not isinstance(version, int) or version > format_version:
        raise DataFormatError(f"{format} format version {version!r} is newer than this hsiffc "
                              f"({__version__}) reads ({format_version}); upgrade hsiffc",
                              path=path)
    return manifest, arrays
