"""Edge cases of the array functions found by fuzzing: planes of the wrong shape, exposures and
bit depths no camera produces, products beyond the float32 range. Each must give a one-line
error naming the parameter, or a flagged value, never a wrong number or a read outside an
array."""

import numpy as np
import pytest

from hsiffc.spectral.bandstats import band_reduce
from hsiffc.data.dq import DQ
from hsiffc.flatfield.two_point import two_point_apply, two_point_fit, uniformity_per_band
from hsiffc.data.frame import Frame
from hsiffc.kernels.bands import band_sums
from hsiffc.kernels.launch import PARALLEL_MIN
from hsiffc.leakage.model import invert_response
from hsiffc.flatfield.model_based import model_ffc_apply
from hsiffc.data.mosaic import Mosaic
from hsiffc.flatfield.polynomial import polynomial_fit
from hsiffc.stages import create
from hsiffc.stages.common import find_exposure

F32_MAX = float(np.finfo(np.float32).max)
BAD = int(DQ.NONFINITE | DQ.DO_NOT_USE)


def test_a_dq_plane_of_another_shape_is_refused_not_read_past_its_end():
    img = np.random.default_rng(0).normal(100, 5, (64, 64))
    bm = np.zeros((64, 64), np.intp)
    with pytest.raises(ValueError, match=r"dq has shape \(2, 2\) but the image has \(64, 64\)"):
        uniformity_per_band(img, bm, dq=np.zeros((2, 2), np.uint32))
    with pytest.raises(ValueError, match=r"good has shape \(2, 2\)"):
        band_reduce(img, bm, np.ones((2, 2), bool))
    with pytest.raises(ValueError, match="must be 2-D of one shape"):
        band_sums(img, bm, np.ones((2, 64), bool), 1)


def test_band_statistics_refuse_empty_frames_and_negative_bands():
    with pytest.raises(ValueError, match="empty"):
        band_reduce(np.zeros((0, 0)))
    with pytest.raises(ValueError, match="flat_signal is empty"):
        two_point_fit(np.zeros((0, 4)))
    bm = np.array([[0, -1], [0, 1]])
    for call in (lambda: band_reduce(np.ones((2, 2)), bm),
                 lambda: uniformity_per_band(np.ones((2, 2)), bm)):
        with pytest.raises(ValueError, match="negative band index"):
            call()


@pytest.mark.parametrize("exposure", [float("inf"), float("nan"), -1.0, "16 ms"])
def test_a_frame_refuses_an_exposure_no_camera_has(exposure):
    with pytest.raises(ValueError, match="exposure_ms must be a finite time >= 0"):
        Frame.from_raw(np.ones((2, 2)), exposure_ms=exposure, bit_depth=10)
    good = Frame.from_raw(np.ones((2, 2)), exposure_ms=0.0, bit_depth=10)  # a bias frame
    with pytest.raises(ValueError, match="exposure_ms"):
        good.replace(meta={"exposure_ms": exposure})


@pytest.mark.parametrize("depth", [0, -3, 33, 10.5])
def test_a_frame_refuses_a_bit_depth_no_adc_has(depth):
    with pytest.raises(ValueError, match="bit_depth must be a whole number 1..32"):
        Frame.from_raw(np.ones((2, 2)), exposure_ms=1.0, bit_depth=depth)


def test_no_exposure_matches_a_nan_or_infinite_time():
    for t in (float("inf"), float("-inf"), float("nan")):
        assert find_exposure([19.35, 40.0], t) is None
    assert find_exposure([19.35, 40.0], 40.0) == 40.0


def _overflowing(shape):
    """A signal whose product with gain 1.5 leaves the float32 range in a few pixels."""
    sig = np.full(shape, 100.0, np.float32)
    sig.reshape(-1)[::997] = F32_MAX
    sig.reshape(-1)[5] = -F32_MAX
    return sig, np.full(shape, 1.5, np.float32)


@pytest.mark.parametrize("path", ["scalar scale", "band map", "mosaic band map"])
def test_two_point_apply_flags_products_beyond_float32(path):
    shape = (256, 300) if path == "mosaic band map" else (8, 12)
    assert path != "mosaic band map" or np.prod(shape) >= PARALLEL_MIN  # the row-phase kernel
    sig, gain = _overflowing(shape)
    over = np.abs(sig.astype(np.float64) * 1.5) > F32_MAX
    kw = {}
    if path == "band map":
        kw = {"scale": np.ones(2), "band_map": np.indices(shape).sum(axis=0) % 2}
    elif path == "mosaic band map":
        kw = {"scale": np.ones(4), "band_map": Mosaic.square(2).band_map(shape)}
    plain = two_point_apply(sig, gain, **kw)
    assert np.array_equal(np.isinf(plain), over)  # without dq: the values as computed
    dq = np.full(shape, DQ.HOT, np.uint32)
    out = two_point_apply(sig, gain, **kw, dq=dq)
    assert np.isfinite(out).all()
    assert (out[over] == 0).all() and np.array_equal(out[~over], plain[~over])
    assert (dq[over] == BAD | DQ.HOT).all() and (dq[~over] == DQ.HOT).all()


@pytest.mark.filterwarnings(  # its flat is 7 % of the range: the fit's check says so
    "ignore::hsiffc.stages.refchecks.FlatTooDarkWarning")
def test_two_point_stage_flags_what_overflows():
    rng = np.random.default_rng(0)
    dark = [Frame.from_raw(np.full((4, 8), 10.0), exposure_ms=5.0, bit_depth=10, kind="dark")
            for _ in range(2)]
    flat = [Frame.from_raw(10 + rng.uniform(50, 100, (4, 8)), exposure_ms=5.0, bit_depth=10)
            for _ in range(2)]
    d = create("dark").fit(dark)
    ffc = create("two_point_ffc", exposure_ms=5.0, normalisation="mean_gain").fit(
        [d.transform(f) for f in flat])
    out = ffc.transform(d.transform(
        Frame.from_raw(np.full((4, 8), -F32_MAX, np.float32), exposure_ms=5.0, bit_depth=10)))
    over = (out.dq & BAD) == BAD
    assert np.isfinite(out.data).all() and over.any()
    assert (out.data[over] == 0).all()


def test_model_ffc_flags_what_overflows_float32_and_refuses_a_negative_exposure():
    out, dq, _ = model_ffc_apply(np.array([[-F32_MAX, 200.0]], np.float32), 10.0, 1e-4, 0.01,
                                 50.0, 1.5)
    assert np.isfinite(out).all() and out[0, 0] == 0 and (dq[0, 0] & BAD) == BAD
    assert out[0, 1] != 0 and (dq[0, 1] & BAD) == 0
    out0, dq0, _ = model_ffc_apply(np.array([[F32_MAX, 60.0]], np.float32), 0.0, 1e-4, 0.01,
                                   50.0, 1.5)  # zero exposure: the offset only
    assert out0[0, 0] == 0 and (dq0[0, 0] & BAD) == BAD and out0[0, 1] == pytest.approx(15.0)
    for bad in (-5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="exposure_ms must be a finite time >= 0"):
            model_ffc_apply(np.array([[200.0]]), bad, 1e-4, 0.01, 50.0, 1.5)


def test_operands_that_do_not_broadcast_are_named():
    with pytest.raises(ValueError, match=r"signal \(4, 4\), gain \(4, 5\): these shapes do not"):
        two_point_apply(np.ones((4, 4)), np.ones((4, 5)))
    with pytest.raises(ValueError, match=r"y \(3,\), a \(4,\)"):
        invert_response(np.ones(3), 10.0, np.ones(4), 0.01, 50.0)


@pytest.mark.parametrize("order", [0, -1, 1.5, True])
def test_polynomial_fit_refuses_an_order_below_one(order):
    with pytest.raises(ValueError, match="order must be a whole number >= 1"):
        polynomial_fit(np.ones((3, 2, 2)), order=order)


def test_linearise_names_the_exposure_when_there_is_no_light_to_recover():
    from hsiffc.leakage.linearise import linearise
    for t in (0.0, float("nan")):
        with pytest.raises(ValueError, match="exposure_ms must be a finite time > 0 ms to "
                                             "linearise"):
            linearise(np.full((2, 2), 120.0), t, 1e-4, 0.01, 50.0, 0.0)
    lin = linearise(np.full((2, 2), 120.0), 10.0, 1e-4, 0.01, 50.0, 0.0)
    assert lin.light_rate.shape == (2, 2) and np.isfinite(lin.light_rate).all()


def test_planes_that_are_not_dq_bits_or_real_counts_are_refused():
    from hsiffc.reconstruct import demosaic
    mosaic = Mosaic.square(2)
    raw = np.ones((8, 8), np.float32)
    for dq, what in ((np.full((8, 8), 0.5), "integer DQ bits"), (np.full((8, 8), -1), "negative")):
        with pytest.raises(ValueError, match=what):
            demosaic(raw, mosaic, dq=dq)
        with pytest.raises(ValueError, match=what):
            Frame(raw, dq)
    with pytest.raises(ValueError, match="real numbers"):
        demosaic(raw.astype(np.complex64), mosaic)
    with pytest.raises(ValueError, match="real counts"):
        Frame.from_raw(raw.astype(object), exposure_ms=1.0, bit_depth=10)
    cube, _, _ = demosaic(raw, mosaic, dq=np.zeros((8, 8), np.int16))  # integers >= 0 are bits
    assert np.isfinite(cube).all()


def test_polynomial_apply_flags_what_is_not_finite_in_float32():
    from hsiffc.flatfield.polynomial import polynomial_apply
    rng = np.random.default_rng(0)
    flat = polynomial_fit(np.stack([rng.uniform(50, 60, (4, 6)) * m for m in (1, 2, 3)]),
                          order=2)
    x = np.full((4, 6), 100.0, np.float32)
    x[0, :3] = F32_MAX, -F32_MAX, np.nan
    out, dq = polynomial_apply(x, flat)
    assert np.isfinite(out).all() and (out[0, :3] == 0).all()
    assert ((dq[0, :3] & BAD) == BAD).all() and not (dq[1:] & BAD).any()
