"""PNG frames (8- or 16-bit, one frame per file), as cameras and OpenCV/Pillow write them.

The header is read by hand before decoding: the ``IHDR`` chunk (the first chunk, 13 bytes,
only one) gives the size, bit depth and colour type (checked against the size limits), the
chunk chain must reach ``IEND`` inside the file (else the file is truncated), every chunk's
CRC and the inflated image data are checked before the decoder sees them (so libpng never
prints its own error lines), and an ``sBIT`` chunk, when present, gives the significant
bits of the samples (e.g. 12 in a 16-bit PNG) as the bit depth. Palette PNGs are refused (they
do not hold counts). Gray+alpha and RGB(A) PNGs give 4- or 3-channel frames that
:mod:`hsiffc.io._quirks` reduces to one channel when the channels are equal.

The image data are inflated once, by the check (libdeflate through imagecodecs, zlib where it
fails, to name the damage): the decoder gets them back as stored deflate blocks, a copy, and
only unfilters them (imagecodecs' libpng for grayscale, OpenCV for colour, whose channel order
the readers expect).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from ._layout import FileLayout
from ..files.limits import ReadLimits

__all__ = ["check_png_data", "decode_png", "open_png", "png_header"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels after OpenCV's IMREAD_UNCHANGED decoding
_CHANNELS = {0: 1, 2: 3, 4: 4, 6: 4}


# valid IHDR bit depths per colour type, and samples per pixel (PNG specification, 11.2.2)
_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
try:  # libdeflate's inflate and checksums, libpng's decoder (a dependency; zlib and OpenCV else)
    import imagecodecs as _codecs

    _crc32, _adler32 = _codecs.deflate_crc32, _codecs.deflate_adler32
except (ImportError, AttributeError):  # pragma: no cover - imagecodecs is a dependency
    _codecs = None
    _crc32, _adler32 = zlib.crc32, zlib.adler32
# Adam7 passes: (first column, first row, column step, row step)
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2),
          (0, 1, 1, 2))


def _damaged(path, what: str) -> DataFormatError:
    return DataFormatError(f"the PNG is damaged: {what}; copy or write it again", path=path)


def _ihdr(body: bytes, path) -> dict:
    """The fields of an IHDR chunk body, each checked against the PNG specification."""
    if len(body) != 13:
        raise _damaged(path, f"its IHDR header chunk is {len(body)} bytes, not 13")
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(
        ">IIBBBBB", body)
    if not (0 < width < 2 ** 31 and 0 < height < 2 ** 31):
        raise _damaged(path, f"its IHDR states a size of {width} x {height} pixels")
    if colour not in _DEPTHS or depth not in _DEPTHS[colour]:
        raise _damaged(path, f"its IHDR states colour type {colour} with {depth}-bit samples, "
                             "which PNG does not define")
    if compression or filtering or interlace not in (0, 1):
        raise _damaged(path, f"its IHDR states compression {compression}, filter method "
                             f"{filtering}, interlace {interlace} (PNG defines 0, 0 and 0/1)")
    return {"width": width, "height": height, "bit_depth": depth, "colour_type": colour,
            "interlace": interlace}


def png_header(path) -> dict:
    """Facts of a PNG's chunks without decoding it: ``width``, ``height``, ``bit_depth`` (per
    sample), ``colour_type``, ``interlace``, ``significant_bits`` (sBIT or None), ``text``
    (tEXt chunks).

    The ``IHDR`` chunk must come first, be 13 bytes and be the only one (a second header,
    which a decoder might read instead of the first, is refused).

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
        Not a PNG, a malformed or repeated IHDR, or the chunk chain ends before ``IEND``
        (truncated file).
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
            if (offset == 8) != (kind == b"IHDR"):
                raise _damaged(path, "its IHDR header chunk is not the first chunk or appears "
                                     "twice")
            if kind in (b"IHDR", b"sBIT", b"tEXt"):
                body = fh.read(length)
                fh.seek(4, 1)
            else:
                body = b""
                fh.seek(length + 4, 1)
            offset += 12 + length
            if kind == b"IHDR":
                facts.update(_ihdr(body, path))
            elif kind == b"sBIT" and body:
                facts["significant_bits"] = max(body)
            elif kind == b"tEXt" and b"\0" in body:
                key, _, value = body.partition(b"\0")
                facts["text"][key.decode("latin-1")] = value.decode("latin-1")[:500]
            elif kind == b"IEND":
                break
    return facts


def _inflated_rows(facts) -> list[tuple[int, int]]:
    """(rows, bytes per row with its filter byte) of each pass of the image's data stream."""
    bits = facts["bit_depth"] * _SAMPLES[facts["colour_type"]]
    w, h = facts["width"], facts["height"]
    passes = _ADAM7 if facts["interlace"] else ((0, 0, 1, 1),)
    out = []
    for x0, y0, dx, dy in passes:
        pw, ph = -(-(w - x0) // dx) if w > x0 else 0, -(-(h - y0) // dy) if h > y0 else 0
        if pw and ph:
            out.append((ph, 1 + -(-(pw * bits) // 8)))
    return out


def _idat_run(blob: bytes, path) -> tuple[int, int, bytes]:
    """Check every chunk's CRC up to ``IEND``; return where the one run of ``IDAT`` chunks
    starts and ends in ``blob``, and their bodies joined (the compressed image data)."""
    view = memoryview(blob)
    offset, idat, runs, last, start, end = 8, [], 0, None, 0, 0
    while offset + 12 <= len(blob):
        length, kind = struct.unpack_from(">I4s", blob, offset)
        body = view[offset + 8:offset + 8 + length]
        crc = blob[offset + 8 + length:offset + 12 + length]
        if len(crc) < 4:
            break
        if _crc32(body, _crc32(kind)) != struct.unpack(">I", crc)[0]:
            raise _damaged(path, f"chunk {kind.decode('latin-1')!r} at byte {offset} fails its "
                                 "CRC check")
        if kind == b"IDAT":
            if last != b"IDAT":
                runs, start = runs + 1, offset
            idat.append(body)
            end = offset + 12 + length
        last = kind
        offset += 12 + length
        if kind == b"IEND":
            break
    if not idat or runs != 1:
        raise _damaged(path, "its image data (IDAT chunks) are missing or not in one run")
    return start, end, b"".join(idat)


def _inflate(idat: bytes, facts: dict, path) -> bytes:
    """The image data inflated, checked to be exactly the size the header states with a valid
    filter type on every row."""
    rows = _inflated_rows(facts)
    expected = sum(n * stride for n, stride in rows)
    raw = None
    if _codecs is not None:  # libdeflate: 2-3 x faster than zlib's inflate
        try:
            raw = _codecs.deflate_decode(idat, out=expected)
        except Exception:  # imagecodecs.DeflateError: zlib names the damage below
            raw = None
    if raw is None or len(raw) != expected:
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(idat, expected + 1)
        except zlib.error as exc:
            raise _damaged(path, f"its image data do not inflate ({exc})") from None
        if len(raw) != expected or not inflater.eof:
            raise _damaged(path, f"its image data inflate to {len(raw)}"
                                 f"{'+' * (len(raw) > expected)} bytes"
                                 f"{'' if inflater.eof else ' (the stream does not end)'}, "
                                 f"the header states {expected}")
    at = 0
    for n, stride in rows:
        filters = np.frombuffer(raw, np.uint8, n * stride, at)[::stride]
        at += n * stride
        if filters.max(initial=0) > 4:
            raise _damaged(path, f"a row has filter type {int(filters.max())} (PNG defines 0..4)")
    return raw


def check_png_data(blob: bytes, facts: dict, path) -> bytes:
    """Check a whole PNG in memory before a decoder sees it, so that libpng never meets damage
    it would report on stderr: every chunk's CRC, the image data (``IDAT``) in one run of
    chunks, inflating to exactly the size the header states, with a valid filter type (0..4)
    on every row.

    Parameters
    ----------
    blob : bytes
        The file's content.
    facts : dict
        :func:`png_header` of the same file.
    path : str or Path
        The file (for the message).

    Returns
    -------
    bytes
        The inflated image data (each row its filter byte, then its filtered bytes).

    Raises
    ------
    DataFormatError
        One line naming the file and the damage.
    """
    return _inflate(_idat_run(blob, path)[2], facts, path)


_STORED_BLOCK = 65535  # the most bytes a stored (uncompressed) deflate block holds


def _stored_png(blob: bytes, start: int, end: int, raw: bytes) -> bytearray:
    """``blob`` with its run of ``IDAT`` chunks (``start:end``) replaced by one chunk holding
    ``raw``, the already inflated image data, as stored deflate blocks: a decoder copies them
    instead of inflating them again. Every other chunk is kept as it was."""
    n_blocks = max(1, -(-len(raw) // _STORED_BLOCK))
    z_len = 2 + 5 * n_blocks + len(raw) + 4
    out = bytearray(start + 12 + z_len + len(blob) - end)
    out[:start] = memoryview(blob)[:start]
    out[start:start + 8] = struct.pack(">I4s", z_len, b"IDAT")
    at = start + 8
    out[at:at + 2] = b"\x78\x01"  # zlib header: deflate, 32 KiB window, no dictionary
    at += 2
    src = memoryview(raw)
    for i in range(n_blocks):
        part = src[i * _STORED_BLOCK:(i + 1) * _STORED_BLOCK]
        out[at:at + 5] = struct.pack("<BHH", i == n_blocks - 1, len(part), 0xFFFF ^ len(part))
        out[at + 5:at + 5 + len(part)] = part
        at += 5 + len(part)
    out[at:at + 4] = struct.pack(">I", _adler32(raw))
    at += 4
    body = memoryview(out)[start + 4:at]
    out[at:at + 4] = struct.pack(">I", _crc32(body))
    body.release()
    out[at + 4:] = memoryview(blob)[end:]
    return out


def decode_png(path, facts: dict | None = None) -> np.ndarray:
    """Decode a PNG checked first by :func:`check_png_data` (OpenCV, ``IMREAD_UNCHANGED``).

    The image data are inflated once, by the check; OpenCV gets them back as stored deflate
    blocks (a copy, not a second inflate) and unfilters them.

    Parameters
    ----------
    path : str or Path
        The file.
    facts : dict, optional
        Its :func:`png_header` (read when not given).

    Returns
    -------
    ndarray
        (H, W) or (H, W, C) as OpenCV decodes it.

    Raises
    ------
    DataFormatError
        A damaged file (one line; libpng prints nothing).
    """
    import cv2

    facts = facts or png_header(path)
    blob = Path(path).read_bytes()
    start, end, idat = _idat_run(blob, path)
    stored = _stored_png(blob, start, end, _inflate(idat, facts, path))
    del blob, idat
    if _codecs is not None and facts["colour_type"] == 0 and b"tRNS" not in stored[:start]:
        # grayscale without transparency: imagecodecs' libpng gives OpenCV's array (colour PNGs
        # go to OpenCV, whose channel order and gray+alpha expansion the readers expect;
        # imagecodecs would add an alpha channel for a tRNS chunk)
        try:
            array = _codecs.png_decode(stored)
        except Exception:  # imagecodecs.PngError: OpenCV says what is wrong below
            array = None
        if array is not None and array.shape == (facts["height"], facts["width"]):
            return array
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        array = cv2.imdecode(np.frombuffer(stored, np.uint8), cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if array is None:
        raise DataFormatError("the PNG cannot be decoded (damaged data); copy or write it "
                              "again", path=path)
    return array


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
        return decode_png(path, facts)

    layout = FileLayout(path=path, format="png", n_frames=1, shape=shape, dtype=dtype,
                        read=read)
    if facts["significant_bits"] and facts["significant_bits"] < depth:
        layout.give("bit_depth", int(facts["significant_bits"]), "file (PNG sBIT chunk)")
    if facts["text"]:
        layout.meta["png_text"] = facts["text"]
    return layout
