"""Reflectance from a white panel on simulated truth: known-reflectance targets recovered within
their noise by the leakage-aware method where the plain ratio is biased; every field-campaign
check triggered by data made to cause it and silent on good data; mosaic frames and cubes
(before and after reconstruction and the IMEC correction matrix); the panel's spectrum; the
figure for a uniform target."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hsiffc.calibrate import calibrate
from hsiffc.data.dq import DQ
from hsiffc.errors import DataFormatError, ParameterError
from hsiffc.data.frame import Frame
from hsiffc.data.mosaic import Mosaic
from hsiffc.reflectance import (ExposureMismatchWarning, GainMismatchWarning,
                                ReferenceLeakageWarning, ReferenceSaturatedWarning,
                                SceneBrighterThanReferenceWarning, TooFewReferenceFramesWarning,
                                WhiteReferenceTooDarkWarning, panel_per_band,
                                read_panel_spectrum, target_report)
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create

LIGHT = PAPER_LIGHT_W_M2["training"]
SWEEP_MS = np.tile(np.geomspace(0.5, 150, 20), 3)
SWEEP_LEVELS = np.repeat([0.5, 1.0, 1.6], 20)


class Sim:
    """A leaky 10-bit 8-band sensor, its calibration, and captures of panels and targets."""

    def __init__(self):
        self.sensor = MosaicSensor.default((32, 64), seed=4)
        sweep = self.sensor.sweep_varying_light(SWEEP_MS, SWEEP_LEVELS, "lamp A",
                                                irradiance_w_m2=LIGHT, n_frames=4, seed=1)
        self.cal = calibrate(sweep)
        self.n_l = len(self.sensor.bands.wavelengths_nm)
        self._seed = 100

    def frames(self, t, rho, n, *, light=1.0):
        self._seed += 1
        return self.sensor.capture(t, "lamp A", irradiance_w_m2=LIGHT * light, n_frames=n,
                                   reflectance=np.full(self.n_l, rho),
                                   seed=self._seed).to_frames()

    def darks(self, t, n=10):
        self._seed += 1
        return self.sensor.capture(t, None, n_frames=n, seed=self._seed).to_frames()

    def pipeline(self, train, *, method, steps=(), **params):
        cal = self.cal if method != "ratio" or params.pop("with_cal", False) else None
        return Pipeline([("dark", create("dark")), *steps,
                         ("refl", create("reflectance", panel=0.99, calibration=cal,
                                         method=method, **params))]).fit(train)


@pytest.fixture(scope="module")
def sim():
    return Sim()


def caught(fn):
    """(result, warning categories) of ``fn()``, every warning recorded."""
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = fn()
    return out, [x.category for x in w], [str(x.message) for x in w]


def band_bias(outs, rho, band_map, n_bands=8):
    """Per band: relative error of the mean reflectance and its standard error (fractions)."""
    r = np.stack([o.data for o in outs]).astype(float)
    good = np.all([o.dq == 0 for o in outs], axis=0)
    pix = r.mean(axis=0)
    bias, se = [], []
    for b in range(n_bands):
        v = pix[good & (band_map == b)]
        bias.append(v.mean() / rho - 1)
        se.append(v.std(ddof=1) / np.sqrt(v.size) / rho)
    return np.array(bias), np.array(se)


# -- the leakage-aware ratio against the plain one ---------------------------------------------

def test_leakage_aware_recovers_known_targets_where_the_plain_ratio_is_biased(sim):
    """The panel at 30 ms leaks (median alpha ~ 25 %): the plain ratio overestimates darker
    targets by a few percent in every band, far beyond its noise; the model's ratio is within
    3.5 standard errors in every band."""
    t = 30.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    model, cats, msgs = caught(lambda: sim.pipeline(train, method="model"))
    assert ReferenceLeakageWarning in cats, msgs
    ratio, cats_r, msgs_r = caught(lambda: sim.pipeline(train, method="ratio", with_cal=True))
    leak = [m for m in msgs_r if "strong leakage" in m][0]
    assert "plain ratio overestimates dark targets" in leak and "method='model'" in leak
    for rho in (0.1, 0.4):
        scene = sim.frames(t, rho, 4)
        b_model, se_model = band_bias([model.transform(f) for f in scene], rho,
                                      sim.sensor.band_map)
        b_ratio, se_ratio = band_bias([ratio.transform(f) for f in scene], rho,
                                      sim.sensor.band_map)
        assert np.all(np.abs(b_model) < 3.5 * se_model + 1e-3), (rho, b_model, se_model)
        assert np.all(b_ratio > 0.01) and np.all(b_ratio > 5 * se_ratio), (rho, b_ratio)
        assert np.median(b_ratio) > 4 * np.median(np.abs(b_model))


def test_both_methods_agree_and_nothing_warns_on_good_data(sim):
    """A bright, linear panel (16 ms), 10 frames, a scene at its exposure: no warning, the
    two methods agree and recover the target."""
    t = 16.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    scene = sim.frames(t, 0.3, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipes = {m: sim.pipeline(train, method=m) for m in ("model", "ratio")}
        outs = {m: [p.transform(f) for f in scene] for m, p in pipes.items()}
    b_model, se = band_bias(outs["model"], 0.3, sim.sensor.band_map)
    b_ratio, _ = band_bias(outs["ratio"], 0.3, sim.sensor.band_map)
    assert np.all(np.abs(b_model) < 3.5 * se + 1e-3)
    assert np.all(np.abs(b_model - b_ratio) < 2e-3)
    out = outs["model"][0]
    assert out.meta["units"] == "reflectance factor"
    info = out.meta["reflectance"]
    assert info["method"] == "model" and info["exposure_scale"] == 1.0
    assert out.history[-1]["stage"] == "reflectance"
    checks = pipes["model"].named_steps["refl"].checks_[0]
    assert checks["warnings"] == [] and checks["n_frames"] == 10


# -- the checks, each made to fire ---------------------------------------------------------------

def test_too_dark_reference_warns_with_its_level_snr_and_noise_gain(sim):
    t = 0.8  # about 15 DN above dark
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    pipe, cats, msgs = caught(lambda: sim.pipeline(train, method="ratio",
                                                   precision_percent=50))
    assert cats == [WhiteReferenceTooDarkWarning], msgs
    msg = msgs[0]
    assert "too dark in 8 of 8 bands" in msg and "DN above dark" in msg
    assert "single-frame SNR" in msg and "x what a reference at half the range gives" in msg
    gain = float(msg.split("Each DN of scene noise becomes ")[1].split(" ")[0])
    level = min(pipe.named_steps["refl"].checks_[0]["level_dn"])
    assert gain == pytest.approx(0.99 / level, rel=1e-2) and gain > 0.03


def test_saturated_reference_warns_and_flags(sim):
    t = 45.0
    train = sim.frames(t, 0.99, 4, light=1.5) + sim.darks(t, 4)
    pipe, cats, msgs = caught(lambda: sim.pipeline(train, method="ratio"))
    assert ReferenceSaturatedWarning in cats, msgs
    assert "% of the pixels at full scale" in [m for m in msgs if "saturated" in m][0]
    dq = pipe.named_steps["refl"].dq_[0]
    assert np.mean(dq & DQ.SATURATED != 0) > 0.2
    out, _, _ = caught(lambda: pipe.transform(sim.frames(t, 0.1, 1)[0]))
    assert np.array_equal(out.dq & DQ.SATURATED != 0, dq & DQ.SATURATED != 0) or \
        np.all((out.dq & DQ.SATURATED) >= (dq & DQ.SATURATED))


def test_a_panel_at_a_full_well_below_full_scale_is_named(sim):
    """A response that stops at a full well below the ADC's full scale is not SATURATED; its
    temporal noise falls to the dark's, which the check sees."""
    t = 24.0
    darks = sim.darks(t)
    whites = [f.replace(data=np.minimum(f.data, np.float32(600))) for f in
              sim.frames(t, 0.99, 10)]  # a full well at 600 DN: every pixel clipped there
    _, cats, msgs = caught(lambda: sim.pipeline(whites + darks, method="ratio"))
    assert cats == [ReferenceSaturatedWarning], msgs
    assert "stopped responding below full scale" in msgs[0] and "no shot noise" in msgs[0]
    # the same panel unclipped: silent
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.pipeline(sim.frames(t, 0.99, 10) + darks, method="ratio")


def test_too_few_frames_for_the_precision(sim):
    t = 16.0
    darks = sim.darks(t)
    _, cats, msgs = caught(lambda: sim.pipeline(sim.frames(t, 0.99, 3) + darks, method="ratio",
                                                precision_percent=0.2))
    assert cats == [TooFewReferenceFramesWarning], msgs
    need = int(msgs[0].split("record about ")[1].split(" ")[0])
    assert need > 3
    _, cats, msgs = caught(lambda: sim.pipeline(sim.frames(t, 0.99, 1) + darks, method="ratio"))
    assert cats == [TooFewReferenceFramesWarning] and "one white-reference frame" in msgs[0]


def test_scene_brighter_than_reference_and_gain_mismatch(sim):
    t = 10.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(sim.frames(t, 0.99, 10) + sim.darks(t), method="model")
    bright = sim.frames(t, 0.99, 2, light=2.5)
    out, cats, msgs = caught(lambda: [pipe.transform(f) for f in bright])
    assert cats == [SceneBrighterThanReferenceWarning], msgs  # once, not once per frame
    assert "probably recorded at another exposure, gain or light" in msgs[0]
    assert out[0].meta["reflectance"]["fraction_above_max"] > 0.9
    # the gain of the frames, when they carry one (hsiffc's readers do not read one today)
    whites = [f.replace(meta={"gain": 1}) for f in sim.frames(t, 0.99, 10)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(whites + sim.darks(t), method="model")
    assert pipe.named_steps["refl"].white_gain_ == [1]
    scene = sim.frames(t, 0.3, 1)[0]
    scene = scene.replace(meta={"gain": 2})
    out, cats, msgs = caught(lambda: pipe.transform(scene))
    assert cats == [GainMismatchWarning] and "gain 2" in msgs[0]
    assert out.meta["reflectance"]["gain_mismatch"] == [1, 2]


def test_scene_at_another_exposure_is_scaled_and_said_so(sim):
    train = sim.frames(8.0, 0.99, 10) + sim.darks(8.0) + sim.darks(24.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(train, method="model")
    scene = sim.frames(24.0, 0.3, 3)
    outs, cats, msgs = caught(lambda: [pipe.transform(f) for f in scene])
    assert cats == [ExposureMismatchWarning], msgs
    assert "scaled by the exposure (x 0.3333)" in msgs[0]
    assert outs[0].meta["reflectance"]["exposure_scale"] == pytest.approx(1 / 3)
    bias, se = band_bias(outs, 0.3, sim.sensor.band_map)
    assert np.all(np.abs(bias) < 3.5 * se + 2e-3), bias


# -- DQ, cubes, order ----------------------------------------------------------------------------

def test_a_dead_reference_pixel_is_flagged_not_a_hole(sim):
    t = 12.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    dead = (5, 7)
    for f in train[:10]:
        f.data[dead] = f.data[dead] * 0 + train[10].data[dead]  # no light at that pixel
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(train, method="ratio")
        out = pipe.transform(sim.frames(t, 0.3, 1)[0])
    assert out.dq[dead] & DQ.NO_FLAT
    assert np.isfinite(out.data).all() and 0.1 < out.data[dead] < 1.0


def test_cube_after_reconstruction_and_the_order_check(sim):
    t = 16.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    scene = sim.frames(t, 0.3, 1)[0]
    cube = create("reconstruct", method="bilinear")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(train, method="ratio", steps=[("cube", cube)])
        out = pipe.transform(scene)
    assert out.data.shape == (32, 64, 8) and out.is_cube
    good = out.dq == 0
    assert abs(np.median(out.data[good]) / 0.3 - 1) < 0.01
    # the model inverts mosaic pixels: after reconstruction the order check says where it goes
    with pytest.raises(ParameterError, match="put 'refl' before 'cube'"):
        Pipeline([("dark", create("dark")), ("cube", create("reconstruct")),
                  ("refl", create("reflectance", panel=0.99, calibration=sim.cal))])
    # linearise before reconstruction, then the ratio of cubes is leakage-aware too
    t = 30.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    lin = create("linearise", calibration=sim.cal)
    pipe, _, _ = caught(lambda: sim.pipeline(
        train, method="ratio", steps=[("lin", lin), ("cube", create("reconstruct",
                                                                       method="nearest"))]))
    mosaic_model, _, _ = caught(lambda: sim.pipeline(train, method="model"))
    scene = sim.frames(t, 0.2, 2)
    cubes = [caught(lambda f=f: pipe.transform(f))[0] for f in scene]
    plain = [caught(lambda f=f: mosaic_model.transform(f))[0] for f in scene]
    med_cube = np.median([np.median(c.data[c.dq == 0]) for c in cubes])
    med_mosaic = np.median([np.median(c.data[c.dq == 0]) for c in plain])
    assert abs(med_cube / med_mosaic - 1) < 0.01 and abs(med_mosaic / 0.2 - 1) < 0.02


def test_cube_after_the_imec_correction_matrix(imec_xml):
    """On virtual bands (a 5x5 sensor, the real IMEC matrix), a flat grey target's reflectance
    is its value in every virtual band."""
    from hsiffc.spectral import imec_5x5_nir

    bands = imec_5x5_nir()
    sensor = MosaicSensor((40, 40), bands=bands,
                          mosaic=Mosaic.square(5, wavelengths_nm=bands.centres_nm), seed=2)
    n_l = len(bands.wavelengths_nm)
    light = PAPER_LIGHT_W_M2["training"]

    def frames(rho, n, seed, dark=False):
        cap = sensor.capture(12.0, None if dark else "lamp A", irradiance_w_m2=light,
                             n_frames=n, reflectance=np.full(n_l, rho), seed=seed)
        return cap.to_frames()

    pipe = Pipeline([("dark", create("dark")),
                     ("cube", create("reconstruct", method="bilinear", correction="imec",
                                     imec_xml=str(imec_xml))),
                     # virtual bands mix bands with coefficients of both signs: their SNR
                     # is lower than the mosaic's (the check is tested on mosaics)
                     ("refl", create("reflectance", panel=0.99, min_reference_snr=3,
                                     precision_percent=5))])
    pipe.fit(frames(0.99, 10, 1) + frames(0, 10, 2, dark=True))
    out = pipe.transform(frames(0.25, 1, 3)[0])
    assert out.data.ndim == 3 and out.data.shape[-1] == len(out.meta["wavelengths_nm"])
    inner = out.data[5:-5, 5:-5][out.dq[5:-5, 5:-5] == 0]
    assert abs(np.median(inner) / 0.25 - 1) < 0.02


# -- panel values ----------------------------------------------------------------------------------

def test_panel_spectrum_file_percent_header_and_interpolation(tmp_path):
    f = tmp_path / "panel.csv"
    f.write_text("# Spectralon certificate\nwavelength_nm,reflectance\n400, 98.0\n800;99.0\n"
                 "1000\t99.5\n", encoding="utf-8")
    wl, r, note = read_panel_spectrum(f)
    assert wl.tolist() == [400, 800, 1000] and note == "percent, divided by 100"
    values = panel_per_band(None, n_bands=2, wavelengths_nm=[600, 900], spectrum=(wl, r))
    assert values.tolist() == pytest.approx([0.985, 0.9925])
    with pytest.raises(ParameterError, match="lie outside it"):
        panel_per_band(None, n_bands=1, wavelengths_nm=[1100], spectrum=(wl, r))
    bad = tmp_path / "bad.csv"
    bad.write_text("500,0.9\n600,x\n", encoding="utf-8")
    with pytest.raises(DataFormatError, match="line 2"):
        read_panel_spectrum(bad)
    with pytest.raises(ParameterError, match="not 99"):
        panel_per_band(99, n_bands=3)
    with pytest.raises(ParameterError, match="3 values but the frames have 2 bands"):
        panel_per_band([0.9, 0.9, 0.9], n_bands=2)


def test_panel_file_through_the_stage(sim, tmp_path):
    f = tmp_path / "panel.csv"
    f.write_text("300,0.5\n1100,0.5\n", encoding="utf-8")
    t = 16.0
    train = sim.frames(t, 0.5, 10) + sim.darks(t)
    pipe = Pipeline([("dark", create("dark")),
                     ("refl", create("reflectance", panel_file=str(f)))])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe.fit(train)
        out = pipe.transform(sim.frames(t, 0.25, 1)[0])
    assert pipe.named_steps["refl"].panel_ == [0.5] * 8
    assert abs(np.median(out.data[out.dq == 0]) / 0.25 - 1) < 0.01
    with pytest.raises(ParameterError, match="not both"):
        create("reflectance", panel=0.9, panel_file=str(f)).fit(train)
    with pytest.raises(ParameterError, match="panel"):
        create("reflectance").fit(train)


# -- the figure for a uniform target ---------------------------------------------------------------

def test_target_report_measures_bias_and_pattern_not_the_scene(sim):
    t = 16.0
    train = sim.frames(t, 0.99, 10) + sim.darks(t)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pipe = sim.pipeline(train, method="model")
        outs = [pipe.transform(f) for f in sim.frames(t, 0.5, 4)]
    rep = target_report(np.stack([o.data for o in outs]), np.stack([o.dq for o in outs]),
                        sim.sensor.band_map, 8, 0.5)
    assert np.all(np.abs(rep.bias_percent) < 1)
    assert np.all(rep.fixed_pattern_percent < rep.single_frame_percent)
    assert rep.n_frames == 4 and "bias %" in rep.to_text()
    # a panel value given wrong shows as a bias of the same size
    wrong = target_report(np.stack([o.data for o in outs]) * 0.9, np.stack([o.dq for o in outs]),
                          sim.sensor.band_map, 8, 0.5)
    assert np.allclose(wrong.bias_percent, 0.9 * (100 + rep.bias_percent) - 100, atol=1e-6)
