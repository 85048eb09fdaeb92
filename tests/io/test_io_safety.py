"""Reading safely: size limits before any decode, truncation and inconsistency from the file
structure, a missing codec named."""

from __future__ import annotations

import time

import numpy as np
import pytest
import tifffile

from hsiffc.errors import DataFormatError
from hsiffc.io import ReadLimits, default_limits, open_source, read_sweep
from testfiles import bomb_tiff




def test_decompression_bomb_refused_fast(tmp_path):
    path = bomb_tiff(tmp_path / "bomb.tif")
    assert path.stat().st_size < 64_000
    t0 = time.perf_counter()
    with pytest.raises(DataFormatError) as excinfo:
        open_source(path, exposure_ms=1, bit_depth=8)
    assert time.perf_counter() - t0 < 2.0
    msg = str(excinfo.value)
    assert "\n" not in msg and "bomb.tif" in msg
    assert "32000 x 32000" in msg and "HSIFFC_MAX_FRAME_PIXELS" in msg


def test_limits_are_overridable(tmp_path, monkeypatch):
    data = np.zeros((3, 40, 50), np.uint8)
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, data, photometric="minisblack")
    small = ReadLimits(max_frame_pixels=1000)
    with pytest.raises(DataFormatError, match="2,000 pixels"):
        open_source(path, exposure_ms=1, bit_depth=8, limits=small)
    with pytest.raises(DataFormatError, match="3 frames"):
        open_source(path, exposure_ms=1, bit_depth=8, limits=ReadLimits(max_frames=2))
    with pytest.raises(DataFormatError, match="HSIFFC_MAX_BYTES"):
        read_sweep(path, exposure_ms=1, bit_depth=8, limits=ReadLimits(max_bytes=5000))
    # streaming holds one frame: the same byte limit allows it
    with open_source(path, exposure_ms=1, bit_depth=8, limits=ReadLimits(max_bytes=5000)) as s:
        assert sum(1 for _ in s) == 3
    monkeypatch.setenv("HSIFFC_MAX_FRAMES", "2")
    assert default_limits().max_frames == 2
    with pytest.raises(DataFormatError, match="more than the limit"):
        read_sweep(path, exposure_ms=1, bit_depth=8)
    monkeypatch.setenv("HSIFFC_MAX_FRAMES", "lots")
    with pytest.raises(DataFormatError, match="HSIFFC_MAX_FRAMES"):
        default_limits()


@pytest.mark.parametrize("keep", [0.3, 0.5, 0.62, 0.75, 0.9, 0.99])
@pytest.mark.parametrize("compression", [None, "zlib", "lzw"])
def test_multipage_tiff_cut_short_is_truncated(tmp_path, keep, compression):
    """The tifffile example of the formats reference, cut: never read as fewer frames."""
    data = np.random.default_rng(1).integers(0, 255, (6, 40, 30), dtype=np.uint8)
    full = tmp_path / "full.tif"
    tifffile.imwrite(full, data, compression=compression, photometric="minisblack")
    cut = tmp_path / "cut.tif"
    cut.write_bytes(full.read_bytes()[:int(full.stat().st_size * keep)])
    with pytest.raises(DataFormatError) as excinfo:
        open_source(cut, exposure_ms=1, bit_depth=8)
    assert "truncated" in str(excinfo.value) or "damaged" in str(excinfo.value)


def test_multipage_tiff_written_page_by_page_cut_between_pages(tmp_path):
    """Pages written one by one (no shape description): the broken page chain is caught."""
    full = tmp_path / "pages.tif"
    with tifffile.TiffWriter(full) as tw:
        for k in range(4):
            tw.write(np.full((16, 16), k, np.uint8), metadata=None, photometric="minisblack")
    with tifffile.TiffFile(full) as tf:
        second = tf.pages[2].offset
    cut = tmp_path / "cut.tif"
    cut.write_bytes(full.read_bytes()[:second])
    with pytest.raises(DataFormatError, match="truncated"):
        open_source(cut, exposure_ms=1, bit_depth=8)


def test_missing_codec_is_named(tmp_path, monkeypatch):
    path = tmp_path / "lzw.tif"
    tifffile.imwrite(path, np.zeros((8, 8), np.uint8), compression="lzw")

    class NoLzw(dict):
        def __getitem__(self, key):
            raise KeyError(f"{key} requires the 'imagecodecs' package")

    monkeypatch.setattr(tifffile.TIFF, "DECOMPRESSORS", NoLzw())
    with pytest.raises(DataFormatError) as excinfo:
        open_source(path, exposure_ms=1, bit_depth=8)
    msg = str(excinfo.value)
    assert "LZW" in msg and "imagecodecs" in msg and "truncated" not in msg


def test_corrected_output_is_not_raw_input(tmp_path):
    path = tmp_path / "x.corrected.tif"
    tifffile.imwrite(path, np.zeros((4, 4), np.float32),
                     description='{"format": "hsiffc-corrected"}', metadata=None)
    with pytest.raises(DataFormatError, match="output of hsiffc correct"):
        open_source(path)


def test_png_cut_short(tmp_path):
    import cv2

    path = tmp_path / "f.png"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (50, 50), dtype=np.uint8))
    blob = path.read_bytes()
    for keep in (0.2, 0.6, 0.97):
        path.write_bytes(blob[:int(len(blob) * keep)])
        with pytest.raises(DataFormatError, match="truncated"):
            open_source(path, exposure_ms=1, bit_depth=8)
