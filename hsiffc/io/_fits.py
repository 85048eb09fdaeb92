"""FITS frames (needs astropy: ``pip install 'hsiffc[fits]'``).

The first HDU with a 2-D or 3-D image is read: ``NAXIS1`` columns, ``NAXIS2`` rows and, for
3-D data, ``NAXIS3`` frames. Sizes come from the header and are checked against the limits
before any data are read. Unsigned integers stored by the FITS convention (signed plus
``BZERO`` = 2**15, 2**31 or 2**63 with ``BSCALE`` = 1) come back as exact ``uint16`` /
``uint32`` / ``uint64``, and signed bytes (``BITPIX`` 8 with ``BZERO`` = -128) as ``int8``;
other scaled integers come back as their physical values ``BSCALE * stored + BZERO`` in
``float32`` (8/16-bit) or ``float64`` (32/64-bit). Metadata from the header: ``EXPTIME`` or
``EXPOSURE`` (seconds, the FITS convention) -> ``exposure_ms``; ``IMAGETYP``/``FRAMETYP``
containing "dark"/"bias" -> kind "dark", "light"/"flat"/"object" -> "light";
``BITDEPTH`` -> bit depth; ``GAIN`` kept in ``meta``. An image in an extension behind an
empty primary HDU also takes the keywords only the primary header holds (unless the extension
says ``INHERIT = F``). A value of these keywords that is not a
number (or, for ``EXPTIME``/``EXPOSURE``, not a finite time >= 0; for ``BITDEPTH``, not a whole
number 1..32) is an error naming the file and the keyword. A damaged file is an error naming
the file; astropy's warnings about it are folded into that message, never printed.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from ._layout import FileLayout
from ..files.limits import ReadLimits

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


def _number(head, key: str, path, *, whole: bool = False, default=None):
    """The numeric value of header keyword ``key`` (``default`` when absent), or a one-line
    DataFormatError naming the file and the keyword."""
    if key not in head:
        return default
    value = head[key]
    number = None
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
            value, (bool, np.bool_)):
        number = float(value)
    elif isinstance(value, str):
        try:
            number = float(value.strip())
        except ValueError:
            number = None
    if number is None or not np.isfinite(number) or (whole and not number.is_integer()):
        raise DataFormatError(f"FITS keyword {key} = {value!r} is not a "
                              f"{'whole ' if whole else 'finite '}number; correct the header",
                              path=path)
    return int(number) if whole else number


def _hint(caught) -> str:
    """The first warning astropy gave while reading, as one short parenthesis (or "")."""
    if not caught:
        return ""
    return " (astropy: " + " ".join(str(caught[0].message).split())[:160] + ")"


def _damaged(path, exc, caught, what="not a readable FITS file") -> DataFormatError:
    """One-line error for a file astropy cannot read, with its first warning as a hint."""
    return DataFormatError(f"{what} ({type(exc).__name__}: {' '.join(str(exc).split())})"
                           f"{_hint(caught)}; check the file or write it again", path=path)


def _stored_type(bitpix: int, bzero: float, bscale: float) -> np.dtype:
    """The dtype frames come back in, from BITPIX, BZERO and BSCALE (see the module doc)."""
    if bscale == 1 and bitpix in (16, 32, 64) and bzero == 2.0 ** (bitpix - 1):
        return np.dtype(f"u{bitpix // 8}")
    if bscale == 1 and bitpix == 8 and bzero == -128:
        return np.dtype(np.int8)
    if bitpix > 0 and (bzero != 0 or bscale != 1):
        return np.dtype(np.float32 if bitpix <= 16 else np.float64)
    return np.dtype(_DTYPES[bitpix])


def _physical(frame: np.ndarray, bitpix: int, bzero: float, bscale: float,
              dtype: np.dtype) -> np.ndarray:
    """Stored FITS values (big-endian, as in the file) as ``dtype``, exactly for integers."""
    if dtype.kind == "u" and bitpix > 8:  # flip the sign bit: stored + 2**(bitpix-1), exact
        signed = frame.astype(np.dtype(f"i{bitpix // 8}"))
        return signed.view(dtype) ^ dtype.type(1 << (bitpix - 1))
    if dtype == np.int8:
        return (frame.astype(np.int16) - 128).astype(np.int8)
    if dtype.kind == "f" and bitpix > 0:
        return (frame * np.float64(bscale) + np.float64(bzero)).astype(dtype)
    return frame.astype(dtype)


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
        Unreadable, truncated or unsupported file, a header over the limits, or a header
        keyword hsiffc reads that holds no valid number.
    """
    fits = _fits_module()
    path = Path(path)
    # astropy reads HDUs lazily and reports damage as warnings (then, sometimes, an OSError):
    # they are recorded here, not printed, and become part of the one-line error
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            hdul = fits.open(path, memmap=True, do_not_scale_image_data=True)
        except Exception as exc:  # astropy raises OSError, ValueError, ... on broken files
            raise _damaged(path, exc, caught) from exc
        try:
            index = None
            try:
                for i, hdu in enumerate(hdul):
                    if (isinstance(hdu, (fits.PrimaryHDU, fits.ImageHDU))
                            and hdu.header.get("NAXIS", 0) in (2, 3)
                            and hdu.header.get("BITPIX") in _DTYPES):
                        index = i
                        break
            except (OSError, ValueError, TypeError, KeyError) as exc:
                raise _damaged(path, exc, caught) from exc
            if index is None:
                raise DataFormatError(f"the FITS file holds no 2-D or 3-D image{_hint(caught)}; "
                                      "check the file or write it again", path=path)
            head = hdul[index].header
            w, h = (_number(head, k, path, whole=True) for k in ("NAXIS1", "NAXIS2"))
            n = _number(head, "NAXIS3", path, whole=True, default=1) if head["NAXIS"] == 3 \
                else 1
            bitpix = int(head["BITPIX"])
            bzero = _number(head, "BZERO", path, default=0.0)
            bscale = _number(head, "BSCALE", path, default=1.0)
            dtype = _stored_type(bitpix, bzero, bscale)
            limits.check_frames(path=path, n_frames=n, shape=(h, w), itemsize=dtype.itemsize)
            info = hdul.fileinfo(index) or {}
            need = info.get("datLoc", 0) + _stored_bytes(hdul[index], fits, n * h * w *
                                                         abs(bitpix) // 8)
            size = path.stat().st_size
            if size < need:
                raise DataFormatError(f"file is truncated: the header needs {need} bytes but "
                                      f"the file has {size}; copy it again", path=path)
            fields = _header_fields(head, path)
            gain = _number(head, "GAIN", path) if "GAIN" in head else None
            primary = hdul[0].header
            if index > 0 and _inherits(head, primary):
                # an image extension behind an empty primary HDU (the common camera layout):
                # the keywords only the primary header holds apply to it (FITS INHERIT)
                for name, (value, origin) in _header_fields(primary, path).items():
                    fields.setdefault(name, (value, origin + ", primary header"))
                if gain is None and "GAIN" in primary:
                    gain = _number(primary, "GAIN", path)
        except BaseException:
            hdul.close()
            raise
    state = {"hdul": hdul}

    def read(k: int) -> np.ndarray:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                if state["hdul"] is None:
                    state["hdul"] = fits.open(path, memmap=True, do_not_scale_image_data=True)
                data = state["hdul"][index].data
                frame = np.asarray(data if data.ndim == 2 else data[k])
            except (OSError, ValueError, TypeError) as exc:
                raise _damaged(path, exc, caught, f"frame {k} cannot be read") from exc
        return _physical(frame, bitpix, bzero, bscale, dtype)

    def close():
        if state["hdul"] is not None:
            state["hdul"].close()
            state["hdul"] = None

    layout = FileLayout(path=path, format="fits", n_frames=n, shape=(h, w), dtype=dtype,
                        read=read, close=close, parallel=False)
    for name, (value, origin) in fields.items():
        layout.give(name, value, origin)
    if gain is not None:
        layout.meta["gain"] = gain
    return layout


def _stored_bytes(hdu, fits, image_bytes: int) -> int:
    """Bytes the data of ``hdu`` take in the file: the image's size, or for a tile-compressed
    image (``CompImageHDU``, what fpack writes) the size of its binary table and heap
    (``NAXIS1 * NAXIS2 + PCOUNT`` of the table header), which is far below the image's."""
    if not isinstance(hdu, fits.CompImageHDU):
        return image_bytes
    table = getattr(getattr(hdu, "_bintable", None), "header", None)
    if table is None:  # another astropy layout: the header gives no compressed size to check
        return 0
    try:
        return int(table["NAXIS1"]) * int(table["NAXIS2"]) + int(table.get("PCOUNT", 0))
    except (KeyError, TypeError, ValueError):
        return 0


def _inherits(head, primary) -> bool:
    """Whether an image extension takes the primary header's keywords: its primary HDU holds
    no data (``NAXIS = 0``) and the extension does not say ``INHERIT = F``."""
    return int(primary.get("NAXIS", 0) or 0) == 0 and head.get("INHERIT", True) is not False


def _header_fields(head, path) -> dict:
    """Field -> (value, origin) of the metadata keywords hsiffc reads from a FITS header."""
    fields = {}
    for key in ("EXPTIME", "EXPOSURE"):
        if key in head:
            seconds = _number(head, key, path)
            if seconds < 0:
                raise DataFormatError(f"FITS keyword {key} = {head[key]!r} is not an exposure "
                                      "time >= 0 s; correct the header", path=path)
            fields["exposure_ms"] = (seconds * 1e3, f"file (FITS {key})")
            break
    for key in ("IMAGETYP", "FRAMETYP"):
        if key in head and _kind(str(head[key])):
            fields["kind"] = (_kind(str(head[key])), f"file (FITS {key})")
            break
    if "BITDEPTH" in head:
        bits = _number(head, "BITDEPTH", path, whole=True)
        if not 1 <= bits <= 32:
            raise DataFormatError(f"FITS keyword BITDEPTH = {head['BITDEPTH']!r} is not a bit "
                                  "depth 1..32; correct the header", path=path)
        fields["bit_depth"] = (bits, "file (FITS BITDEPTH)")
    return fields
