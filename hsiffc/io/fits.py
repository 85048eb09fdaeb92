"""FITS frames (needs astropy: ``pip install 'hsiffc[fits]'``).

The first HDU with a 2-D or 3-D image is read: ``NAXIS1`` columns, ``NAXIS2`` rows and, for
3-D data, ``NAXIS3`` frames. Sizes come from the header and are checked against the limits
before any data are read. Integer data stored with ``BZERO`` (16-bit unsigned as signed plus
32768) come back unsigned, as astropy scales them. Metadata from the header: ``EXPTIME`` or
``EXPOSURE`` (seconds, the FITS convention) -> ``exposure_ms``; ``IMAGETYP``/``FRAMETYP``
containing "dark"/"bias" -> kind "dark", "light"/"flat"/"object" -> "light";
``BITDEPTH`` -> bit depth; ``GAIN`` kept in ``meta``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from .layout import FileLayout
from .limits import ReadLimits

__all__ = ["open_fits"]

_DTYPES = {8: np.uint8, 16: np.int16, 32: np.int32, 64: np.int64, -32: np.float32,
           -64: np.float64}


def _fits_module():
    try:
        from astropy.io import fits
    except ImportError:
        raise DataFormatError("reading FITS files needs astropy; install it with "
                              "pip install 'hsiffc[fits]' (or pip install astropy)") from None
    return fits


def _kind(text: str):
    t = text.lower()
    if "dark" in t or "bias" in t:
        return "dark"
    if any(w in t for w in ("light", "flat", "object", "science")):
        return "light"
    return None


def open_fits(path, limits: ReadLimits) -> FileLayout:
    """Parse a FITS header and return its :class:`FileLayout` (no data read).

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
    fits = _fits_module()
    path = Path(path)
    try:
        hdul = fits.open(path, memmap=True, do_not_scale_image_data=True)
    except Exception as exc:  # astropy raises OSError, ValueError, ... on broken files
        raise DataFormatError(f"not a readable FITS file ({type(exc).__name__}: {exc}); check "
                              "the file or write it again", path=path) from exc
    try:
        index = None
        for i, hdu in enumerate(hdul):
            if hdu.header.get("NAXIS", 0) in (2, 3) and hdu.header.get("BITPIX") in _DTYPES:
                index = i
                break
        if index is None:
            raise DataFormatError("the FITS file holds no 2-D or 3-D image", path=path)
        head = hdul[index].header
        w, h = int(head["NAXIS1"]), int(head["NAXIS2"])
        n = int(head.get("NAXIS3", 1)) if head["NAXIS"] == 3 else 1
        bitpix = int(head["BITPIX"])
        bzero, bscale = head.get("BZERO", 0), head.get("BSCALE", 1)
        dtype = np.dtype(_DTYPES[bitpix])
        if bitpix == 16 and bzero == 32768 and bscale == 1:
            dtype = np.dtype(np.uint16)
        elif bitpix > 8 and (bzero != 0 or bscale != 1):
            dtype = np.dtype(np.float32)  # scaled integers: astropy returns physical values
        limits.check_frames(path=path, n_frames=n, shape=(h, w), itemsize=dtype.itemsize)
        info = hdul.fileinfo(index) or {}
        need = info.get("datLoc", 0) + n * h * w * abs(bitpix) // 8
        size = path.stat().st_size
        if size < need:
            raise DataFormatError(f"file is truncated: the header needs {need} bytes but the "
                                  f"file has {size}; copy it again", path=path)
    except BaseException:
        hdul.close()
        raise
    state = {"hdul": hdul}

    def read(k: int) -> np.ndarray:
        if state["hdul"] is None:
            state["hdul"] = fits.open(path, memmap=True, do_not_scale_image_data=True)
        data = state["hdul"][index].data
        frame = np.asarray(data if data.ndim == 2 else data[k])
        if dtype == np.uint16 and bitpix == 16:
            return (frame.astype(np.int32) + 32768).astype(np.uint16)
        if dtype.kind == "f" and bitpix > 0:
            return (frame * np.float64(bscale) + np.float64(bzero)).astype(dtype)
        return frame.astype(dtype)

    def close():
        if state["hdul"] is not None:
            state["hdul"].close()
            state["hdul"] = None

    layout = FileLayout(path=path, format="fits", n_frames=n, shape=(h, w), dtype=dtype,
                        read=read, close=close, parallel=False)
    for key in ("EXPTIME", "EXPOSURE"):
        if key in head:
            layout.give("exposure_ms", float(head[key]) * 1e3, f"file (FITS {key})")
            break
    for key in ("IMAGETYP", "FRAMETYP"):
        if key in head and _kind(str(head[key])):
            layout.give("kind", _kind(str(head[key])), f"file (FITS {key})")
            break
    if "BITDEPTH" in head:
        layout.give("bit_depth", int(head["BITDEPTH"]), "file (FITS BITDEPTH)")
    if "GAIN" in head:
        layout.meta["gain"] = float(head["GAIN"])
    return layout
