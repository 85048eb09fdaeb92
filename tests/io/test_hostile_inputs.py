"""Hostile and unusual inputs, round two (issue 35): a lock file that is a hard link to an input,
valid files once refused, size limits applied to headers before any decode, malformed headers
and tampered pipeline files. Each case: inputs byte-identical afterwards, valid files read, bad
ones refused with one line naming the file and the field, exit status 2."""

from __future__ import annotations

import hashlib
import json
import os
import struct
import subprocess
import sys
import zipfile
import zlib

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.errors import DataFormatError
from hsiffc.io import open_source
from checks import one_line as _one_line  # the one checker of one-line errors
from testfiles import bomb_tiff, capped_child, capped_cli, hand_png, synthetic_imec_xml


def _digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    assert main(["simulate", str(root / "s.tif"), "--exposures-ms", "2", "4", "8", "16",
                 "--shape", "8", "8"]) == 0
    assert main(["calibrate", str(root / "s.tif"), "-o", str(root / "cal.npz")]) == 0
    return root




def _descriptor(root, image_name, *, n_line="n 12 40 40"):
    desc = root / "EMVA1288_Data.txt"
    desc.write_text(f"v 3.0\n{n_line}\nb 1000 5.5\ni {image_name}\ni {image_name}\n"
                    f"d 1000\ni {image_name}\ni {image_name}\n")
    return desc


# -- 1. the lock file -----------------------------------------------------------------------------
def test_lock_file_hard_linked_to_an_input_is_refused_and_the_input_kept(sweep, tmp_path,
                                                                          capsys):
    out = tmp_path / "out"
    out.mkdir()
    before = _digest(sweep / "s.tif")
    os.link(sweep / "s.tif", out / ".hsiffc.lock")
    try:
        code = main(["correct", str(sweep / "s.tif"), "--calibration", str(sweep / "cal.npz"),
                     "-o", str(out), "-q"])
        assert code == 2
        _one_line(capsys, ".hsiffc.lock", "hard link")
        assert _digest(sweep / "s.tif") == before
        assert not list(out.glob("*.corrected.tif"))
    finally:
        (out / ".hsiffc.lock").unlink()


@pytest.mark.parametrize("planted", ["data", "fifo", "folder"])
def test_lock_file_that_hsiffc_did_not_make_is_never_written(tmp_path, planted):
    from hsiffc.files.atomic import OutputError
    from hsiffc.files.folderlock import folder_lock

    lock = tmp_path / ".hsiffc.lock"
    if planted == "data":
        lock.write_bytes(b"\x00\x01 measured data, one name only")
    elif planted == "fifo":
        os.mkfifo(lock)
    else:
        lock.mkdir()
    before = lock.read_bytes() if planted == "data" else None
    with pytest.raises(OutputError) as info, folder_lock(tmp_path):
        pass
    assert "\n" not in str(info.value) and ".hsiffc.lock" in str(info.value)
    if before is not None:
        assert lock.read_bytes() == before


def test_lock_left_by_a_killed_run_is_taken_over(tmp_path):
    """A record left by a run killed with -9 (the kernel released its flock) is a lock file
    hsiffc made: the next run takes it."""
    from hsiffc.files.folderlock import folder_lock

    lock = tmp_path / ".hsiffc.lock"
    lock.write_text('{"pid": 1, "host": "gone", "started": "2026-01-01T00:00:00+0000", '
                    '"command": "hsiffc correct"}\n')
    with folder_lock(tmp_path) as me:
        assert f'"pid": {me["pid"]}' in lock.read_text()
    assert lock.read_bytes() == b""


# -- 2. valid files read --------------------------------------------------------------------------
def test_tiff_written_frame_by_frame_with_tifffile_defaults_is_read(tmp_path):
    path = tmp_path / "frames.tif"
    with tifffile.TiffWriter(path) as tw:
        for k in range(3):
            tw.write(np.full((6, 5), 10 * k, np.uint16))  # each page its own series
    with tifffile.TiffFile(path) as tf:
        assert [p.description for p in tf.pages] == ['{"shape": [6, 5]}'] * 3
    with open_source(path, exposure_ms=1, bit_depth=12) as src:
        data = src.to_sweep().data
    assert data.shape == (3, 6, 5) and data[:, 0, 0].tolist() == [0, 10, 20]
    # one series of 3 cut to 2 pages still declares 3: refused as truncated
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, np.zeros((3, 6, 5), np.uint16), photometric="minisblack")
    with tifffile.TiffFile(whole) as tf:
        third = tf.pages[2].offset
    cut = tmp_path / "cut.tif"
    cut.write_bytes(whole.read_bytes()[:third])
    with pytest.raises(DataFormatError, match="truncated"):
        open_source(cut, exposure_ms=1, bit_depth=12)


def test_rice_tile_compressed_fits_is_read_and_its_truncation_found(tmp_path):
    fits = pytest.importorskip("astropy.io.fits")
    data = np.random.default_rng(0).integers(1000, 1016, (3, 128, 96)).astype(np.int16)
    path = tmp_path / "rice.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(data, compression_type="RICE_1")]
                 ).writeto(path)
    assert path.stat().st_size < data.nbytes / 2  # compressed: far smaller than the image
    with open_source(path, exposure_ms=1, bit_depth=12) as src:
        np.testing.assert_array_equal(src.to_sweep().data, data)
    cut = tmp_path / "cut.fits"
    cut.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
    with pytest.raises(DataFormatError, match="truncated"):
        open_source(cut, exposure_ms=1, bit_depth=12)


# -- 3. limits applied to headers before any decode ---------------------------------------------
def test_emva_images_larger_than_their_descriptor_are_refused_before_decoding(tmp_path):
    """A 2 MB PNG of 20000 x 20000 (400 MB decoded) and a few-KB deflate TIFF claiming
    32000 x 32000 (1 GB), each behind an 'n 12 40 40' line, read in a child whose memory
    would not hold them."""

    for name in ("png", "tif"):
        (tmp_path / name).mkdir()
    hand_png(tmp_path / "png" / "big.png", 20000, 20000)
    bomb_tiff(tmp_path / "tif" / "big.tif")
    assert max(p.stat().st_size for p in tmp_path.rglob("big.*")) < 2_000_000
    descs = [_descriptor(tmp_path / name, f"big.{name}") for name in ("png", "tif")]
    code, err = capped_cli(["info", *descs])  # the first one stops the command
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "20000 x 20000" in lines[0] and "'n' line" in lines[0], err
    code, err = capped_cli(["info", descs[1]])
    assert code == 2 and "32000 x 32000" in err and len(err.strip().splitlines()) == 1, err


def test_imec_xml_declaring_a_huge_grid_is_refused_before_allocating(tmp_path):

    xml = synthetic_imec_xml().replace("<measurement_range_end_nm>410</measurement_range_end_nm>",
                         "<measurement_range_end_nm>200000000</measurement_range_end_nm>")
    (tmp_path / "huge.xml").write_text(xml)
    done = capped_child(f"""
        from hsiffc.errors import DataFormatError
        from hsiffc.spectral.imec import read_imec_xml
        try:
            read_imec_xml({str(tmp_path / "huge.xml")!r})
        except DataFormatError as exc:
            print(exc)
    """, extra_mb=200)
    assert done.returncode == 0, done.stderr
    assert "HSIFFC_MAX_SPECTRAL_SAMPLES" in done.stdout and "huge.xml" in done.stdout


def test_mosaic_tile_and_simulated_shape_are_bounded(sweep, tmp_path):
    """A tile larger than the frame (--mosaic 12000x12000 took 9.4 GB, a sidecar's
    "100000x100000" ran out of memory) and simulate --shape 50000 50000 (24 GB): refused in
    one line each, in a child whose memory would not hold them."""
    data = tmp_path / "raw.tif"
    tifffile.imwrite(data, np.zeros((2, 32, 64), np.uint16), photometric="minisblack")
    side = tmp_path / "raw.toml"
    side.write_text('[defaults]\nexposure_ms = 5\nbit_depth = 12\nmosaic = "100000x100000"\n')
    runs = [["info", str(sweep / "s.tif"), "--mosaic", "12000x12000"],
            ["info", str(data), "--sidecar", str(side)],
            ["simulate", str(tmp_path / "x.tif"), "--exposures-ms", "1", "--shape", "50000",
             "50000"]]
    code = "".join(f"sys.stderr.write('===\\n'); sys.stderr.flush(); codes.append(main({r!r})); "
                   for r in runs)
    done = capped_child(f"codes = []; {code}sys.exit(10 * max(codes) + min(codes))")
    assert done.returncode == 22, done.stderr
    parts = [[ln for ln in p.splitlines() if ln.strip()] for p in done.stderr.split("===")[1:]]
    assert [len(p) for p in parts] == [1, 1, 1], done.stderr
    for part, names in zip(parts, [("--mosaic", "12000 x 12000", "larger than the frames"),
                                   ("sidecar raw.toml", "mosaic '100000x100000'", "64 x 32"),
                                   ("--shape 50000 50000", "HSIFFC_MAX_FRAME_PIXELS")]):
        assert all(n in part[0] for n in names), part[0]
    assert not (tmp_path / "x.tif").exists()


# -- 4. malformed input: one line, exit 2 -------------------------------------------------------
def test_png_with_a_short_ihdr_is_one_line(tmp_path, capsys):
    path = hand_png(tmp_path / "short.png", 1, 1,
                chunks=[(b"IHDR", b"\0\0\0\x08\0\0"), (b"IEND", b"")])
    assert main(["info", str(path), "--exposure-ms", "1"]) == 2
    _one_line(capsys, "short.png", "IHDR")


@pytest.mark.parametrize("area", [("-4", "2", "60", "28"), ("1", "2", "0", "28"),
                                  ("1", "2", "64", "28")], ids=["negative", "zero", "outside"])
def test_imec_filter_area_outside_the_sensor_is_refused(tmp_path, area):

    text = synthetic_imec_xml().replace(
        "<offset_x>1</offset_x><offset_y>2</offset_y>\n      <width>60</width>"
        "<height>28</height>",
        f"<offset_x>{area[0]}</offset_x><offset_y>{area[1]}</offset_y>"
        f"<width>{area[2]}</width><height>{area[3]}</height>")
    assert text != synthetic_imec_xml()
    (tmp_path / "a.xml").write_text(text)
    from hsiffc.spectral.imec import read_imec_xml

    with pytest.raises(DataFormatError, match="filter_area") as info:
        read_imec_xml(tmp_path / "a.xml")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("what", ["sidecar", "pipeline description", "manifest"])
def test_deeply_nested_documents_are_one_line(sweep, pipeline_file, tmp_path, capsys, what):
    deep = "[" * 5000 + "]" * 5000
    if what == "sidecar":
        side = tmp_path / "deep.toml"
        side.write_text(f"[defaults]\nexposure_ms = {deep}\n")
        argv = ["info", str(sweep / "s.tif"), "--sidecar", str(side)]
    elif what == "pipeline description":
        desc = tmp_path / "deep.toml"
        desc.write_text(f'x = {deep}\n[[step]]\nname = "dark"\nstage = "dark"\n')
        argv = ["fit", str(desc), str(sweep / "s.tif"), "-o", str(tmp_path / "p.npz")]
    else:
        pipe = _tampered(pipeline_file, tmp_path, manifest_text=lambda text: text.replace(
            '"fitted_": true', f'"fitted_": true, "deep_": {deep}', 1))
        argv = ["correct", str(sweep / "s.tif"), "--pipeline", str(pipe), "-o",
                str(tmp_path / "out")]
    assert main(argv) == 2
    _one_line(capsys, "deep" if what != "manifest" else "t.npz", "nest")


# -- 5. tampered pipeline files ----------------------------------------------------------------
@pytest.fixture(scope="module")
def pipeline_file(sweep):
    desc = sweep / "p.toml"
    desc.write_text('[[step]]\nname = "dark"\nstage = "dark"\n[[step]]\nname = "ffc"\n'
                    'stage = "two_point_ffc"\ncalibration = "cal.npz"\n')
    assert main(["fit", str(desc), str(sweep / "s.tif"), "-o", str(sweep / "pipe.npz")]) == 0
    return sweep / "pipe.npz"


def _tampered(src, tmp_path, *, arrays=None, manifest=None, manifest_text=None):
    """A copy of the fitted pipeline ``src`` with arrays replaced or the manifest edited."""
    with np.load(src) as z:
        members = {k: z[k] for k in z.files}
    text = members.pop("manifest.json").tobytes().decode()
    if manifest is not None:
        doc = json.loads(text)
        manifest(doc)
        text = json.dumps(doc)
    if manifest_text is not None:
        text = manifest_text(text)
    members.update(arrays or {})
    members["manifest.json"] = np.frombuffer(text.encode(), np.uint8)
    out = tmp_path / "t.npz"
    np.savez_compressed(out, **members)
    return out


def _state(step, key, value):
    return lambda doc: doc["steps"][step]["state"].__setitem__(key, value)


@pytest.mark.parametrize("how, names", [
    (dict(arrays={"ffc/gain_": np.full((8, 8), "abc")}), ["ffc/gain_", "<U3", "not numbers"]),
    (dict(manifest=_state(0, "exposures_ms_", "abc")),
     ["step 'dark'", "exposures_ms_", "expected a list of numbers"]),
    (dict(manifest=_state(0, "exposures_ms_", [2.0, 4.0])),
     ["step 'dark'", "masters_", "4 entries", "lists 2"]),
    (dict(manifest=_state(1, "selected_ms_", {"a": 1})), ["step 'ffc'", "selected_ms_"]),
    (dict(arrays={"ffc/gain_": np.zeros((8, 8), np.complex64)}), ["ffc/gain_", "complex64"]),
    (dict(arrays={"ffc/dq_": np.zeros((8, 8), np.float32)}), ["ffc", "dq_", "unsigned"]),
    (dict(arrays={"ffc/extra_": np.zeros(3)}), ["ffc", "extra_", "not one"]),
    (dict(arrays={"stray": np.zeros(3)}), ["stray", "no step"]),
], ids=["strings", "json-type", "list-length", "dict-for-list", "complex", "float-dq", "extra",
        "stray"])
def test_tampered_pipeline_is_refused_naming_the_field(sweep, pipeline_file, tmp_path, capsys,
                                                       how, names):
    pipe = _tampered(pipeline_file, tmp_path, **how)
    code = main(["correct", str(sweep / "s.tif"), "--pipeline", str(pipe), "-o",
                 str(tmp_path / "out")])
    assert code == 2
    line = _one_line(capsys, "t.npz", *names)
    assert "\x1b" not in line  # no terminal colour codes from a compiler dump


def test_pipeline_array_inflating_to_more_than_the_frame_is_refused_before_loading(
        sweep, pipeline_file, tmp_path):
    """512 MiB of zeros (0.5 MB compressed) in place of an 8 x 8 gain: refused from the .npy
    header, in a child whose memory would not hold it."""
    pipe = _tampered(pipeline_file, tmp_path)
    with zipfile.ZipFile(pipe, "a", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open("ffc/big_.npy", "w", force_zip64=True) as fh:
            header = {"descr": "<f4", "fortran_order": False, "shape": (8192, 16384)}
            np.lib.format.write_array_header_1_0(fh, header)
            block = bytes(1 << 24)
            for _ in range(32):
                fh.write(block)
    assert pipe.stat().st_size < 4_000_000
    code, err = capped_cli(["correct", sweep / "s.tif", "--pipeline", pipe, "-o",
                            tmp_path / "out"])
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "big_" in err, err


def test_valid_products_still_load(sweep, pipeline_file):
    from hsiffc.calibrate import Calibration
    from hsiffc.stages import Pipeline

    pipe = Pipeline.load(pipeline_file)
    assert [n for n, _ in pipe.steps] == ["dark", "ffc"]
    assert Calibration.load(sweep / "cal.npz").frame_shape == (8, 8)


# -- 6. damaged PNG data: hsiffc's line only, never libpng's ------------------------------------
def test_damaged_png_gives_one_line_and_nothing_from_libpng(tmp_path):
    rows = [bytes([0]) + bytes(range(k, k + 16)) for k in range(12)]
    good = hand_png(tmp_path / "good.png", 16, 12, rows=rows)
    with open_source(good, exposure_ms=1, bit_depth=8) as src:
        assert src.to_sweep().data[0, 3, 0] == 3
    blob = good.read_bytes()
    ihdr = struct.pack(">IIBBBBB", 16, 12, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"".join(rows))
    at = blob.index(b"IDAT") + 10
    (tmp_path / "crc.png").write_bytes(blob[:at] + bytes([blob[at] ^ 0xFF]) + blob[at + 1:])
    hand_png(tmp_path / "zlib.png", 16, 12,
             chunks=[(b"IHDR", ihdr), (b"IDAT", idat[:2] + b"\xff" * 20), (b"IEND", b"")])
    hand_png(tmp_path / "filter.png", 16, 12, rows=[bytes([9]) + r[1:] for r in rows])
    big = struct.pack(">IIBBBBB", 16, 2000, 8, 0, 0, 0, 0)  # a decoder might read this one
    hand_png(tmp_path / "ihdr2.png", 16, 12, chunks=[(b"IHDR", ihdr), (b"IHDR", big),
                                                 (b"IDAT", idat), (b"IEND", b"")])
    hand_png(tmp_path / "short.png", 16, 12, chunks=[
        (b"IHDR", ihdr), (b"IDAT", zlib.compress(b"".join(rows[:6]))), (b"IEND", b"")])
    names = ["crc", "zlib", "filter", "ihdr2", "short"]
    code = "".join(f"sys.stderr.write('=== {n}\\n'); sys.stderr.flush(); "
                   f"codes.append(main(['info', {str(tmp_path / (n + '.png'))!r}, "
                   "'--exposure-ms', '1', '--bit-depth', '8'])); " for n in names)
    done = subprocess.run([sys.executable, "-c", "import sys; from hsiffc.cli import main; "
                           f"codes = []; {code}sys.exit(max(codes) * (min(codes) == max(codes)))"],
                          capture_output=True, text=True,
                          timeout=120)  # a child: libpng writes to the process's stderr itself
    assert done.returncode == 2, done.stderr  # every one exit status 2
    parts = done.stderr.split("=== ")[1:]
    assert len(parts) == len(names), done.stderr
    for name, part in zip(names, parts):
        lines = [ln for ln in part.splitlines()[1:] if ln.strip()]
        assert len(lines) == 1 and f"{name}.png" in lines[0], (name, part)
    assert "libpng" not in done.stderr


# -- 7. ENVI bit depth ----------------------------------------------------------------------------
@pytest.mark.parametrize("bits, ok", [(99, False), (0, False), (17, False), (12, True)])
def test_envi_bit_depth_is_checked(tmp_path, bits, ok):
    np.zeros((2, 4, 5), np.uint16).tofile(tmp_path / "c.img")
    (tmp_path / "c.hdr").write_text(f"ENVI\nsamples = 5\nlines = 4\nbands = 2\nheader offset = 0"
                                    f"\ndata type = 12\ninterleave = bsq\nbyte order = 0\n"
                                    f"bit depth = {bits}\n")
    if ok:
        with open_source(tmp_path / "c.hdr", exposure_ms=1) as src:
            assert src.to_sweep().bit_depth == bits
    else:
        with pytest.raises(DataFormatError, match="'bit depth'.*1..16"):
            open_source(tmp_path / "c.hdr", exposure_ms=1)


# -- 8. FIFOs, devices and sockets where a file is expected -------------------------------------
def test_fifo_where_a_file_is_expected_never_blocks(sweep, tmp_path):
    """A named pipe as an EMVA descriptor, inside a folder searched for one, as a sidecar, an
    IMEC XML mosaic, a pipeline description or a calibration: each refused (or skipped) in one
    line without being opened (opening one blocked forever before)."""
    fifos = tmp_path / "fifos"
    fifos.mkdir()
    for name in ("EMVA1288_Data.txt", "notes.txt", "side.toml", "imec.xml", "p.toml", "c.npz"):
        os.mkfifo(fifos / name)
    s_tif = str(sweep / "s.tif")
    runs = [["info", str(fifos / "notes.txt")],
            ["info", str(fifos)],
            ["info", s_tif, "--sidecar", str(fifos / "side.toml")],
            ["info", s_tif, "--mosaic", str(fifos / "imec.xml")],
            ["fit", str(fifos / "p.toml"), s_tif, "-o", str(tmp_path / "p.npz")],
            ["correct", s_tif, "--calibration", str(fifos / "c.npz"), "-o", str(tmp_path / "o")]]
    code = "".join(f"sys.stderr.write('===\\n'); sys.stderr.flush(); codes.append(main({r!r})); "
                   for r in runs)
    done = subprocess.run([sys.executable, "-c", "import sys; from hsiffc.cli import main; "
                           f"codes = []; {code}sys.exit(10 * max(codes) + min(codes))"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 22, done.stderr
    parts = [[ln for ln in p.splitlines() if ln.strip()] for p in done.stderr.split("===")[1:]]
    assert [len(p) for p in parts] == [1] * len(runs), done.stderr
    for k, part in enumerate(parts):
        if k == 1:  # the folder: its FIFOs are skipped, so it holds no descriptor
            assert "no image file" in part[0] or "no EMVA 1288 descriptor" in part[0], part
        else:
            assert "named pipe (FIFO)" in part[0], part


@pytest.mark.parametrize("kind", ["fifo", "device", "socket"])
def test_special_files_are_refused_as_inputs_without_opening(tmp_path, kind):
    import socket

    path = tmp_path / "frames.tif"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        os.symlink("/dev/zero", path)
    else:
        sock = socket.socket(socket.AF_UNIX)
        sock.bind(str(path))
    with pytest.raises(DataFormatError) as info:
        open_source(path, exposure_ms=1, bit_depth=8)
    assert {"fifo": "named pipe", "device": "character device", "socket": "socket"}[kind] \
        in str(info.value)
