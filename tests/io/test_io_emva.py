"""EMVA 1288 reader: the real Reference Set (read once per module) and synthetic bad descriptors."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from hsiffc.errors import DataFormatError
from hsiffc.io import read_emva1288, read_sweep
from hsiffc.io.emva import find_emva_descriptor

H, W = 6, 8  # synthetic frames: 6 rows x 8 columns ("n 8 8 6")


# -- real data -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def real(emva_dir):
    start = time.perf_counter()
    sweep = read_emva1288(emva_dir)
    return sweep, time.perf_counter() - start


def _descriptor_records(path: Path):
    """(kind, exposure, photons, image) per image line, parsed independently of the reader."""
    records, current = [], None
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if parts[0] == "b":
            current = ("light", float(parts[1]), float(parts[2]))
        elif parts[0] == "d":
            current = ("dark", float(parts[1]), np.nan)
        elif parts[0] == "i":
            records.append(current + (parts[1],))
    return records


@pytest.mark.realdata
def test_real_shape_dtype_bits(real):
    sweep, _ = real
    assert sweep.bit_depth == 8
    assert sweep.data.dtype == np.uint8
    assert sweep.data.shape == (600, 128, 256)
    assert sweep.meta["format"] == "emva1288" and sweep.meta["version"] == "3.0"
    assert any("ROI" in c for c in sweep.meta["comments"])


@pytest.mark.realdata
def test_real_sweep_and_spatial_structure(real):
    sweep, _ = real
    sweep_steps, spatial = sweep.meta["sweep_steps"], sweep.meta["spatial_steps"]
    assert len(sweep_steps) == 200 and len(spatial) == 2
    for s in sweep_steps:
        assert np.count_nonzero(sweep.step == s) == 2
    kinds = [sweep.kind[sweep.step == s][0] for s in sweep_steps]
    assert kinds.count("light") == 100 and kinds.count("dark") == 100
    spatial_kinds = sorted(sweep.kind[sweep.step == s][0] for s in spatial)
    assert spatial_kinds == ["dark", "light"]
    for s in spatial:
        assert np.count_nonzero(sweep.step == s) == 100
        names = [n for n, k in zip(sweep.meta["image_files"], sweep.step) if k == s]
        assert all("_s_" in n for n in names)          # detected structurally, named so
    t = {float(sweep.exposure_ms[sweep.step == s][0]) for s in spatial}
    assert len(t) == 1                                   # one exposure for the spatial set
    assert sweep.is_light.sum() == 300 and sweep.is_dark.sum() == 300


@pytest.mark.realdata
def test_real_acquisition_order_exposure_and_photons(real, emva_dir):
    sweep, _ = real
    records = _descriptor_records(emva_dir / "EMVA1288_Data.txt")
    assert len(records) == sweep.n_frames
    assert sweep.meta["image_files"] == [r[3] for r in records]
    assert sweep.kind.tolist() == [r[0] for r in records]
    assert np.all(np.diff(sweep.step) >= 0) and sweep.step[0] == 0 and sweep.step[-1] == 201
    # default unit: ns (EMVA 1288 convention) -> ms
    np.testing.assert_allclose(sweep.exposure_ms, [r[1] * 1e-6 for r in records])
    assert sweep.exposure_ms[2] == pytest.approx(40e-6)  # "b 040.00 018.25" -> 40 ns
    np.testing.assert_array_equal(sweep.photons, [r[2] for r in records])
    assert sweep.photons[2] == 18.25 and np.isnan(sweep.photons[sweep.is_dark]).all()
    assert (sweep.illumination == "").all()


@pytest.mark.realdata
def test_real_levels(real):
    sweep, _ = real
    dark_mean = sweep.data[sweep.is_dark].mean()
    assert 2.7 < dark_mean < 3.1  # measured 2.873 DN over every dark frame
    light_steps = [s for s in sweep.meta["sweep_steps"] if sweep.kind[sweep.step == s][0] == "light"]
    brightest = sorted(light_steps, key=lambda s: sweep.photons[sweep.step == s][0])[-5:]
    top = sweep.data[np.isin(sweep.step, brightest)].max(axis=0)
    assert (top == 255).mean() > 0.5                      # most pixels clip at 255
    assert (top < 255).sum() > 1000                       # several thousand never reach 255


@pytest.mark.realdata
def test_real_read_is_fast(real):
    _, seconds = real
    assert seconds < 10.0, f"reading the full set took {seconds:.1f} s"


@pytest.mark.realdata
def test_real_subset_and_unit(emva_dir):
    sub = read_emva1288(emva_dir / "EMVA1288_Data.txt", steps=[1, 100], max_frames_per_step=3,
                        exposure_unit="us")
    assert sub.step.tolist() == [1, 1, 100, 100, 100]
    assert sub.exposure_ms[0] == pytest.approx(0.040)    # 40 us
    assert sub.meta["spatial_steps"] == [100] and sub.meta["sweep_steps"] == [1]
    assert sub.meta["exposure_unit_in_descriptor"] == "us"


@pytest.mark.realdata
def test_real_round_trip_through_tiff(real, tmp_path):
    from hsiffc.io import write_sweep
    sweep, _ = real
    back = read_sweep(write_sweep(tmp_path / "emva.tif", sweep))
    np.testing.assert_array_equal(back.data, sweep.data)
    np.testing.assert_array_equal(back.exposure_ms, sweep.exposure_ms)
    np.testing.assert_array_equal(back.photons, sweep.photons)
    np.testing.assert_array_equal(back.step, sweep.step)
    assert back.kind.tolist() == sweep.kind.tolist() and back.bit_depth == 8
    assert back.meta["spatial_steps"] == sweep.meta["spatial_steps"]
    assert back.meta["source_in_file"] == sweep.source


@pytest.mark.realdata
def test_read_sweep_dispatches_folder_and_txt(emva_dir):
    for target in (emva_dir, emva_dir / "EMVA1288_Data.txt"):
        sweep = read_sweep(target)
        assert sweep.data.shape == (600, 128, 256)


# -- synthetic descriptors ---------------------------------------------------------------------------
def png(path: Path, value=10, shape=(H, W), dtype=np.uint8) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full(shape, value, dtype=dtype))
    return path.name


def make_set(root: Path, *, steps=None, header="v 3.0\nn 8 8 6\n", name="EMVA1288_Data.txt",
             spatial=0) -> Path:
    """A small valid measurement; ``steps`` is a list of (line, n_images, value)."""
    steps = steps or [("b 1000 5.5", 2, 40), ("b 2000 11.0", 2, 80), ("d 1000", 2, 3),
                      ("d 2000", 2, 4)]
    if spatial:
        steps = steps[:2] + [("b 1500 8.0", spatial, 60)] + steps[2:] + [("d 1500", spatial, 3)]
    lines = ["# synthetic test set", header.rstrip("\n")]
    for k, (line, n, value) in enumerate(steps):
        lines.append(line)
        for j in range(n):
            lines.append("i images/s{:02d}_{:03d}.png".format(k, j))
            png(root / "images" / f"s{k:02d}_{j:03d}.png", value + j)
    path = root / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_synthetic_valid_set(tmp_path):
    desc = make_set(tmp_path)
    sweep = read_emva1288(desc)
    assert sweep.data.shape == (8, H, W) and sweep.data.dtype == np.uint8
    assert sweep.kind.tolist() == ["light"] * 4 + ["dark"] * 4
    assert sweep.step.tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
    np.testing.assert_allclose(sweep.exposure_ms, [1e-3] * 2 + [2e-3] * 2 + [1e-3] * 2 + [2e-3] * 2)
    assert sweep.photons[:4].tolist() == [5.5, 5.5, 11.0, 11.0] and np.isnan(sweep.photons[4:]).all()
    assert sweep.data[0, 0, 0] == 40 and sweep.data[1, 0, 0] == 41 and sweep.data[-1, 0, 0] == 5
    assert sweep.meta["comments"] == ["synthetic test set"]
    assert sweep.meta["spatial_steps"] == [] and sweep.meta["sweep_steps"] == [0, 1, 2, 3]
    assert sweep.source == str(desc)


@pytest.mark.parametrize("unit,factor", [("s", 1e3), ("ms", 1.0), ("us", 1e-3), ("ns", 1e-6)])
def test_synthetic_exposure_unit(tmp_path, unit, factor):
    sweep = read_emva1288(make_set(tmp_path), exposure_unit=unit)
    assert sweep.exposure_ms[0] == pytest.approx(1000 * factor)


def test_unknown_exposure_unit_argument(tmp_path):
    with pytest.raises(ValueError, match="exposure_unit"):
        read_emva1288(make_set(tmp_path), exposure_unit="min")


def test_synthetic_spatial_detection(tmp_path):
    sweep = read_emva1288(make_set(tmp_path, spatial=10))
    assert sweep.meta["spatial_steps"] == [2, 5]
    assert sweep.meta["sweep_steps"] == [0, 1, 3, 4]
    assert sweep.n_frames == 28
    assert sweep.kind[sweep.step == 2][0] == "light" and sweep.kind[sweep.step == 5][0] == "dark"


def test_synthetic_subset(tmp_path):
    desc = make_set(tmp_path, spatial=10)
    sweep = read_emva1288(desc, steps=[5, 0], max_frames_per_step=4)
    assert sweep.step.tolist() == [0, 0, 5, 5, 5, 5]        # descriptor order kept
    assert sweep.meta["spatial_steps"] == [5]
    with pytest.raises(ValueError, match="do not exist"):
        read_emva1288(desc, steps=[99])
    with pytest.raises(ValueError, match="no step"):
        read_emva1288(desc, steps=[])


def test_folder_with_single_other_descriptor_and_windows_paths(tmp_path):
    desc = make_set(tmp_path, name="measurement.txt")
    desc.write_text(desc.read_text().replace("images/", "images\\"))
    (tmp_path / "notes.txt").write_text("just notes\n")
    assert find_emva_descriptor(tmp_path) == desc
    assert read_sweep(tmp_path).n_frames == 8


def test_tiff_images_and_16_bit(tmp_path):
    (tmp_path / "img").mkdir()
    lines = ["v 3.0", "n 12 8 6", "b 10 1", "i img/a.tif", "i img/b.png", "d 10 0", "i img/c.tif"]
    tifffile.imwrite(tmp_path / "img" / "a.tif", np.full((H, W), 4095, np.uint16))
    png(tmp_path / "img" / "b.png", 1000, dtype=np.uint16)
    tifffile.imwrite(tmp_path / "img" / "c.tif", np.full((H, W), 7, np.uint16))
    (tmp_path / "d.txt").write_text("\n".join(lines))
    sweep = read_emva1288(tmp_path / "d.txt")
    assert sweep.data.dtype == np.uint16 and sweep.bit_depth == 12
    assert sweep.data[:, 0, 0].tolist() == [4095, 1000, 7]


# -- bad descriptors ---------------------------------------------------------------------------------
def edit(desc: Path, old: str, new: str) -> Path:
    text = desc.read_text()
    assert old in text
    desc.write_text(text.replace(old, new, 1))
    return desc


def line_of(desc: Path, fragment: str) -> int:
    return next(k for k, line in enumerate(desc.read_text().splitlines(), 1) if fragment in line)


def check(excinfo, desc: Path, *hints):
    msg = str(excinfo.value)
    assert desc.name in msg, msg
    for hint in hints:
        assert hint in msg, f"{hint!r} not in {msg!r}"


def test_missing_descriptor(tmp_path):
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(tmp_path / "EMVA1288_Data.txt")
    check(excinfo, tmp_path / "EMVA1288_Data.txt", "not found", "check the path")
    folder = tmp_path / "empty"
    folder.mkdir()
    (folder / "readme.txt").write_text("no version line here\n")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(folder)
    check(excinfo, folder, "no EMVA 1288 descriptor", "give the descriptor file")


def test_folder_with_two_descriptors(tmp_path):
    make_set(tmp_path, name="one.txt")
    make_set(tmp_path, name="two.txt")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(tmp_path)
    check(excinfo, tmp_path, "several", "one.txt", "two.txt")


@pytest.mark.parametrize("old,new,hints", [
    ("b 2000 11.0", "b 2000", ["malformed 'b' line", "b <exposure> <photons>"]),
    ("b 2000 11.0", "b 2000 eleven", ["not a number"]),
    ("b 2000 11.0", "b -2000 11.0", ["negative"]),
    ("d 2000", "d 2000 5", ["dark step cannot have photons"]),
    ("d 2000", "x 2000", ["malformed line", "#, v, n, b, d or i"]),
    ("v 3.0", "v", ["malformed version line"]),
])
def test_malformed_lines(tmp_path, old, new, hints):
    desc = edit(make_set(tmp_path), old, new)
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, new)}", *hints)


def test_image_before_any_step(tmp_path):
    desc = edit(make_set(tmp_path), "n 8 8 6\n", "n 8 8 6\ni images/s00_000.png\n")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "line 4", "before any 'b' or 'd'")


def test_image_line_without_path(tmp_path):
    desc = edit(make_set(tmp_path), "i images/s01_000.png", "i")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "without an image path")


def test_missing_image(tmp_path):
    desc = make_set(tmp_path)
    (tmp_path / "images" / "s02_001.png").unlink()
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, 's02_001')}", "s02_001.png", "not found")


@pytest.mark.parametrize("keep", [0, 10, 40, 0.5, -12])
def test_truncated_or_unreadable_png(tmp_path, keep):
    desc = make_set(tmp_path)
    image = tmp_path / "images" / "s01_001.png"
    blob = image.read_bytes()
    cut = keep if isinstance(keep, int) and keep >= 0 else (
        int(len(blob) * keep) if isinstance(keep, float) else len(blob) + keep)
    image.write_bytes(blob[:cut])
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, 's01_001')}", "s01_001.png",
          "unreadable or truncated")


def test_not_an_image(tmp_path):
    desc = make_set(tmp_path)
    (tmp_path / "images" / "s00_000.png").write_text("hello")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "s00_000.png", "unreadable or truncated")


def test_truncated_tiff_image(tmp_path):
    desc = make_set(tmp_path)
    tifffile.imwrite(tmp_path / "images" / "t.tif", np.zeros((H, W), np.uint8))
    (tmp_path / "images" / "t.tif").write_bytes((tmp_path / "images" / "t.tif").read_bytes()[:30])
    edit(desc, "i images/s03_001.png", "i images/t.tif")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "t.tif", "unreadable or truncated")


@pytest.mark.parametrize("shape", [(W, H), (H, W + 1), (H, W, 3)])
def test_wrong_image_size(tmp_path, shape):
    desc = make_set(tmp_path)
    png(tmp_path / "images" / "s01_000.png", 9, shape=shape)
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, 's01_000')}", "s01_000.png", "6 rows x 8 columns")


def test_step_without_images(tmp_path):
    desc = edit(make_set(tmp_path), "d 1000\n", "d 500\nd 1000\n")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, 'd 500')}", "no 'i' image lines")


def test_descriptor_without_steps(tmp_path):
    desc = tmp_path / "EMVA1288_Data.txt"
    desc.write_text("v 3.0\nn 8 8 6\n")
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "no 'b' or 'd' step")


@pytest.mark.parametrize("old,new,hints", [
    ("n 8 8 6\n", "", ["unknown bit depth", "'n <bits> <width> <height>'"]),
    ("n 8 8 6", "n 0 8 6", ["line 3", "unknown bit depth 0"]),
    ("n 8 8 6", "n 24 8 6", ["line 3", "unknown bit depth 24"]),
    ("n 8 8 6", "n 8 8", ["line 3", "malformed 'n' line"]),
    ("n 8 8 6", "n 8.5 8 6", ["line 3", "whole numbers"]),
    ("n 8 8 6", "n 8 8 6\nn 10 8 6", ["line 4", "contradicts"]),
])
def test_bad_header(tmp_path, old, new, hints):
    desc = edit(make_set(tmp_path), old, new)
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, *hints)


def test_values_above_bit_depth(tmp_path):
    desc = edit(make_set(tmp_path), "n 8 8 6", "n 7 8 6")
    png(tmp_path / "images" / "s01_001.png", 200)
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, f"line {line_of(desc, 's01_001')}", "200 DN", "127 DN", "bit depth")


def test_16_bit_image_in_8_bit_set(tmp_path):
    desc = make_set(tmp_path)
    png(tmp_path / "images" / "s00_001.png", 100, dtype=np.uint16)
    with pytest.raises(DataFormatError) as excinfo:
        read_emva1288(desc)
    check(excinfo, desc, "s00_001.png", "uint16", "8-bit")


def test_read_sweep_dispatch_synthetic(tmp_path):
    desc = make_set(tmp_path)
    assert read_sweep(desc).n_frames == 8
    assert read_sweep(tmp_path).n_frames == 8
