"""Hostile and unusual inputs, round two (issue 35): a lock file that is a hard link to an input,
valid files once refused, size limits applied to headers before any decode, malformed headers
and tampered pipeline files. Each case: inputs byte-identical afterwards, valid files read, bad
ones refused with one line naming the file and the field, exit status 2."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.errors import DataFormatError
from hsiffc.io import open_source


def _one_line(capsys, *names) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


def _digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    assert main(["simulate", str(root / "s.tif"), "--exposures-ms", "2", "4", "8", "16",
                 "--shape", "8", "8"]) == 0
    assert main(["calibrate", str(root / "s.tif"), "-o", str(root / "cal.npz")]) == 0
    return root


def _in_child(code: str, *, max_mb: int) -> subprocess.CompletedProcess:
    """Run ``code`` in a child Python whose address space is capped at ``max_mb`` MiB
    (``RLIMIT_AS``): an allocation past the cap fails there instead of passing unnoticed."""
    prelude = ("import resource\n"
               f"resource.setrlimit(resource.RLIMIT_AS, ({max_mb << 20}, {max_mb << 20}))\n")
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=120)


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
    from hsiffc.atomic import OutputError, folder_lock

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
    from hsiffc.atomic import folder_lock

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
