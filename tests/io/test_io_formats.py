"""Every input format, written with the library real tools use, reads back to the same arrays
and metadata through the one streaming reader (hsiffc.io.open_source)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from hsiffc.errors import DataFormatError
from hsiffc.io import FrameMeta, open_source, read_sweep, write_sweep
from hsiffc.io.envi import parse_envi_header, read_envi
from hsiffc.io.envi import write_envi
from hsiffc.data.sweep import Sweep

RNG = np.random.default_rng(7)


def frames(n=3, shape=(24, 30), bits=12, dtype=np.uint16):
    return RNG.integers(0, 2 ** bits, (n,) + shape).astype(dtype)


@pytest.mark.parametrize("compression", [None, "lzw", "zlib", "zstd", "packbits"])
@pytest.mark.parametrize("dtype,bits", [(np.uint8, 8), (np.uint16, 10), (np.uint16, 12),
                                        (np.uint16, 16)])
def test_plain_tiff_any_compression(tmp_path, compression, dtype, bits):
    data = frames(4, bits=bits, dtype=dtype)
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, data, compression=compression, photometric="minisblack")
    with open_source(path, exposure_ms=2.5, bit_depth=bits) as src:
        assert (src.n_frames, src.frame_shape, src.dtype) == (4, (24, 30), np.dtype(dtype))
        got = [(raw, meta) for raw, meta in src]
    np.testing.assert_array_equal(np.stack([r for r, _ in got]), data)
    assert all(isinstance(m, FrameMeta) and m.exposure_ms == 2.5 and m.kind == "light"
               for _, m in got)
    assert [m.page for _, m in got] == [0, 1, 2, 3]
    assert src.origins["exposure_ms"] == "--exposure-ms"


def test_plain_tiff_float_frames(tmp_path):
    data = RNG.normal(100, 5, (2, 8, 9)).astype(np.float32)
    path = tmp_path / "f.tif"
    tifffile.imwrite(path, data, compression="zlib", photometric="minisblack")
    sweep = read_sweep(path, exposure_ms=1.0, bit_depth=12)
    np.testing.assert_array_equal(sweep.data, data)
    with pytest.raises(DataFormatError, match="no bit_depth"):
        open_source(path, exposure_ms=1.0)


def test_single_page_files_in_a_folder_are_one_sweep(tmp_path):
    data = frames(5, dtype=np.uint8, bits=8)
    for i, frame in enumerate(data):
        tifffile.imwrite(tmp_path / f"f{i:02d}.tif", frame, compression="lzw")
    (tmp_path / "notes.txt").write_text("not an image")
    sweep = read_sweep(tmp_path, exposure_ms=4.0, bit_depth=8)
    np.testing.assert_array_equal(sweep.data, data)
    glob_sweep = read_sweep(str(tmp_path / "f0[1-3].tif"), exposure_ms=4.0, bit_depth=8)
    np.testing.assert_array_equal(glob_sweep.data, data[1:4])


def test_exposure_time_tag_written_by_pillow(tmp_path):
    from PIL import Image, TiffImagePlugin

    frame = frames(1, dtype=np.uint8, bits=8)[0]
    info = TiffImagePlugin.ImageFileDirectory_v2()
    info[33434] = 0.025                            # EXIF ExposureTime, seconds
    Image.fromarray(frame).save(tmp_path / "cam.tif", tiffinfo=info, compression="tiff_lzw")
    with open_source(tmp_path / "cam.tif", bit_depth=8) as src:
        assert src.exposure_ms[0] == pytest.approx(25.0)
        assert "ExposureTime" in src.origins["exposure_ms"]
        np.testing.assert_array_equal(src.read(0), frame)


def test_tiff_exposure_tag_in_image_ifd(tmp_path):
    tifffile.imwrite(tmp_path / "t.tif", frames(1)[0], extratags=[(33434, 5, 1, (1, 50), True)])
    assert read_sweep(tmp_path / "t.tif", bit_depth=12).exposure_ms[0] == pytest.approx(20.0)


@pytest.mark.parametrize("writer", ["opencv", "pillow"])
@pytest.mark.parametrize("dtype,bits", [(np.uint8, 8), (np.uint16, 16)])
def test_png_8_and_16_bit(tmp_path, writer, dtype, bits):
    frame = frames(1, dtype=dtype, bits=bits)[0]
    path = tmp_path / "f.png"
    if writer == "opencv":
        assert cv2.imwrite(str(path), frame)
    else:
        from PIL import Image
        Image.fromarray(frame).save(path)
    with open_source(path, exposure_ms=3.0, bit_depth=bits) as src:
        assert src.dtype == np.dtype(dtype) and src.format == "png"
        np.testing.assert_array_equal(src.read(0), frame)


def test_png_sbit_gives_bit_depth(tmp_path):
    from PIL import Image, PngImagePlugin

    frame = frames(1, bits=12)[0]
    path = tmp_path / "s.png"
    Image.fromarray(frame).save(path)
    blob = path.read_bytes()
    import struct
    import zlib
    chunk = b"sBIT" + bytes([12])
    sbit = struct.pack(">I", 1) + chunk + struct.pack(">I", zlib.crc32(chunk))
    at = 8 + 25  # after the signature and IHDR
    path.write_bytes(blob[:at] + sbit + blob[at:])
    assert PngImagePlugin  # Pillow still reads the file
    with open_source(path, exposure_ms=1.0) as src:
        assert src.bit_depth == 12 and "sBIT" in src.origins["bit_depth"]
        np.testing.assert_array_equal(src.read(0), frame)


def _hand_envi(tmp_path, data, interleave, byte_order="<", extra=""):
    """An ENVI pair written by hand per the header spec (not with hsiffc's writer)."""
    n, h, w = data.shape
    axes = {"bsq": (0, 1, 2), "bil": (1, 0, 2), "bip": (1, 2, 0)}[interleave]
    raw = np.ascontiguousarray(data.transpose(axes)).astype(data.dtype.newbyteorder(byte_order))
    (tmp_path / "cube.img").write_bytes(b"\0" * 16 + raw.tobytes())
    code = {np.dtype(np.uint16): 12, np.dtype(np.uint8): 1, np.dtype(np.float32): 4}[data.dtype]
    (tmp_path / "cube.hdr").write_text(
        "ENVI\ndescription = {hand written\n  test file}\n"
        f"samples = {w}\nlines   = {h}\nbands   = {n}\nheader offset = 16\n"
        f"file type = ENVI Standard\ndata type = {code}\ninterleave = {interleave}\n"
        f"byte order = {1 if byte_order == '>' else 0}\n; a comment line\n" + extra)
    return tmp_path / "cube.hdr"


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
@pytest.mark.parametrize("order", ["<", ">"])
def test_envi_hand_written_every_interleave(tmp_path, interleave, order):
    data = frames(3, bits=12)
    hdr = _hand_envi(tmp_path, data, interleave, order,
                     "exposure time = {5, 10, 20}\ngain = 2.5\nbit depth = 12\n"
                     "wavelength units = nm\nwavelength = {600.5, 610,\n 620}\n")
    # a 3-band header with one wavelength per band is a cube, not raw frames
    with pytest.raises(DataFormatError, match="spectral cube"):
        open_source(hdr)
    cube, head = read_envi(hdr)
    np.testing.assert_array_equal(cube, np.moveaxis(data, 0, -1))
    assert head["wavelengths_nm"] == [600.5, 610.0, 620.0]
    text = hdr.read_text().replace("wavelength = {600.5, 610,\n 620}\n", "")
    hdr.write_text(text)
    for target in (hdr, tmp_path / "cube.img"):
        sweep = read_sweep(target)
        np.testing.assert_array_equal(sweep.data, data)
        assert sweep.exposure_ms.tolist() == [5.0, 10.0, 20.0] and sweep.bit_depth == 12
        assert sweep.meta["gain"] == "2.5"


def test_envi_wavelengths_join_the_mosaic(tmp_path):
    data = frames(1, shape=(10, 15), bits=8, dtype=np.uint8)
    wl = [600 + 10 * i for i in range(25)]
    write_envi(tmp_path / "raw", data[0], wavelengths_nm=None,
               extra={"exposure_ms": 7, "wavelength": wl})
    with open_source(tmp_path / "raw.hdr", mosaic="5x5", bit_depth=8) as src:
        assert src.mosaic.n_bands == 25 and src.mosaic.wavelengths_nm == tuple(map(float, wl))
        assert src.exposure_ms[0] == 7.0


@pytest.mark.parametrize("interleave", ["bsq", "bil", "bip"])
def test_envi_writer_round_trip_and_spectral(tmp_path, interleave):
    cube = RNG.normal(50, 3, (6, 7, 4)).astype(np.float32)
    hdr, img = write_envi(tmp_path / "out.hdr", cube, wavelengths_nm=[600, 650, 700, 750],
                          interleave=interleave, extra={"exposure time": 12.5})
    back, head = read_envi(hdr)
    np.testing.assert_array_equal(back, cube)
    assert head["wavelengths_nm"] == [600, 650, 700, 750] and head["interleave"] == interleave
    assert parse_envi_header(hdr)["exposure time"] == "12.5"
    spectral = pytest.importorskip("spectral")
    img_sp = spectral.open_image(str(hdr))
    np.testing.assert_array_equal(np.array(img_sp.load()), cube)
    assert [float(w) for w in img_sp.bands.centers] == [600, 650, 700, 750]


def test_envi_written_by_spectral_reads_back(tmp_path):
    spectral = pytest.importorskip("spectral")
    data = frames(2, bits=12)
    spectral.envi.save_image(str(tmp_path / "sp.hdr"), np.moveaxis(data, 0, -1),
                             dtype=np.uint16, interleave="bil",
                             metadata={"exposure time": 8, "bit depth": 12})
    sweep = read_sweep(tmp_path / "sp.hdr")
    np.testing.assert_array_equal(sweep.data, data)
    assert sweep.exposure_ms.tolist() == [8.0, 8.0]


def test_envi_truncated_data_file(tmp_path):
    hdr = _hand_envi(tmp_path, frames(3, bits=12), "bsq")
    img = tmp_path / "cube.img"
    img.write_bytes(img.read_bytes()[:-10])
    with pytest.raises(DataFormatError, match="truncated"):
        open_source(hdr, exposure_ms=1, bit_depth=12)


def test_fits_frames_and_header(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    data = frames(3, bits=12)
    header = fits.Header({"EXPTIME": 0.015, "IMAGETYP": "Dark Frame", "GAIN": 1.5})
    fits.PrimaryHDU(data, header=header).writeto(tmp_path / "d.fits")
    with open_source(tmp_path / "d.fits", bit_depth=12) as src:
        assert src.dtype == np.uint16 and src.kind.tolist() == ["dark"] * 3
        assert src.exposure_ms.tolist() == pytest.approx([15.0] * 3)
        sweep = src.to_sweep()
    np.testing.assert_array_equal(sweep.data, data)
    assert sweep.meta["gain"] == 1.5


def test_hsiffc_tiff_still_self_describing(tmp_path):
    sweep = Sweep(frames(2, bits=10), exposure_ms=[1.0, 2.0], kind=["dark", "light"],
                  bit_depth=10, illumination=["", "lamp"])
    path = write_sweep(tmp_path / "s.tif", sweep, compression="zlib")
    with open_source(path) as src:
        assert src.format == "hsiffc-tiff" and src.origins["exposure_ms"] == "file (hsiffc JSON)"
        assert src.kind.tolist() == ["dark", "light"] and src.bit_depth == 10
    # a sidecar next to a self-describing file is not consulted
    (tmp_path / "hsiffc.toml").write_text("[defaults]\nexposure_ms = 99.0\n")
    assert read_sweep(path).exposure_ms.tolist() == [1.0, 2.0]


def test_emva_descriptor_through_open_source(emva_dir):
    with open_source(emva_dir) as src:
        assert src.format == "emva1288" and src.n_frames == 600 and src.bit_depth == 8
        raw, meta = next(iter(src))
        assert raw.shape == (128, 256) and meta.step == 0


def test_stream_twice_random_access_and_prefetch_off(tmp_path):
    data = frames(5)
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, data, compression="lzw", photometric="minisblack")
    src = open_source(path, exposure_ms=1, bit_depth=12)
    first = np.stack([raw for raw, _ in src])
    np.testing.assert_array_equal(src.read(3), data[3])       # reopened after the pass
    src.prefetch = 0
    second = np.stack([raw for raw, _ in src])
    np.testing.assert_array_equal(first, data)
    np.testing.assert_array_equal(second, data)
    src.close()


def test_bad_frame_in_the_middle_stops_the_stream(tmp_path):
    data = frames(4, bits=8, dtype=np.uint16)
    data[2, 0, 0] = 4000
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, data, photometric="minisblack")
    seen = []
    with pytest.raises(DataFormatError, match="frame 2"):
        with open_source(path, exposure_ms=1, bit_depth=8) as src:
            for raw, meta in src:
                seen.append(meta.index)
    assert seen == [0, 1]
