"""hsiffc's TIFF format: a stack of raw frames, one TIFF page per frame, plus one JSON document.

File layout
-----------
* Page ``k`` holds frame ``k`` of the sweep as a single-channel (H, W) image, in acquisition
  order, in the frames' own dtype (``uint8`` / ``uint16`` raw DN, or ``float32`` for averaged or
  processed frames; ``uint32``, signed ``int8``/``int16``/``int32`` and ``float64`` are also
  written as they are, e.g. by ``hsiffc import`` of a signed camera file). Values are never
  rescaled, clipped or wrapped, neither on writing nor on reading.
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
from pathlib import Path

import numpy as np
import tifffile

from ..files.jsonsafe import json_safe
from ..files.atomic import atomic_path
from ..errors import DataFormatError
from ..data.sweep import Sweep
from .document import (EXPOSURE_UNITS_MS, FORMAT_NAME, FORMAT_VERSION, exposure_to_ms,
                       parse_document)
from ..files.limits import default_limits
from .tiffpages import TIFF_SUFFIXES, open_tiff

__all__ = ["write_sweep", "read_sweep_tiff", "FORMAT_NAME", "FORMAT_VERSION", "EXPOSURE_UNITS_MS",
           "exposure_to_ms", "TIFF_SUFFIXES", "WRITABLE_DTYPES"]

#: the frame dtypes an hsiffc TIFF stores as they are
WRITABLE_DTYPES = (np.uint8, np.uint16, np.uint32, np.int8, np.int16, np.int32, np.float32,
                    np.float64)


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
        Output file; must end in ``.tif`` or ``.tiff``. A missing folder is created, as every
        hsiffc writer does.
    sweep : Sweep
        Frames (``uint8``, ``uint16``, ``uint32``, ``int8``, ``int16``, ``int32``, ``float32``
        or ``float64``; kept as they are, negative values included) and metadata. Exposure
        times are written in milliseconds. ``sweep.meta`` must be JSON-serialisable; NaN/inf
        inside it are written as ``null``.
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
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; give a file name ending in .tif")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) to replace it "
                              "(the existing file was left unchanged)")
    data = np.ascontiguousarray(sweep.data)
    if data.dtype.type not in WRITABLE_DTYPES:
        raise DataFormatError(
            f"cannot write frames of dtype {data.dtype}: an hsiffc TIFF stores (u)int8/16/32 or "
            "float32/64 frames and hsiffc does not change values to fit; convert the frames "
            "first if their values fit one of those (e.g. sweep.data.astype(np.float64))",
            path=path)
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
def read_sweep_tiff(path) -> Sweep:
    """Read an hsiffc TIFF into a :class:`~hsiffc.Sweep`.

    Plain TIFFs (without the hsiffc JSON document) are refused here; read them with
    :func:`hsiffc.io.read_sweep` or :func:`hsiffc.io.open_source`, which take their metadata
    from tags, a sidecar or keyword arguments.

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
        bit depth, integer data above ``2**bit_depth - 1``, or a header over the size limits
        (:mod:`hsiffc.files.limits`). Each message names the file, the problem and the fix.
        NaN/inf in float frames are *not* an error here.
    """
    from .metadata import Overrides
    from .source import FrameSource

    path = Path(path)
    if not path.exists():
        raise DataFormatError("file not found; check the path", path=path)
    if path.is_dir():
        raise DataFormatError("is a folder, not a TIFF file; give the .tif file", path=path)
    limits = default_limits()
    layout = open_tiff(path, limits)
    if not layout.strict:
        layout.close()
        parse_document(layout.meta.get("tiff_description", ""), path)  # raises the hint
    if len(layout.shape) != 2:
        layout.close()
        raise DataFormatError(f"pages must all be single-channel images of one shape, found "
                              f"{layout.shape}; write one (H, W) frame per page", path=path)
    with FrameSource([layout], Overrides(), limits, label=str(path)) as src:
        return src.to_sweep()

