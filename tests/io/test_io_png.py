"""PNG frames decode from one inflate (hsiffc checks the image data and hands them on to OpenCV
as stored deflate blocks): the arrays equal libpng's own decoding of the file for every row
filter type, bit depth, interlacing and split of the image data into chunks."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from hsiffc.io import open_source

ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2),
         (0, 1, 1, 2))


def _chunk(kind, body):
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _random_png(path, rng, width, height, depth, interlace, n_idat, extra=()):
    """A PNG of random filtered rows (every filter type 0..4, random bytes after it: any such
    data is a valid image), its compressed data split over ``n_idat`` chunks."""
    passes = ADAM7 if interlace else ((0, 0, 1, 1),)
    rows = []
    for x0, y0, dx, dy in passes:
        pw, ph = -(-(width - x0) // dx) if width > x0 else 0, -(-(height - y0) // dy) if \
            height > y0 else 0
        for _ in range(ph if pw else 0):
            rows.append(bytes([rng.integers(0, 5)]) + rng.bytes(pw * depth // 8))
    assert {r[0] for r in rows} == set(range(5))  # every filter type is there
    z = zlib.compress(b"".join(rows), 6)
    cut = np.linspace(0, len(z), n_idat + 1).astype(int)
    ihdr = struct.pack(">IIBBBBB", width, height, depth, 0, 0, 0, int(interlace))
    chunks = [(b"IHDR", ihdr), *extra] + [(b"IDAT", z[a:b]) for a, b in zip(cut[:-1], cut[1:])]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(_chunk(k, b) for k, b in
                                                     chunks + [(b"IEND", b"")]))
    return path


@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("interlace", [False, True])
@pytest.mark.parametrize("shape,n_idat", [((37, 53), 1), ((300, 170), 5)])
def test_png_decodes_as_libpng_does(tmp_path, depth, interlace, shape, n_idat):
    rng = np.random.default_rng(depth + 2 * interlace + n_idat)
    h, w = shape  # (300, 170) at 16 bits: 102 kB of image data, two stored blocks
    path = _random_png(tmp_path / "r.png", rng, w, h, depth, interlace, n_idat,
                       extra=[(b"tEXt", b"Comment\0random rows"), (b"sBIT", bytes([depth]))])
    expected = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert expected is not None and expected.shape == shape
    with open_source(path, exposure_ms=1.0, bit_depth=depth) as src:
        got = src.read(0)
    assert got.dtype == expected.dtype == np.dtype(f"uint{depth}")
    np.testing.assert_array_equal(got, expected)


def test_png_of_opencv_default_filters(tmp_path):
    """What OpenCV writes (libpng's adaptive filters) reads back exactly, 16 bits."""
    frame = np.random.default_rng(3).integers(0, 4096, (257, 300)).astype(np.uint16)
    frame[:, :150] = np.arange(150) * 27  # smooth half: other filters than the noise
    path = tmp_path / "cv.png"
    assert cv2.imwrite(str(path), frame, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    with open_source(path, exposure_ms=1.0, bit_depth=12) as src:
        np.testing.assert_array_equal(src.read(0), frame)


@pytest.mark.parametrize("depth", [8, 16])
def test_png_with_a_transparent_gray_level_decodes_as_opencv_does(tmp_path, depth):
    """A grayscale PNG with a tRNS chunk: the array OpenCV gives (one channel)."""
    rng = np.random.default_rng(depth)
    path = _random_png(tmp_path / "t.png", rng, 23, 40, depth, False, 1,
                       extra=[(b"tRNS", struct.pack(">H", 3))])
    expected = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    with open_source(path, exposure_ms=1.0, bit_depth=depth) as src:
        np.testing.assert_array_equal(src.read(0), expected)
