"""The Sweep container and Mosaic layouts."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc import DQ, Mosaic, Sweep
from hsiffc.data.dq import describe


def test_mosaic_band_map_with_offset_and_rectangular_tiles():
    m = Mosaic(np.arange(25).reshape(5, 5), offset=(3, 0))
    bm = m.band_map((10, 7))
    assert bm[3, 0] == 0 and bm[3, 4] == 4 and bm[4, 0] == 5 and bm[2, 0] == 20
    r = Mosaic.rectangular(2, 4)
    assert r.n_bands == 8 and r.band_map((2, 8))[1].tolist() == [4, 5, 6, 7, 4, 5, 6, 7]
    assert Mosaic.from_dict(r.to_dict()) == r


@pytest.mark.parametrize("pattern,msg", [
    (np.array([[0, 2]]), "every band index"),
    (np.zeros((2, 2, 2), int), "2-D integer"),
    (np.array([[0.0, 1.0]]), "2-D integer"),
])
def test_mosaic_rejects_bad_patterns(pattern, msg):
    with pytest.raises(ValueError, match=msg):
        Mosaic(pattern)


def test_mosaic_wavelength_count_must_match():
    with pytest.raises(ValueError, match="wavelengths_nm has 3"):
        Mosaic.square(2, wavelengths_nm=[1, 2, 3])


def test_sweep_groups_steps_and_selects():
    data = np.arange(6 * 2 * 2).reshape(6, 2, 2)
    sw = Sweep(data, [1, 1, 1, 1, 2, 2], ["light", "light", "dark", "dark", "light", "light"],
               8, photons=[10, 10, np.nan, np.nan, 20, 20])
    assert sw.step.tolist() == [0, 0, 1, 1, 2, 2]
    assert sw.light().n_frames == 4 and sw.dark().exposure_ms.tolist() == [1, 1]
    means = sw.step_means()
    assert means["n_frames"].tolist() == [2, 2, 2]
    assert np.allclose(means["data"][2], data[4:6].mean(axis=0))
    assert np.allclose(sw.light_rate_relative(), [10, 10, np.nan, np.nan, 10, 10], equal_nan=True)
    assert sw.full_scale_dn == 255 and "6 frames (4 light, 2 dark)" in sw.summary()


@pytest.mark.parametrize("kwargs,msg", [
    (dict(exposure_ms=[1, -1]), "exposure_ms must be finite and >= 0"),
    (dict(exposure_ms=[1, np.nan]), "exposure_ms must be finite"),
    (dict(kind=["light", "bright"]), "kind must be one of"),
    (dict(exposure_ms=[1, 2, 3]), "one entry per frame"),
    (dict(bit_depth=0), "bit_depth"),
])
def test_sweep_rejects_bad_metadata(kwargs, msg):
    args = dict(data=np.zeros((2, 3, 3)), exposure_ms=[1, 2], kind=["light", "light"], bit_depth=10)
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        Sweep(**args)


def test_dq_names():
    assert describe(DQ.SATURATED | DQ.LEAKAGE) == ["SATURATED", "LEAKAGE"]
    assert describe(0) == []
