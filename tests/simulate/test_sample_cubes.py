"""The bundled sample cubes: checksums, content as documented, reproducible from the script."""

from __future__ import annotations

import hashlib
import importlib.util

import numpy as np
import pytest

from hsiffc.io import read_sweep

FILES = ["darks.tif", "sweep_2900K.tif", "training_2900K.tif", "test_2200K.tif"]


def _manifest(folder):
    lines = (folder / "MANIFEST.sha256").read_text().splitlines()
    return {name: digest for digest, name in (ln.split("  ", 1) for ln in lines if ln.strip())}


def test_manifest_lists_every_file_with_its_checksum(sample_cubes):
    man = _manifest(sample_cubes)
    assert sorted(man) == sorted(FILES)
    for name, digest in man.items():
        assert hashlib.sha256((sample_cubes / name).read_bytes()).hexdigest() == digest, name


def test_sample_data_stay_small(sample_cubes):
    total = sum(p.stat().st_size for p in sample_cubes.iterdir() if p.is_file())
    assert total < 10e6


def test_contents_are_as_documented(sample_cubes):
    darks = read_sweep(sample_cubes / "darks.tif")
    assert set(darks.kind) == {"dark"} and {6.45, 16.125, 32.25} <= set(darks.exposure_ms)
    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    assert sweep.bit_depth == 10 and sweep.mosaic.n_bands == 8
    assert "2900" in sweep.illumination[sweep.is_light][0]
    light = sweep.light()
    # dynamic saturation: the response levels off below full scale at long exposures
    last = light.data[light.exposure_ms == light.exposure_ms.max()].mean(axis=0)
    prev = light.data[light.exposure_ms == np.unique(light.exposure_ms)[-2]].mean(axis=0)
    assert last.mean() < sweep.full_scale_dn - 50
    assert abs(last.mean() - prev.mean()) < 2
    training = read_sweep(sample_cubes / "training_2900K.tif")
    assert sorted(set(training.exposure_ms)) == [6.45, 12.9, 19.35, 25.8, 32.25]
    assert np.all(np.bincount(training.step) == 10)
    test = read_sweep(sample_cubes / "test_2200K.tif")
    assert "2200" in test.illumination[0] and 16.125 in set(test.exposure_ms)


def test_regenerating_reproduces_the_files(sample_cubes, tmp_path):
    spec = importlib.util.spec_from_file_location("make_samples",
                                                  sample_cubes / "make_samples.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.make(tmp_path)
    for name in FILES:
        a, b = read_sweep(sample_cubes / name), read_sweep(tmp_path / name)
        assert np.array_equal(a.data, b.data), name
        assert np.array_equal(a.exposure_ms, b.exposure_ms)
    if _manifest(tmp_path) != _manifest(sample_cubes):
        pytest.fail("pixel data match but file bytes differ: a metadata field is not "
                    "reproducible (compare the JSON descriptions)")
