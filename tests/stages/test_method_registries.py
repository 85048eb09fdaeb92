"""One registry and one contract per method family (issue 37): every registered method of
every family returns the family's result type on a tiny input, the family's function
dispatches through the registry, and an unknown name is one line naming it, the closest and
the valid names. A method added to a registry without a case here fails
``test_every_*_method_has_a_case``."""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass, replace

import numpy as np
import pytest

from hsiffc.calibrate import CALIBRATION_METHODS, Calibration, calibrate
from hsiffc.data.dark import subtract_dark
from hsiffc.data.mosaic import Mosaic
from hsiffc.data.sweep import Sweep
from hsiffc.errors import ParameterError
from hsiffc.flatfield import FFC_METHODS, FROM_CALIBRATION, Corrected, FFCMethod, correct_flat
from hsiffc.flatfield.model_based import model_ffc_apply
from hsiffc.flatfield.model_based import model_flat_fit
from hsiffc.flatfield.polynomial import polynomial_apply, polynomial_fit
from hsiffc.flatfield.two_point import two_point_correct, two_point_fit
from hsiffc.leakage.validity import (ALPHA_METHODS, AlphaFlags, DarkFlagged, alpha_map,
                                     subtract_dark_and_flag, validity_flags)
from hsiffc.reconstruct import DEMOSAIC_METHODS, Demosaiced, demosaic
from hsiffc.reflectance import (REFLECTANCE_METHODS, Rates, reflectance_factor,
                                resolve_method)
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

SHAPE = (8, 8)
TRAIN = PAPER_LIGHT_W_M2["training"]


def _one_line_error(call, valid, closest):
    """``call`` raises a ParameterError of one line that names every valid name and
    suggests ``closest``."""
    with pytest.raises(ParameterError) as info:
        call()
    text = str(info.value)
    assert "\n" not in text
    assert f"did you mean {closest!r}?" in text
    for name in valid:
        assert name in text


# -- demosaicking ---------------------------------------------------------------------------

@pytest.mark.parametrize("method", sorted(DEMOSAIC_METHODS))
def test_every_demosaic_method_returns_demosaiced(method):
    rng = np.random.default_rng(0)
    raw = rng.uniform(100, 200, SHAPE).astype(np.float32)
    alpha = rng.uniform(0, 20, SHAPE).astype(np.float32)
    plain = demosaic(raw, Mosaic.square(2), method=method)
    assert type(plain) is Demosaiced and plain.alpha is None
    assert plain.cube.shape == plain.dq.shape == SHAPE + (4,)
    with_alpha = demosaic(raw, Mosaic.square(2), method=method, alpha=alpha)
    assert type(with_alpha) is Demosaiced and with_alpha.alpha.shape == SHAPE + (4,)
    assert np.array_equal(with_alpha.cube, plain.cube)  # alpha= changes only the alpha


def test_demosaic_dispatches_through_the_registry(monkeypatch):
    """A method registered with a refinement step gets it: demosaic reads the registry."""
    seen = []
    monkeypatch.setitem(DEMOSAIC_METHODS, "test_refined", type(DEMOSAIC_METHODS["bilinear"])(
        "bilinear, then a recorded refinement", refine=lambda p, cube: seen.append(cube.shape)))
    out = demosaic(np.ones(SHAPE, np.float32), Mosaic.square(2), method="test_refined")
    assert type(out) is Demosaiced and seen == [SHAPE + (4,)]


def test_unknown_demosaic_method_is_one_line():
    _one_line_error(lambda: demosaic(np.ones(SHAPE), Mosaic.square(2), method="bilinar"),
                    DEMOSAIC_METHODS, "bilinear")


def test_cube_choices_come_from_the_registry():
    from hsiffc.batch.context import CUBE_METHODS
    from hsiffc.cli.reflectance import CUBE_METHODS as REFLECTANCE_CUBES

    assert CUBE_METHODS == (*DEMOSAIC_METHODS, "tile")
    assert REFLECTANCE_CUBES == tuple(DEMOSAIC_METHODS)


# -- flat-field correction ------------------------------------------------------------------

def _ffc_case(method):
    """(raw, dark, flat, keywords) of a tiny frame for ``method``, and the public array
    function's (out, dq) on the same input (the registry entry must give the same)."""
    rng = np.random.default_rng(1)
    dark = rng.uniform(20, 30, SHAPE)
    pixel_gain = rng.uniform(0.9, 1.1, SHAPE)
    raw = (dark + 400 * pixel_gain).astype(np.float32)
    dq = np.zeros(SHAPE, np.uint32)
    dq[0, 0] = 1
    if method == "two_point":
        flat = dark + 1000 * pixel_gain
        ff = two_point_fit(subtract_dark(flat, dark))  # as two_point_correct fits it
        ref = two_point_correct(raw, dark, flat, dq=dq)
        return raw, dark, ff, {}, ref
    if method == "polynomial":
        levels = np.stack([m * pixel_gain for m in (200.0, 500.0, 900.0)])
        pf = polynomial_fit(levels, order=2)
        out, pdq = polynomial_apply(raw - dark.astype(np.float32), pf)
        return raw, dark, pf, {}, (out, pdq | dq)
    if method == "model":
        a, b = np.full(SHAPE, 1e-4), np.full(SHAPE, 0.01)
        mf = model_flat_fit(pixel_gain, np.full(SHAPE, 0.01), a, b, np.zeros(SHAPE, int))
        out, mdq, alpha = model_ffc_apply(raw, 20.0, a, b, dark, mf.gain,
                                          gain_sweep=mf.gain_sweep)
        return raw, dark, mf, {"exposure_ms": 20.0, "a": a, "b": b}, (out, mdq | mf.dq | dq,
                                                                        alpha)
    return None


def test_every_ffc_method_has_a_case():
    assert all(_ffc_case(m) is not None for m in FFC_METHODS)


@pytest.mark.parametrize("method", list(FFC_METHODS))
def test_every_ffc_method_returns_corrected(method):
    raw, dark, flat, kw, ref = _ffc_case(method)
    dq = np.zeros(SHAPE, np.uint32)
    dq[0, 0] = 1
    res = correct_flat(method, raw, dark, flat, dq=dq, **kw)
    assert type(res) is Corrected
    assert res.out.dtype == np.float32 and res.dq.dtype == np.uint32
    assert res.out.shape == res.dq.shape == SHAPE
    assert res.dq[0, 0] & 1  # the frame's DQ is kept
    assert (res.alpha is None) == (method != "model")
    # the entry is the public array function behind the common signature: same numbers
    np.testing.assert_array_equal(res.out, ref[0])
    np.testing.assert_array_equal(res.dq, ref[1])
    if res.alpha is not None:
        np.testing.assert_array_equal(res.alpha, ref[2])
    # the flat's own arrays are not changed by applying it
    again = correct_flat(method, raw, dark, flat, dq=dq, **kw)
    np.testing.assert_array_equal(again.dq, res.dq)


def test_ffc_entries_check_the_flat_and_the_method():
    raw, dark, ff, _, _ = _ffc_case("two_point")
    _one_line_error(lambda: correct_flat("two-point", raw, dark, ff), FFC_METHODS, "two_point")
    with pytest.raises(ParameterError, match="flat= must be a PolynomialFlat"):
        correct_flat("polynomial", raw, dark, ff)
    _, _, mf, _, _ = _ffc_case("model")
    with pytest.raises(ParameterError, match="needs exposure_ms=, a=, b="):
        correct_flat("model", raw, dark, mf)


@dataclass(frozen=True)
class ScaleFlat:
    """What the test's method learns: one factor per pixel."""

    gain: np.ndarray


def _scaled(raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None, calibration=None):
    out = (subtract_dark(raw, dark) * flat.gain).astype(np.float32)
    return Corrected(out, np.zeros(out.shape, np.uint32) | (0 if dq is None else dq), None)


#: a flat-field method added through the registry alone: half the signal above the dark
SCALED = FFCMethod("test: the signal above the dark times a learnt factor", _scaled, ScaleFlat,
                   learn=lambda cal: ScaleFlat(np.full(cal.frame_shape, 0.5, np.float32)),
                   state_schema={"gain_": ("f", ("H", "W"))})


def test_a_method_added_to_the_registry_runs_from_the_command_line(monkeypatch, tmp_path,
                                                                   calibrations, sensor):
    """One registry line makes a new flat-field method a choice of ``hsiffc correct --ffc``, a
    step of the default pipeline and of a pipeline file (its state checked by its schema)."""
    from hsiffc.batch.context import FFC_CHOICES
    from hsiffc.cli import build_parser, main
    from hsiffc.io import write_sweep
    from hsiffc.io.corrected import read_corrected
    from hsiffc.stages import Pipeline
    from hsiffc.stages.defaults import default_pipeline

    assert "scaled" not in FFC_CHOICES
    monkeypatch.setitem(FFC_METHODS, "scaled", SCALED)
    assert "scaled" in FROM_CALIBRATION and "scaled" in FFC_CHOICES
    cal = tmp_path / "cal.npz"
    calibrations["joint"].save(cal)
    scene = sensor.sweep([10.0, 20.0], "lamp A", irradiance_w_m2=TRAIN / 4, n_frames=2,
                         darks=False, seed=8)
    write_sweep(tmp_path / "scene.tif", replace(scene, meta={}))
    out = {}
    for ffc in ("none", "scaled"):
        assert main(["correct", str(tmp_path / "scene.tif"), "--calibration", str(cal), "-o",
                     str(tmp_path / ffc), "--ffc", ffc, "-q"]) == 0
        out[ffc] = read_corrected(tmp_path / ffc / "scene.corrected.tif")
    steps = [s["stage"] for s in out["scaled"].provenance["pipeline"]["steps"]]
    assert steps == ["dark", "alpha_mask", "flat_field"]
    np.testing.assert_allclose(out["scaled"].data, 0.5 * out["none"].data, rtol=1e-5, atol=1e-3)
    np.testing.assert_array_equal(out["scaled"].dq, out["none"].dq)
    # a pipeline file keeps the step; its state is checked against the method's schema
    pipe = default_pipeline(calibrations["joint"], ffc="scaled")
    pipe.save(tmp_path / "pipe.npz")
    again = Pipeline.load(tmp_path / "pipe.npz")
    frame = sensor.capture(20.0, "lamp A", irradiance_w_m2=TRAIN / 4, seed=9).to_frames()[0]
    np.testing.assert_array_equal(again.transform(frame).data, pipe.transform(frame).data)
    # the command line's help lists it, read from the registry
    sub = next(a for a in build_parser()._actions if a.choices and "correct" in a.choices)
    ffc_opt = next(a for a in sub.choices["correct"]._actions if a.dest == "ffc")
    assert tuple(ffc_opt.choices) == (*FROM_CALIBRATION, "none")


def test_a_method_learnt_from_frames_only_is_no_default_choice():
    from hsiffc.stages.ffc import from_calibration

    assert tuple(FROM_CALIBRATION) == ("model",)  # two_point and polynomial need flats
    with pytest.raises(ParameterError, match="learns from training frames"):
        from_calibration("two_point", None)


# -- calibration and alpha (one tiny simulated sweep per calibration method) -----------------

@pytest.fixture(scope="module")
def sensor():
    return MosaicSensor(SHAPE, seed=0)


def _sweep(sensor, method):
    if method == "joint":
        return sensor.sweep(np.geomspace(2.0, 400.0, 12), "lamp A", n_frames=2, seed=1,
                            irradiance_w_m2=TRAIN / 4)
    if method == "paper":  # sweeps into dynamic saturation under several light levels
        parts = []
        # as tests/calibrate/test_calibrate.py, smaller
        for i, level in enumerate([0.1, 0.25, 0.6]):
            k = 30 * level
            t_lin = (800 + np.log(k / 2) / 0.0125 - 32) / k  # linear time to saturation
            ts = np.concatenate([np.geomspace(1, t_lin, 6), t_lin * np.array([1.6, 2.2, 2.8])])
            parts.append(sensor.sweep(np.round(ts, 3), "lamp A", irradiance_w_m2=TRAIN * level,
                                      n_frames=2, darks=(i == 0), seed=20 + i,
                                      label=f"lamp A x{level}"))
        cat = {f: np.concatenate([getattr(p, f) for p in parts])
               for f in ("data", "exposure_ms", "kind", "illumination")}
        return Sweep(cat["data"], cat["exposure_ms"], cat["kind"], 10,
                     illumination=cat["illumination"], mosaic=sensor.mosaic)
    return None


@pytest.fixture(scope="module")
def calibrations(sensor):
    return {m: calibrate(_sweep(sensor, m), method=m) for m in CALIBRATION_METHODS}


def test_every_calibration_method_returns_a_calibration(calibrations):
    assert set(calibrations) == set(CALIBRATION_METHODS)
    for method, cal in calibrations.items():
        assert type(cal) is Calibration and cal.method == method
        assert cal.a.shape == SHAPE
        how = CALIBRATION_METHODS[method]  # what the command line passes it, it takes
        assert how.reports_progress == ("progress" in inspect.signature(how.fit).parameters)


def test_unknown_calibration_method_is_one_line(sensor):
    from hsiffc.calibrate import METHODS

    assert METHODS == tuple(CALIBRATION_METHODS)  # the old name, kept
    _one_line_error(lambda: calibrate(_sweep(sensor, "joint"), method="jiont"),
                    CALIBRATION_METHODS, "joint")


@pytest.mark.parametrize("method", list(ALPHA_METHODS))
def test_every_alpha_method_returns_its_types(calibrations, sensor, method):
    cal = calibrations["joint"]
    frame = sensor.capture(30.0, "lamp A", irradiance_w_m2=TRAIN / 4, seed=3).frames[0]
    alpha = alpha_map(frame, 30.0, cal, method=method)
    assert alpha.dtype == np.float32 and alpha.shape == SHAPE
    flags = validity_flags(frame, 30.0, cal, threshold_percent=12.0, method=method)
    assert type(flags) is AlphaFlags and flags.dq.dtype == np.uint32
    np.testing.assert_array_equal(flags.alpha, alpha)


def test_unknown_alpha_method_is_one_line(calibrations):
    _one_line_error(lambda: alpha_map(np.ones(SHAPE), 10.0, calibrations["joint"],
                                      method="papr"), ALPHA_METHODS, "paper")


def test_subtract_dark_and_flag_has_one_return_type(calibrations, sensor):
    cal = calibrations["joint"]
    frame = sensor.capture(30.0, "lamp A", irradiance_w_m2=TRAIN / 4, seed=3).frames[0]
    dark = cal.dark_at(30.0).astype(np.float32)
    args = (frame, dark, 30.0, cal)
    plain = subtract_dark_and_flag(*args, threshold_percent=12.0)
    bm = sensor.mosaic.band_map(SHAPE)
    with_mean = subtract_dark_and_flag(*args, threshold_percent=12.0, band_map=bm)
    unknown_period = subtract_dark_and_flag(*args, threshold_percent=12.0,
                                            band_map=np.array(bm))
    for res in (plain, with_mean, unknown_period):
        assert type(res) is DarkFlagged
        np.testing.assert_array_equal(res.signal, plain.signal)
        np.testing.assert_array_equal(res.dq, plain.dq)
    assert plain.band_mean is None and unknown_period.band_mean is None
    assert with_mean.band_mean.shape == (sensor.mosaic.n_bands,)
    # the alpha of the one pass is the alpha of the methods that say so (a fused front end
    # stands in for their alpha mask)
    one_pass = [name for name, how in ALPHA_METHODS.items() if how.one_pass]
    assert one_pass == ["paper"]
    for name in one_pass:
        alone = validity_flags(frame, 30.0, cal, threshold_percent=12.0, method=name, dark=dark)
        np.testing.assert_array_equal(plain.alpha, alone.alpha)
        np.testing.assert_array_equal(plain.dq, alone.dq)


# -- reflectance ------------------------------------------------------------------------------

def _reflectance_case(method):
    """(whether the case gives a calibration, what the method runs as, the public array
    function whose rate it must give on a dark-subtracted frame) for ``method``."""
    from hsiffc.leakage.linearise import linearise

    def ratio(frame, cal):
        return frame.signal / np.float32(frame.exposure_ms)

    def model(frame, cal):
        return linearise(frame.raw, frame.exposure_ms, cal.a, cal.b, frame.dark_removed, 0.0,
                         full_scale_dn=2 ** frame.bit_depth - 1,
                         alpha_limit_percent=90.0).light_rate

    return {"auto": (True, "model", model), "model": (True, "model", model),
            "ratio": (False, "ratio", ratio)}.get(method)


def test_every_reflectance_method_has_a_case():
    assert all(_reflectance_case(m) is not None for m in REFLECTANCE_METHODS)


@pytest.mark.parametrize("method", list(REFLECTANCE_METHODS))
def test_every_reflectance_method_divides_its_registered_rate(calibrations, sensor, method):
    """The reflectance stage runs the method the registry resolves it to, and its output is
    that method's rate (the same numbers as the public array function behind it) over the
    white reference's, times the panel."""
    from hsiffc.stages import Pipeline, create

    with_cal, runs_as, reference = _reflectance_case(method)
    cal = calibrations["joint"] if with_cal else None
    assert resolve_method(method, with_cal) == runs_as
    whites = sensor.capture(30.0, "lamp A", irradiance_w_m2=TRAIN / 4, n_frames=3,
                            seed=5).to_frames()
    darks = sensor.capture(30.0, None, n_frames=3, seed=6).to_frames()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a tiny reference: its checks warn, not tested here
        pipe = Pipeline([("dark", create("dark")),
                         ("refl", create("reflectance", panel=0.9, calibration=cal,
                                         method=method))]).fit(whites + darks)
        out = pipe.transform(whites[0])
    stage = pipe.named_steps["refl"]
    how = REFLECTANCE_METHODS[runs_as]
    assert stage.method_ == runs_as and stage.requires == how.requires
    assert how.leakage_aware == with_cal
    scene = pipe.named_steps["dark"].transform(whites[0])
    rates = how.rate(scene, cal, prepared=None, alpha_limit_percent=90.0)
    assert type(rates) is Rates and (rates.alpha is None) == (not how.leakage_aware)
    np.testing.assert_array_equal(rates.rate, reference(scene, cal))
    expected = reflectance_factor(rates.rate, stage.white_rate_[0], 0.9)
    good = out.dq == 0
    assert good.any()
    np.testing.assert_array_equal(out.data[good], expected[good])


def test_unknown_reflectance_method_is_one_line():
    _one_line_error(lambda: resolve_method("rato", calibrated=False), REFLECTANCE_METHODS,
                    "ratio")


def test_reflectance_choices_come_from_the_registry():
    from hsiffc.cli import build_parser
    from hsiffc.stages.reflectance import Reflectance

    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and "reflectance" in a.choices)
    acts = next(a for a in sub.choices["reflectance"]._actions if a.choices and "fit" in a.choices)
    method = next(a for a in acts.choices["fit"]._actions if a.dest == "method")
    assert tuple(method.choices) == tuple(REFLECTANCE_METHODS)
    assert Reflectance.param_spec["method"].choices == tuple(REFLECTANCE_METHODS)
