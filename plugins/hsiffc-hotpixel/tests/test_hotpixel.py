"""Tests of the hot_pixel_repair plugin stage (fast: small simulated sensors)."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.data.dq import DQ
from hsiffc.data.frame import Frame
from hsiffc.data.mosaic import Mosaic
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor, SensorParams
from hsiffc.stages import NotFittedError, check_stage
from hsiffc_hotpixel import HotPixelRepair, same_band_median, same_band_offsets


def _frames(sensor, cap, kind):
    return cap.to_frames(kind)


@pytest.fixture(scope="module")
def sim():
    sensor = MosaicSensor((64, 64), seed=5,
                          params=SensorParams(hot_fraction=0.01, dead_fraction=0.01))
    light = sensor.capture(10.0, "lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2["training"],
                           n_frames=3)
    train = (_frames(sensor, sensor.capture(200.0, None, n_frames=3), "dark")
             + _frames(sensor, light, "light")
             + _frames(sensor, sensor.capture(10.0, None, n_frames=3), "dark"))
    return sensor, train


def test_offsets_are_whole_tiles():
    assert same_band_offsets((1, 1)) == [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1),
                                         (1, -1), (1, 0), (1, 1)]
    assert len(same_band_offsets((2, 4), radius=2)) == 24
    band = Mosaic.rectangular(2, 4).band_map((12, 24))
    for dy, dx in same_band_offsets((2, 4), radius=2):
        assert np.array_equal(band[4:8, 8:12], band[4 + dy:8 + dy, 8 + dx:12 + dx])


def test_same_band_median_excludes_and_edges():
    values = np.arange(25, dtype=np.float32).reshape(5, 5)
    med = same_band_median(values, same_band_offsets((1, 1)))
    assert med[2, 2] == 12.0  # symmetric neighbourhood
    assert med[0, 0] == np.median([1, 5, 6])  # only the neighbours on the sensor
    exclude = np.zeros((5, 5), bool)
    exclude[[0, 1], [1, 1]] = True
    one = same_band_median(values, same_band_offsets((1, 1)), np.array([0]), np.array([0]),
                           exclude=exclude)
    assert one[0] == 5.0
    exclude[:] = True
    assert np.isnan(same_band_median(values, same_band_offsets((1, 1)), np.array([2]),
                                     np.array([2]), exclude=exclude)[0])


def test_detects_simulated_defects(sim):
    sensor, train = sim
    stage = HotPixelRepair().fit(train)
    assert np.array_equal(stage.hot_.astype(bool), sensor.hot)
    assert np.array_equal(stage.dead_.astype(bool), sensor.dead)
    assert stage.n_hot_ == int(sensor.hot.sum()) > 0
    assert stage.n_dead_ == int(sensor.dead.sum()) > 0
    assert stage.hot_.dtype == np.uint8 and stage.dark_exposure_ms_ == 200.0
    assert stage.flat_exposure_ms_ == 10.0 and 1.0 < stage.sigma_dn_ < 4.0


def test_unmatched_flat_uses_master_dark(sim):
    sensor, train = sim
    stage = HotPixelRepair().fit(train[:6])  # darks at 200 ms only, flats at 10 ms
    assert np.array_equal(stage.hot_.astype(bool), sensor.hot)
    assert np.array_equal(stage.dead_.astype(bool), sensor.dead)


def test_transform_repairs_flags_and_keeps_input(sim):
    sensor, train = sim
    stage = HotPixelRepair().fit(train)
    frame = train[3]
    dq_in = frame.dq.copy()
    dq_in[0, 0] |= DQ.SATURATED
    frame = frame.replace(dq=dq_in)
    before = frame.data.copy()
    out = stage.transform(frame)
    assert np.array_equal(frame.data, before) and np.array_equal(frame.dq, dq_in)
    assert np.all(np.isfinite(out.data))
    assert np.all(out.dq[sensor.hot] & DQ.HOT) and np.all(out.dq[sensor.dead] & DQ.DEAD)
    assert out.dq[0, 0] & DQ.SATURATED
    good = ~(sensor.hot | sensor.dead)
    assert np.array_equal(out.data[good], frame.data[good])
    band = sensor.band_map
    level = np.array([np.median(frame.data[(band == b) & good]) for b in range(8)])[band]
    assert np.abs(out.data - level)[~good].max() < 0.1 * level.min()
    assert out.meta["hot_pixel_repair"]["hot"] == int(sensor.hot.sum())


def test_no_usable_neighbour_keeps_value_without_nan():
    frames = [Frame.from_raw(np.full((3, 3), 10.0), exposure_ms=50.0, bit_depth=10,
                             kind="dark")]
    stage = HotPixelRepair().fit(frames)
    stage.hot_ = np.ones((3, 3), np.uint8)  # every neighbour flagged
    out = stage.transform(frames[0])
    assert np.all(out.data == 10.0)
    assert np.all(out.dq & DQ.DO_NOT_USE) and out.meta["hot_pixel_repair"]["unrepaired"] == 9


def test_uniform_dark_finds_nothing():
    frames = [Frame.from_raw(np.full((8, 8), 32.0), exposure_ms=50.0, bit_depth=10, kind="dark")]
    stage = HotPixelRepair().fit(frames)
    assert stage.n_hot_ == 0 and stage.n_dead_ == 0 and stage.flat_exposure_ms_ is None


def test_contract_and_errors(sim):
    sensor, train = sim
    check_stage(HotPixelRepair(radius=2), train, train[4])
    with pytest.raises(NotFittedError):
        HotPixelRepair().transform(train[0])
    for bad in ({"hot_sigma": 0}, {"dead_fraction": 1.5}, {"radius": 0}, {"radius": 1.5}):
        with pytest.raises(ValueError):
            HotPixelRepair(**bad).fit(train)
    with pytest.raises(ValueError, match="before the dark stage"):
        HotPixelRepair().fit([f.replace(dark_removed=np.zeros_like(f.data)) for f in train])
    stage = HotPixelRepair().fit(train)
    small = Frame.from_raw(np.zeros((8, 8)), exposure_ms=1.0, bit_depth=10,
                           mosaic=sensor.mosaic)
    with pytest.raises(ValueError, match="shape"):
        stage.transform(small)
