"""hsiffc TIFF format: round trips, hand-written files, atomic writes and every bad-file case."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc import Mosaic, Sweep
from hsiffc.errors import DataFormatError
from hsiffc.io import read_sweep, read_sweep_tiff, write_sweep
from hsiffc.io import tiff as tiffmod


def make_sweep(dtype=np.uint16, bit_depth=12, n=6, shape=(5, 7), seed=0) -> Sweep:
    rng = np.random.default_rng(seed)
    if np.issubdtype(dtype, np.integer):
        data = rng.integers(0, 2 ** bit_depth, size=(n,) + shape).astype(dtype)
    else:
        data = rng.uniform(0, 2 ** bit_depth - 1, size=(n,) + shape).astype(dtype)
    kind = ["light", "light", "dark", "dark", "light", "light"][:n]
    return Sweep(
        data=data,
        exposure_ms=[0.5, 0.5, 0.5, 0.5, 2.25, 2.25][:n],
        kind=kind,
        bit_depth=bit_depth,
        step=[0, 0, 1, 1, 2, 2][:n],
        photons=[120.5, 120.5, np.nan, np.nan, 540.0, 540.0][:n],
        illumination=["2900K", "2900K", "", "", "LED 850nm", "LED 850nm"][:n],
        mosaic=Mosaic(np.array([[0, 1], [2, 3]]), wavelengths_nm=(600.5, 650.0, 700.0, 750.0),
                      offset=(1, 0), name="2x2 test"),
        source="simulated",
        meta={"gain": 2.0, "nested": {"list": [1, 2, 3], "text": "µ-ok"}, "flag": True},
    )


def hand_written(path: Path, doc, frames) -> Path:
    """A file as a user would write it with plain tifffile."""
    text = doc if isinstance(doc, str) else json.dumps(doc)
    tifffile.imwrite(path, np.asarray(frames), photometric="minisblack", description=text,
                     metadata=None)
    return path


def assert_error(excinfo, path: Path, *hints: str):
    msg = str(excinfo.value)
    assert path.name in msg, msg
    for hint in hints:
        assert hint.lower() in msg.lower(), f"{hint!r} not in {msg!r}"


# -- round trips -----------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype,bits", [(np.uint8, 8), (np.uint16, 12), (np.uint16, 16),
                                        (np.float32, 10)])
def test_round_trip_every_field(tmp_path, dtype, bits):
    sweep = make_sweep(dtype, bits)
    out = write_sweep(tmp_path / "sweep.tif", sweep)
    assert out == tmp_path / "sweep.tif"
    back = read_sweep_tiff(out)
    assert back.data.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.data, sweep.data)
    np.testing.assert_array_equal(back.exposure_ms, sweep.exposure_ms)
    assert back.kind.tolist() == sweep.kind.tolist()
    assert back.illumination.tolist() == sweep.illumination.tolist()
    np.testing.assert_array_equal(back.photons, sweep.photons)  # NaN == NaN here
    np.testing.assert_array_equal(back.step, sweep.step)
    assert back.bit_depth == bits
    np.testing.assert_array_equal(back.mosaic.pattern, sweep.mosaic.pattern)
    assert back.mosaic.wavelengths_nm == (600.5, 650.0, 700.0, 750.0)
    assert back.mosaic.offset == (1, 0) and back.mosaic.name == "2x2 test"
    assert back.source == str(out)
    assert back.meta == {**sweep.meta, "source_in_file": "simulated"}


def test_round_trip_without_optional_fields(tmp_path):
    sweep = Sweep(np.zeros((2, 3, 4), np.uint8), exposure_ms=[1, 2], kind="dark", bit_depth=8)
    back = read_sweep_tiff(write_sweep(tmp_path / "a.tiff", sweep))
    assert back.mosaic is None and back.meta == {}
    assert np.isnan(back.photons).all()
    assert back.kind.tolist() == ["dark", "dark"]
    np.testing.assert_array_equal(back.step, sweep.step)


def test_single_frame_is_a_sweep_of_one(tmp_path):
    sweep = Sweep(np.full((4, 5), 7, np.uint16), exposure_ms=3.0, kind="light", bit_depth=10)
    back = read_sweep_tiff(write_sweep(tmp_path / "one.tif", sweep))
    assert back.data.shape == (1, 4, 5) and back.exposure_ms.tolist() == [3.0]


def test_float_nan_and_inf_are_kept_not_rejected(tmp_path):
    sweep = make_sweep(np.float32, 10)
    data = sweep.data.copy()
    data[0, 0, 0], data[1, 2, 3] = np.nan, np.inf
    sweep = Sweep(data, sweep.exposure_ms, sweep.kind, 10)
    back = read_sweep_tiff(write_sweep(tmp_path / "nan.tif", sweep))
    assert np.isnan(back.data[0, 0, 0]) and np.isinf(back.data[1, 2, 3])


def test_meta_numpy_values_and_nan_become_json(tmp_path):
    sweep = Sweep(np.zeros((1, 2, 2), np.uint8), 1.0, "light", 8,
                  meta={"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": (1, 2)})
    back = read_sweep_tiff(write_sweep(tmp_path / "m.tif", sweep))
    assert back.meta == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": [1, 2]}


def test_compression_round_trip(tmp_path):
    sweep = make_sweep(np.uint16, 12)
    back = read_sweep_tiff(write_sweep(tmp_path / "z.tif", sweep, compression="zlib"))
    np.testing.assert_array_equal(back.data, sweep.data)


def test_document_schema_is_versioned_and_one_json(tmp_path):
    out = write_sweep(tmp_path / "s.tif", make_sweep())
    with tifffile.TiffFile(out) as tf:
        doc = json.loads(tf.pages[0].description)
        assert len(tf.pages) == 6
        assert all(not p.description for p in list(tf.pages)[1:])
    assert doc["format"] == "hsiffc" and doc["format_version"] == 1
    assert doc["content"] == "frames" and doc["exposure_unit"] == "ms"
    assert doc["photons"][2] is None and doc["n_frames"] == 6
    assert doc["wavelengths_nm"] == [600.5, 650.0, 700.0, 750.0]


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 4), h=st.integers(1, 6), w=st.integers(1, 6),
       bits=st.integers(1, 16), seed=st.integers(0, 2 ** 16),
       exposure=st.floats(0, 1e6, allow_nan=False), dark=st.booleans())
def test_round_trip_property(n, h, w, bits, seed, exposure, dark):
    dtype = np.uint8 if bits <= 8 else np.uint16
    data = np.random.default_rng(seed).integers(0, 2 ** bits, size=(n, h, w)).astype(dtype)
    sweep = Sweep(data, exposure, "dark" if dark else "light", bits)
    with tempfile.TemporaryDirectory() as tmp:
        back = read_sweep_tiff(write_sweep(Path(tmp) / "p.tif", sweep))
    np.testing.assert_array_equal(back.data, data)
    assert back.data.dtype == dtype and back.bit_depth == bits
    np.testing.assert_array_equal(back.exposure_ms, sweep.exposure_ms)
    assert back.kind.tolist() == sweep.kind.tolist()


# -- hand-written files ----------------------------------------------------------------------------
def test_hand_written_minimal_file_scalar_exposure(tmp_path):
    frames = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
    path = hand_written(tmp_path / "mine.tif",
                        {"format": "hsiffc", "exposure": 10, "exposure_unit": "ms",
                         "bit_depth": 12}, frames)
    sweep = read_sweep_tiff(path)
    assert sweep.exposure_ms.tolist() == [10.0, 10.0, 10.0]
    assert sweep.kind.tolist() == ["light"] * 3           # documented default
    assert sweep.illumination.tolist() == [""] * 3
    assert sweep.step.tolist() == [0, 0, 0]
    assert sweep.bit_depth == 12 and sweep.mosaic is None
    np.testing.assert_array_equal(sweep.data, frames)


@pytest.mark.parametrize("unit,factor", [("s", 1e3), ("ms", 1.0), ("us", 1e-3), ("ns", 1e-6)])
def test_exposure_units_are_converted_to_ms(tmp_path, unit, factor):
    path = hand_written(tmp_path / f"{unit}.tif",
                        {"format": "hsiffc", "exposure": [2.0, 40.0], "exposure_unit": unit,
                         "bit_depth": 8, "kind": ["dark", "light"], "illumination": "lamp A",
                         "photons": [None, 17.5]}, np.zeros((2, 3, 3), np.uint8))
    sweep = read_sweep_tiff(path)
    np.testing.assert_allclose(sweep.exposure_ms, [2.0 * factor, 40.0 * factor])
    assert sweep.kind.tolist() == ["dark", "light"]
    assert sweep.illumination.tolist() == ["lamp A", "lamp A"]
    assert np.isnan(sweep.photons[0]) and sweep.photons[1] == 17.5


def test_hand_written_wavelengths_without_mosaic_go_to_meta(tmp_path):
    path = hand_written(tmp_path / "wl.tif",
                        {"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
                         "wavelengths_nm": [500, 600], "camera": "X"}, np.zeros((1, 2, 2), np.uint8))
    sweep = read_sweep_tiff(path)
    assert sweep.meta["wavelengths_nm"] == [500, 600]
    assert sweep.meta["extra_fields"] == {"camera": "X"}


def test_hand_written_mosaic_takes_top_level_wavelengths(tmp_path):
    path = hand_written(tmp_path / "mw.tif",
                        {"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
                         "mosaic": {"pattern": [[0, 1]]}, "wavelengths_nm": [500, 600]},
                        np.zeros((1, 2, 2), np.uint8))
    assert read_sweep_tiff(path).mosaic.wavelengths_nm == (500.0, 600.0)


# -- atomic writing --------------------------------------------------------------------------------
def test_write_leaves_no_temporary_files(tmp_path):
    write_sweep(tmp_path / "s.tif", make_sweep())
    write_sweep(tmp_path / "s.tif", make_sweep(seed=1), overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.tif"]


def test_existing_file_refused_and_left_byte_identical(tmp_path):
    path = write_sweep(tmp_path / "s.tif", make_sweep())
    before = path.read_bytes()
    with pytest.raises(FileExistsError) as excinfo:
        write_sweep(path, make_sweep(seed=5))
    assert str(path) in str(excinfo.value) and "overwrite=True" in str(excinfo.value)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.tif"]
    write_sweep(path, make_sweep(seed=5), overwrite=True)
    np.testing.assert_array_equal(read_sweep_tiff(path).data, make_sweep(seed=5).data)


def test_failed_write_leaves_nothing_behind(tmp_path, monkeypatch):
    original = write_sweep(tmp_path / "keep.tif", make_sweep())
    before = original.read_bytes()

    def broken(fh, *args, **kwargs):
        fh.write(b"II*\x00partial")
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(tiffmod.tifffile, "imwrite", broken)
    with pytest.raises(OSError, match="disk full"):
        write_sweep(tmp_path / "new.tif", make_sweep())
    with pytest.raises(OSError, match="disk full"):
        write_sweep(original, make_sweep(seed=3), overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.tif"]
    assert original.read_bytes() == before


def test_write_rejects_bad_requests(tmp_path):
    with pytest.raises(DataFormatError) as excinfo:
        write_sweep(tmp_path / "s.png", make_sweep())
    assert_error(excinfo, tmp_path / "s.png", ".tif")
    # a missing folder is created, as by every writer (calibrate -o, correct -o, --json):
    # simulate alone refused it, with a message that named "a file"
    made = write_sweep(tmp_path / "missing" / "s.tif", make_sweep())
    assert made.is_file()
    made.unlink()
    made.parent.rmdir()
    bad = Sweep(np.full((1, 2, 2), 300, np.uint16), 1.0, "light", 8)
    with pytest.raises(DataFormatError) as excinfo:
        write_sweep(tmp_path / "b.tif", bad)
    assert_error(excinfo, tmp_path / "b.tif", "exceed the stated bit depth")
    with pytest.raises(DataFormatError) as excinfo:
        write_sweep(tmp_path / "i.tif", Sweep(np.zeros((1, 2, 2), np.int64), 1.0, "light", 8))
    assert_error(excinfo, tmp_path / "i.tif", "float32")
    with pytest.raises(TypeError, match="JSON"):
        write_sweep(tmp_path / "o.tif",
                    Sweep(np.zeros((1, 2, 2), np.uint8), 1.0, "light", 8, meta={"x": object()}))
    assert not list(tmp_path.iterdir())


# -- bad files -------------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(tmp_path / "nothere.tif")
    assert_error(excinfo, tmp_path / "nothere.tif", "not found", "check the path")


def test_not_a_tiff(tmp_path):
    path = tmp_path / "fake.tif"
    path.write_text("this is not an image\n")
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "not a readable TIFF", "write it again")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.tif"
    path.write_bytes(b"")
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "empty", "write it again")


@pytest.mark.parametrize("keep", [0.05, 0.2, 0.35, 0.5, 0.65, 0.8, 0.95, 0.999])
@pytest.mark.parametrize("compression", [None, "zlib"])
def test_truncated_file(tmp_path, keep, compression):
    full = write_sweep(tmp_path / "full.tif", make_sweep(np.uint16, 12, shape=(40, 30)),
                       compression=compression)
    blob = full.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(blob[:int(len(blob) * keep)])
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(cut)
    assert_error(excinfo, cut, "truncated")


def test_plain_tiff_says_which_json_to_add(tmp_path):
    path = tmp_path / "plain.tif"
    tifffile.imwrite(path, np.zeros((2, 3, 3), np.uint8), photometric="minisblack")
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "without hsiffc metadata", '"format": "hsiffc"', '"exposure"',
                 '"exposure_unit": "ms"', '"bit_depth"')


@pytest.mark.parametrize("doc,hints", [
    ("not json {", ["without hsiffc metadata"]),
    ("{not json", ["not valid JSON", '"format": "hsiffc"']),
    ({"format": "other"}, ["without hsiffc metadata", '"format": "hsiffc"']),
    ({"shape": [2, 3, 3]}, ["without hsiffc metadata", '"format": "hsiffc"']),
    ({"format": "hsiffc", "exposure_unit": "ms", "bit_depth": 8}, ["no 'exposure'", "exposure"]),
    ({"format": "hsiffc", "exposure": 1, "bit_depth": 8}, ["exposure_unit", '"ms"']),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "min", "bit_depth": 8},
     ["unknown exposure_unit 'min'", "'ns'"]),
    ({"format": "hsiffc", "exposure": [1, 2, 3], "exposure_unit": "ms", "bit_depth": 8},
     ["3 entries", "2 pages", "one entry per page"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "kind": ["light"]}, ["'kind' has 1 entries", "2 pages"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "illumination": ["a", "b", "c"]}, ["'illumination' has 3 entries"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "photons": [1.0]}, ["'photons' has 1 entries"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "step": [0, 1, 2]}, ["'step' has 3 entries"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms"}, ["no 'bit_depth'", "bit_depth"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": "twelve"},
     ["bit_depth", "1..32"]),
    ({"format": "hsiffc", "exposure": -1, "exposure_unit": "ms", "bit_depth": 8},
     [">= 0", "fix the JSON"]),
    ({"format": "hsiffc", "exposure": "long", "exposure_unit": "ms", "bit_depth": 8},
     ["'exposure'", "not valid"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "kind": "bright"}, ["'bright'", "light"]),
    ({"format": "hsiffc", "format_version": 99, "exposure": 1, "exposure_unit": "ms",
      "bit_depth": 8}, ["format_version 99", "upgrade hsiffc"]),
    ({"format": "hsiffc", "content": "cube", "exposure": 1, "exposure_unit": "ms",
      "bit_depth": 8}, ["'cube'", "reader"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "mosaic": {"pattern": [[0, 2]]}}, ["invalid 'mosaic'"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "meta": [1, 2]}, ["'meta' must be a JSON object"]),
    ({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8,
      "n_frames": 5}, ["declares 5 frames", "truncated"]),
])
def test_bad_metadata(tmp_path, doc, hints):
    path = hand_written(tmp_path / "bad.tif", doc, np.zeros((2, 3, 3), np.uint8))
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, *hints)


def test_data_above_bit_depth(tmp_path):
    frames = np.zeros((2, 3, 3), np.uint16)
    frames[1, 2, 2] = 1024
    path = hand_written(tmp_path / "over.tif", {"format": "hsiffc", "exposure": 1,
                                                "exposure_unit": "ms", "bit_depth": 10}, frames)
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "data exceed the stated bit depth", "1024", "1023", "bit_depth")


def test_pages_of_different_shapes(tmp_path):
    path = tmp_path / "shapes.tif"
    doc = json.dumps({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8})
    with tifffile.TiffWriter(path) as tw:
        tw.write(np.zeros((4, 4), np.uint8), description=doc, metadata=None)
        tw.write(np.zeros((5, 4), np.uint8), metadata=None)
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "one shape", "(4, 4)", "(5, 4)")


def test_rgb_pages_are_rejected(tmp_path):
    path = tmp_path / "rgb.tif"
    doc = json.dumps({"format": "hsiffc", "exposure": 1, "exposure_unit": "ms", "bit_depth": 8})
    tifffile.imwrite(path, np.zeros((4, 4, 3), np.uint8), photometric="rgb", description=doc,
                     metadata=None)
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(path)
    assert_error(excinfo, path, "single-channel")


def test_folder_given_as_tiff(tmp_path):
    folder = tmp_path / "dir.tif"
    folder.mkdir()
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep_tiff(folder)
    assert_error(excinfo, folder, "folder")


# -- dispatcher ------------------------------------------------------------------------------------
def test_read_sweep_dispatches_tiff(tmp_path):
    sweep = make_sweep()
    path = write_sweep(tmp_path / "S.TIFF", sweep)
    np.testing.assert_array_equal(read_sweep(path).data, sweep.data)


def test_read_sweep_rejects_other_inputs(tmp_path):
    other = tmp_path / "frames.npy"
    np.save(other, np.zeros((2, 2)))
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep(other)
    assert_error(excinfo, other, ".tif", ".txt", "folder")
    with pytest.raises(DataFormatError) as excinfo:
        read_sweep(tmp_path / "gone.tif")
    assert_error(excinfo, tmp_path / "gone.tif", "not found", ".tif")


def test_env_does_not_leak_files(tmp_path):
    """Writing inside a folder never creates anything else there (also checks permissions)."""
    path = write_sweep(tmp_path / "perm.tif", make_sweep())
    mode = path.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask
