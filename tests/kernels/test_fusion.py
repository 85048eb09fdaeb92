"""Stage fusion (hsiffc.stages.fusion): a pipeline's dark + alpha mask + two-point FFC run as
one pass must give the frame the stages give one by one, bit for bit, with the same history,
on simulated frames (with saturated, non-finite and flagged pixels, both sizes of kernel
build) and on the real EMVA 1288 sweep."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from hsiffc.calibrate import calibrate
from hsiffc.data.dq import DQ
from hsiffc.data.frame import Frame
from hsiffc.io import read_emva1288
from hsiffc.kernels.launch import PARALLEL_MIN
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create
from hsiffc.stages import fusion
from hsiffc.spectral.bandstats import band_reduce
from hsiffc.data.mosaic import row_period, single_band_map
from hsiffc.leakage.validity import subtract_dark_and_flag

TRAIN = PAPER_LIGHT_W_M2["training"]


def _stage_by_stage(pipe, frame):
    """The pipeline's result with fusion switched off (every stage's own transform)."""
    return pipe.transform(frame, fuse=False)


def _assert_same_frame(a: Frame, b: Frame):
    for field in ("data", "dq", "alpha", "dark_removed"):
        x, y = getattr(a, field), getattr(b, field)
        assert x.dtype == y.dtype and x.shape == y.shape, field
        assert np.array_equal(x, y, equal_nan=True), field
    assert a.corrected_by == b.corrected_by
    assert a.meta == b.meta  # history, dark source, alpha threshold, FFC meta


@pytest.fixture(scope="module")
def sim():
    """A (272, 512) sensor: over PARALLEL_MIN pixels, so the kernels' parallel build runs;
    its calibration from a small sweep; training darks and flats."""
    s = MosaicSensor((272, 512), seed=3)
    assert s.shape[0] * s.shape[1] >= PARALLEL_MIN
    cal = calibrate(s.sweep(np.round(np.geomspace(2, 400, 10), 3), "lamp A",
                            irradiance_w_m2=0.25 * TRAIN, n_frames=1, seed=1))
    train = Frame.list_from_sweep(s.sweep([12.9, 19.35, 25.8], "lamp A", irradiance_w_m2=TRAIN,
                                          n_frames=2, seed=2))
    return s, cal, train


def _pipe(cal, train, **ffc):
    return Pipeline([("dark", create("dark", match="scale")),
                     ("mask", create("alpha_mask", calibration=cal)),
                     ("ffc", create("two_point_ffc", calibration=cal, **ffc))]).fit(train)


@pytest.mark.parametrize("ffc", [{}, {"normalisation": "mean_gain"}, {"exposure_ms": 19.35}])
def test_fused_front_end_equals_the_stages_one_by_one(sim, ffc):
    s, cal, train = sim
    pipe = _pipe(cal, train, **ffc)
    raw = s.capture(40.0, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"], seed=4).frames[0]
    raw = raw.astype(np.float32)
    raw[5, 7] = np.nan  # NONFINITE (set to 0 DN by from_raw), a saturated pixel, a hot row
    raw[9, :40] = 1023
    frame = Frame.from_raw(raw, exposure_ms=40.0, bit_depth=10, mosaic=s.mosaic)
    assert fusion.fusable(pipe.steps, frame) == 3
    fused = pipe.transform(frame)
    assert np.count_nonzero(fused.dq) > 40 and fused.alpha is not None
    _assert_same_frame(fused, _stage_by_stage(pipe, frame))


@pytest.fixture(scope="module")
def small_sim():
    """A (32, 64) sensor (under PARALLEL_MIN: the kernels' serial build), its calibration and
    training flats."""
    s = MosaicSensor((32, 64), seed=5)
    cal = calibrate(s.sweep(np.round(np.geomspace(2, 400, 10), 3), "lamp A",
                            irradiance_w_m2=0.25 * TRAIN, n_frames=1, seed=1))
    train = Frame.list_from_sweep(s.sweep([12.9, 25.8], "lamp A", irradiance_w_m2=TRAIN,
                                          n_frames=2, seed=2))
    return s, cal, train


def test_fused_front_end_on_a_small_frame_and_in_a_longer_pipeline(small_sim):
    s, cal, train = small_sim
    pipe = Pipeline(_pipe(cal, train).steps + [("cube", create("reconstruct"))]).fit(train)
    frame = Frame.from_raw(s.capture(30.0, "lamp A", irradiance_w_m2=TRAIN, seed=7).frames[0],
                           exposure_ms=30.0, bit_depth=10, mosaic=s.mosaic)
    fused = pipe.transform(frame)
    assert [h["step"] for h in fused.history] == ["dark", "mask", "ffc", "cube"]
    _assert_same_frame(fused, _stage_by_stage(pipe, frame))


def test_dark_and_mask_fuse_before_the_model_based_ffc(small_sim):
    """hsiffc correct's default pipeline: dark and alpha mask fused, then model_ffc (a small
    frame: the model_ffc kernel's parallel build costs ~45 s to compile, and the benchmark
    checks it against the serial one)."""
    s, cal, train = small_sim
    pipe = Pipeline([("dark", create("dark", calibration=cal)),
                     ("mask", create("alpha_mask", calibration=cal)),
                     ("ffc", create("model_ffc", calibration=cal))]).fit(train)
    frame = Frame.from_raw(s.capture(25.0, "lamp A", irradiance_w_m2=TRAIN, seed=6).frames[0],
                           exposure_ms=25.0, bit_depth=10, mosaic=s.mosaic)
    assert fusion.fusable(pipe.steps, frame) == 2
    fused = pipe.transform(frame)
    assert [h["step"] for h in fused.history] == ["dark", "mask", "ffc"]
    assert np.count_nonzero(fused.dq) > 0
    _assert_same_frame(fused, _stage_by_stage(pipe, frame))


def test_the_fused_pass_takes_the_band_mean_band_reduce_gives():
    """The pass's per-band mean of the frame over the pixels its DQ leaves good is
    ``band_reduce``'s, bit for bit: 70 rows (a partial block of sums and of rows per call),
    with NaN, inf, saturated and flagged pixels, a mosaic's map and a single band's."""
    s = MosaicSensor((70, 48), seed=8)
    cal = calibrate(s.sweep(np.round(np.geomspace(2, 400, 8), 3), "lamp A",
                            irradiance_w_m2=0.25 * TRAIN, n_frames=1, seed=1))
    raw = s.capture(30.0, "lamp A", irradiance_w_m2=0.2 * TRAIN,
                    seed=9).frames[0].astype(np.float32)
    raw[3, :5] = [np.nan, np.inf, -np.inf, 1023, 0]
    dark = np.full(raw.shape, 20, np.float32)
    dq = np.zeros(raw.shape, np.uint32)
    dq[60:, 10] = 1
    args = (raw, dark, 30.0, cal)
    kw = {"threshold_percent": 5.0, "dq": dq}
    plain = subtract_dark_and_flag(*args, **kw)
    for bm in (s.mosaic.band_map(raw.shape), single_band_map(raw.shape)):
        assert row_period(bm) > 0
        n = int(bm.max()) + 1
        *out, mean = subtract_dark_and_flag(*args, **kw, band_map=bm, n_bands=n + 1)
        for x, y in zip(out, plain[:3], strict=True):
            assert np.array_equal(x, y, equal_nan=True)
        good = plain[2] == 0
        assert 0 < np.count_nonzero(~good) < good.size
        assert np.array_equal(mean, band_reduce(raw, bm, good, n_bands=n + 1), equal_nan=True)
        assert np.isfinite(mean[:n]).all() and np.isnan(mean[n])
    # a map whose row period is not known gives no mean (the FFC then takes it itself)
    assert plain.band_mean is None  # without a band map
    assert subtract_dark_and_flag(*args, **kw, band_map=np.array(bm)).band_mean is None
    with pytest.raises(ValueError, match=r"band_map has shape \(2, 2\) but the frame has"):
        subtract_dark_and_flag(*args, **kw, band_map=np.zeros((2, 2), int))


def test_what_is_not_fused_runs_stage_by_stage(sim):
    s, cal, train = sim
    frame = Frame.from_raw(s.capture(20.0, "lamp A", irradiance_w_m2=TRAIN, seed=4).frames[0],
                           exposure_ms=20.0, bit_depth=10, mosaic=s.mosaic)
    pipe = _pipe(cal, train)
    model_alpha = Pipeline([pipe.steps[0], ("mask", create("alpha_mask", calibration=cal,
                                                           method="model")), pipe.steps[2]])
    assert fusion.fusable(model_alpha.steps, frame) == 0
    assert fusion.fusable(pipe.steps[:1], frame) == 0
    assert fusion.fusable(pipe.steps[1:], frame) == 0
    assert fusion.fusable(pipe.steps[:2], frame) == 2
    # a frame whose dark was removed already is not fused; one of another shape fuses the
    # dark and the mask only, and gets the dark stage's own error
    assert fusion.fusable(pipe.steps, pipe.steps[0][1].transform(frame)) == 0
    small = Frame.from_raw(np.zeros((8, 8)), exposure_ms=20.0, bit_depth=10, mosaic=s.mosaic)
    assert fusion.fusable(pipe.steps, small) == 2
    for fuse in (True, False):  # the fit's frame contract says it first
        with pytest.raises(ValueError, match=r"fitted on 272 x 512 px frames"):
            pipe.transform(small, fuse=fuse)
    pipe.fitted_on = None  # a pipeline saved without the record: the dark stage's own error
    for fuse in (True, False):
        with pytest.raises(ValueError, match=r"dark has shape \(272, 512\) but frames have"):
            pipe.transform(small, fuse=fuse)


def test_fused_front_end_on_the_real_emva_sweep(emva_dir):
    """Real CMOS frames (8 bit, no mosaic): calibration and flats from the measured sweep, the
    test frame a measured one at another level; fused equals stage by stage."""
    sweep = read_emva1288(emva_dir / "EMVA1288_Data.txt", max_frames_per_step=2)
    frames = Frame.list_from_sweep(sweep)
    cal = calibrate(sweep)
    lights = sorted({f.exposure_ms for f in frames if f.kind == "light"})
    train = [f for f in frames if f.exposure_ms in lights[len(lights) // 2:][:2]
             or f.kind == "dark"]
    pipe = Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=cal)),
                     ("ffc", create("two_point_ffc", calibration=cal))]).fit(train)
    test = next(f for f in frames if f.kind == "light" and f.exposure_ms == lights[-3])
    assert fusion.fusable(pipe.steps, test) == 3
    fused = pipe.transform(test)
    assert np.count_nonzero(fused.dq) > 0
    _assert_same_frame(fused, _stage_by_stage(pipe, test))


def test_fixed_flag_planes_are_read_once_merged_and_still_reach_the_dq(sim):
    """A fitted two-point FFC's flat flags are read-only, so the fused pass merges them with
    the calibration's flags once (the plan's FusedFrontEnd: PreparedCalibration.with_flags)
    and reads one plane for both; the frame stays the one the stages give one by one, flat
    flags included."""
    s, cal, train = sim
    pipe = _pipe(cal, train)
    ffc = pipe.named_steps["ffc"]
    assert not ffc.dq_.flags.writeable  # fixed once fitted
    with pytest.raises(ValueError, match="read-only"):
        ffc.dq_[0, 0] = 1
    flat = np.zeros(ffc.dq_.shape, np.uint32)  # a flat with unusable pixels
    flat[3, :50] = DQ.NO_FLAT
    flat.flags.writeable = False
    ffc.dq_ = flat
    raw = s.capture(30.0, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"], seed=6).frames[0]
    frame = Frame.from_raw(raw, exposure_ms=30.0, bit_depth=10, mosaic=s.mosaic)
    fused = pipe.transform(frame)
    _assert_same_frame(fused, _stage_by_stage(pipe, frame))
    assert np.all(fused.dq[3, :50] & DQ.NO_FLAT) and not np.any(fused.dq[4] & DQ.NO_FLAT)
    front = pipe.plan.units[0]  # the plan was made again: the stage changed since the fit
    assert isinstance(front, fusion.FusedFrontEnd)
    assert repr(front) == "FusedFrontEnd(dark + mask + ffc)" and repr(front) in repr(pipe)
    prepared = front.calibration_with_flat
    assert prepared.merged_with is flat and not prepared.flags.flags.writeable
    np.testing.assert_array_equal(prepared.flags,
                                  np.asarray(cal.arrays["flags"], np.uint32) | flat)
    plan = pipe.plan
    pipe.transform(frame)
    assert pipe.plan is plan  # made once, not per frame
    # the calibration stays plain data (nothing kept on it): it pickles as it is
    again = pickle.loads(pickle.dumps(cal))
    assert not [k for k in vars(again) if k.startswith("_")]
    np.testing.assert_array_equal(again.arrays["flags"], cal.arrays["flags"])
    # a writable plane could change under a merged one: refused, and read as its own plane
    writable = flat.copy()
    with pytest.raises(ValueError, match="read-only uint32 plane"):
        front.calibration.with_flags(writable)
    ffc.dq_ = writable
    _assert_same_frame(pipe.transform(frame), fused)
    assert pipe.plan.units[0].calibration_with_flat is None


def test_a_loaded_two_point_ffc_has_fixed_flags(sim, tmp_path):
    s, cal, train = sim
    pipe = _pipe(cal, train)
    loaded = Pipeline.load(pipe.save(tmp_path / "p.npz"))
    dq = loaded.named_steps["ffc"].dq_
    assert not dq.flags.writeable and dq.dtype == np.uint32
    np.testing.assert_array_equal(dq, pipe.named_steps["ffc"].dq_)
