"""The everyday workflow without a sweep, in the words of the camera-data guide: a folder of plain 8-bit
compressed TIFFs of a 5x5 mosaic camera, a dark and a white reference, metadata from a sidecar,
``hsiffc fit`` + ``hsiffc correct``, a cube with 25 bands and the IMEC wavelengths in order, and
a full-resolution PPID cube, ENVI only, that SPy and ``read_cube`` read back alike, with its
quicklook.

The camera is the IMEC 5x5 NIR sensor of the shared data set, its vendor XML read as it is but
for the sensor and filter-area size: a 208 x 410 px window of the CMV2000 (filter area 200 x 405
px from row 3, as the real one starts at row 3), so that the test runs in seconds; every code
path is the full sensor's (the sidecar naming the XML, the crop to the filter area, the 25
wavelengths). The full-size figures (a 2048 x 1088 frame) are measured by
``benchmarks/bench_outputs.py``.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.io import read_corrected
from hsiffc.io.envi import read_envi
from hsiffc.spectral.imec import read_imec_xml

SENSOR = (208, 410)  # a window of the CMV2000 (1088 x 2048)
AREA = (200, 405)  # its filter area, from row 3 (the real one: 1080 x 2045 from row 3)
ROWS, COLS = slice(3, 3 + AREA[0]), slice(0, AREA[1])


@pytest.fixture
def window_xml(imec_xml, tmp_path):
    """The IMEC sensor's XML with the sensor and filter area cut to the test's window."""
    text = imec_xml.read_text()
    sizes = {"sensor_info": SENSOR, "filter_area": AREA}
    for block, (h, w) in sizes.items():
        m = re.search(rf"<{block}\b.*?</{block}>", text, re.S)
        part = re.sub(r"<width>\d+</width>", f"<width>{w}</width>", m.group(0))
        part = re.sub(r"<height>\d+</height>", f"<height>{h}</height>", part)
        text = text[:m.start()] + part + text[m.end():]
    path = tmp_path / "imec-window.xml"
    path.write_text(text)
    return path


def _camera_frames(rng, gain, dark, level, n):
    """8-bit frames as the camera software saves them: dark offset + gain x level + noise."""
    out = []
    for _ in range(n):
        signal = dark + gain * level + rng.normal(0, 1.0, SENSOR)
        out.append(np.clip(np.rint(signal), 0, 255).astype(np.uint8))
    return out


def _nonuniformity(frame, mosaic, rows=slice(20, 180)):
    """Mean over bands of 100 std/mean within the band (a fixed-pattern measure)."""
    band = mosaic.band_map(frame.shape)[rows]
    values = frame[rows]
    return float(np.mean([100 * values[band == b].std() / values[band == b].mean()
                          for b in range(mosaic.n_bands)]))


def test_folder_of_camera_tiffs_fit_correct_cube(tmp_path, window_xml, capsys):
    imec_xml = window_xml
    rng = np.random.default_rng(5)
    gain = rng.uniform(0.8, 1.2, SENSOR)            # pixel response non-uniformity
    dark = rng.uniform(4, 8, SENSOR)                # dark offset per pixel, DN
    refs, raw = tmp_path / "refs", tmp_path / "raw"
    refs.mkdir()
    raw.mkdir()
    for i, f in enumerate(_camera_frames(rng, gain, dark, 0.0, 2)):
        tifffile.imwrite(refs / f"dark_{i}.tif", f, compression="lzw")
    for i, f in enumerate(_camera_frames(rng, gain, dark, 150.0, 2)):
        tifffile.imwrite(refs / f"white_{i}.tif", f, compression="lzw")
    scene_level = 150.0 * (0.5 + 0.3 * np.sin(np.arange(SENSOR[1]) / 40.0))[None, :]
    for i, f in enumerate(_camera_frames(rng, gain, dark, scene_level, 2)):
        tifffile.imwrite(raw / f"scene_{i}.tif", f, compression="zlib")
    sidecar = (f'[defaults]\nbit_depth = 8\nmosaic = "{imec_xml}"\nexposure_ms = 20.0\n\n'
               '[[files]]\nmatch = "dark_*"\nkind = "dark"\n\n'
               '[[files]]\nmatch = "white_*"\nkind = "light"\nillumination = "halogen"\n')
    (refs / "hsiffc.toml").write_text(sidecar)
    (raw / "hsiffc.csv").write_text("file,exposure_ms,kind,bit_depth,mosaic\n"
                                    f"scene_*.tif,20,light,8,{imec_xml}\n")
    (tmp_path / "pipe.toml").write_text(
        '[[step]]\nname = "dark"\nstage = "dark"\n\n'
        '[[step]]\nname = "ffc"\nstage = "two_point_ffc"\nexposure_ms = 20.0\n')

    assert main(["info", str(refs)]) == 0
    text = capsys.readouterr().out
    assert "sidecar hsiffc.toml" in text and "active area" in text

    assert main(["fit", str(tmp_path / "pipe.toml"), str(refs),
                 "-o", str(tmp_path / "pipe.npz")]) == 0
    assert main(["correct", "--pipeline", str(tmp_path / "pipe.npz"), str(raw),
                 "-o", str(tmp_path / "out"), "--format", "tiff,envi", "-q"]) == 0
    capsys.readouterr()

    out = read_corrected(tmp_path / "out" / "scene_0.corrected.tif")
    assert out.data.shape == (1,) + AREA           # one file, one frame; cropped to the filter area
    assert out.provenance["calibration"] is None   # no calibration needed
    imec = read_imec_xml(imec_xml)
    mosaic = imec.mosaic()
    truth = np.broadcast_to(scene_level, SENSOR)[ROWS, COLS]   # the scene, without the sensor
    raw0 = tifffile.imread(raw / "scene_0.tif")[ROWS, COLS].astype(np.float64)
    before = _nonuniformity(raw0 / truth, mosaic)
    after = _nonuniformity(out.data[0] / truth, mosaic)
    assert after < before / 3, (before, after)     # the fixed pattern is removed

    cube, head = read_envi(tmp_path / "out" / "scene_0.corrected.hdr")
    assert cube.shape == (AREA[0] // 5, AREA[1] // 5, 25)  # one spectrum per tile, as before
    np.testing.assert_allclose(head["wavelengths_nm"], np.sort(imec.bands.centres_nm), rtol=1e-5)
    dq_cube, _ = read_envi(tmp_path / "out" / "scene_0.corrected.dq.hdr")
    assert dq_cube.shape == cube.shape and dq_cube.dtype == np.uint16  # the bits in use
    assert np.isfinite(cube).all()

    # the product of the work: a full-resolution PPID cube, ENVI only, that SPy opens
    import spectral

    from hsiffc.cubes import read_cube

    assert main(["correct", "--pipeline", str(tmp_path / "pipe.npz"), str(raw / "scene_0.tif"),
                 "-o", str(tmp_path / "cubes"), "--cube", "ppid", "--format", "envi",
                 "-q"]) == 0
    written = [p for p in (tmp_path / "cubes").iterdir() if not p.name.startswith(".")]
    assert sorted(p.name for p in written) == [
        "scene_0.corrected.dq.hdr", "scene_0.corrected.dq.img", "scene_0.corrected.hdr",
        "scene_0.corrected.img"]                    # ENVI only: no hsiffc TIFF, no alpha
    cube_bytes = AREA[0] * AREA[1] * 25 * 4         # the float32 cube's own size
    total = sum(p.stat().st_size for p in written)
    assert 1.5 * cube_bytes < total <= 1.6 * cube_bytes, total / cube_bytes  # + uint16 DQ + headers
    hdr = tmp_path / "cubes" / "scene_0.corrected.hdr"
    img = spectral.open_image(str(hdr))
    assert (img.nrows, img.ncols, img.nbands) == AREA + (25,)   # every band at every pixel
    order = np.argsort(imec.bands.centres_nm)
    np.testing.assert_allclose(img.bands.centers, imec.bands.centres_nm[order], rtol=1e-5)
    np.testing.assert_allclose(img.bands.bandwidths, imec.bands.fwhm_nm[order], rtol=1e-5)
    full = img.open_memmap()
    assert np.isfinite(full).all()
    back = read_cube(hdr)                           # hsiffc reads its own export: the same
    np.testing.assert_array_equal(back.data, full)
    assert [float(w) for w in back.wavelengths_nm] == [float(w) for w in img.bands.centers]
    spy_dq = spectral.open_image(str(hdr.with_name("scene_0.corrected.dq.hdr"))).open_memmap()
    np.testing.assert_array_equal(back.dq, spy_dq)
    assert back.attrs["provenance"]["pipeline"]["steps"]
    del spy_dq, back
    # the full cube's band means follow the tile cube's: the same scene, the same band order
    np.testing.assert_allclose(full.mean(axis=(0, 1)), cube.mean(axis=(0, 1)), rtol=0.02)
    png = tmp_path / "cubes" / "scene_0.png"
    assert main(["quicklook", str(hdr), "-o", str(png), "--pixel", "100", "200", "--bands", "1",
                 "13", "25"]) == 0
    assert png.stat().st_size > 20_000


def test_correct_without_calibration_needs_a_pipeline(tmp_path, capsys):
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((10, 10), np.uint8))
    assert main(["correct", str(tmp_path / "a.tif"), "-o", str(tmp_path / "out")]) == 2
    assert "--calibration" in capsys.readouterr().err
