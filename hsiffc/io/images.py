"""PNG frames (8- or 16-bit, one frame per file), as cameras and OpenCV/Pillow write them.

The header is read by hand before decoding: the ``IHDR`` chunk gives the size, bit depth and
colour type (checked against the size limits), the chunk chain must reach ``IEND`` inside the
file (else the file is truncated), and an ``sBIT`` chunk, when present, gives the significant
bits of the samples (e.g. 12 in a 16-bit PNG) as the bit depth. Palette PNGs are refused (they
do not hold counts). Gray+alpha and RGB(A) PNGs give 4- or 3-channel frames that
:mod:`hsiffc.io.quirks` reduces to one channel when the channels are equal.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from .layout import FileLayout
from .limits import ReadLimits

__all__ = ["open_png", "png_header"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels after OpenCV's IMREAD_UNCHANGED decoding
_CHANNELS = {0: 1, 2: 3, 4: 4, 6: 4}


def png_header(path) -> dict:
    """Facts of a PNG's chunks without decoding it: ``width``, ``height``, ``bit_depth`` (per
    sample), ``colour_type``, ``significant_bits`` (sBIT or None), ``text`` (tEXt chunks).

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    dict

    Raises
    ------
    DataFormatError
        Not a PNG, or the chunk chain ends before ``IEND`` (truncated file).
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        if fh.read(8) != _SIGNATURE:
            raise DataFormatError("not a PNG file (no PNG signature); check the file",
                                  path=path)
        facts = {"significant_bits": None, "text": {}}
        offset = 8
        while True:
            head = fh.read(8)
            if len(head) < 8:
                raise DataFormatError(f"file is truncated: the PNG chunk chain ends at byte "
                                      f"{offset} of {size} before IEND; copy or write it again",
                                      path=path)
            length, kind = struct.unpack(">I4s", head)
            if offset + 12 + length > size:
                raise DataFormatError(f"file is truncated: chunk {kind!r} needs bytes up to "
                                      f"{offset + 12 + length} but the file has {size}; copy or "
                                      "write it again", path=path)
            if kind in (b"IHDR", b"sBIT", b"tEXt"):
                body = fh.read(length)
                fh.seek(4, 1)
            else:
                body = b""
                fh.seek(length + 4, 1)
            offset += 12 + length
            if kind == b"IHDR":
                width, height, depth, colour = struct.unpack(">IIBB", body[:10])
                facts.update(width=width, height=height, bit_depth=depth, colour_type=colour)
            elif kind == b"sBIT" and body:
                facts["significant_bits"] = max(body)
            elif kind == b"tEXt" and b"\0" in body:
                key, _, value = body.partition(b"\0")
                facts["text"][key.decode("latin-1")] = value.decode("latin-1")[:500]
            elif kind == b"IEND":
                break
    if "width" not in facts:
        raise DataFormatError("the PNG has no IHDR header chunk; the file is damaged", path=path)
    return facts


def open_png(path, limits: ReadLimits) -> FileLayout:
    """Parse a PNG's header and return its :class:`FileLayout` (one frame, nothing decoded).

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
    path = Path(path)
    if path.stat().st_size == 0:
        raise DataFormatError("file is empty (0 bytes); copy or write it again", path=path)
    facts = png_header(path)
    colour, depth = facts["colour_type"], facts["bit_depth"]
    if colour == 3:
        raise DataFormatError("a palette (indexed-colour) PNG does not hold raw counts; save the "
                              "camera frame as a grayscale PNG", path=path)
    if colour not in _CHANNELS or depth not in (8, 16):
        raise DataFormatError(f"unsupported PNG colour type {colour} with {depth}-bit samples; "
                              "save the frame as an 8- or 16-bit grayscale PNG", path=path)
    dtype = np.dtype(np.uint16 if depth == 16 else np.uint8)
    channels = _CHANNELS[colour]
    shape = (facts["height"], facts["width"]) + ((channels,) if channels > 1 else ())
    limits.check_frames(path=path, n_frames=1, shape=shape, itemsize=dtype.itemsize)

    def read(k: int) -> np.ndarray:
        import cv2

        buffer = np.fromfile(path, dtype=np.uint8)
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        try:
            array = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if array is None:
            raise DataFormatError("the PNG cannot be decoded (damaged data); copy or write it "
                                  "again", path=path)
        return array

    layout = FileLayout(path=path, format="png", n_frames=1, shape=shape, dtype=dtype,
                        read=read)
    if facts["significant_bits"] and facts["significant_bits"] < depth:
        layout.give("bit_depth", int(facts["significant_bits"]), "file (PNG sBIT chunk)")
    if facts["text"]:
        layout.meta["png_text"] = facts["text"]
    return layout
