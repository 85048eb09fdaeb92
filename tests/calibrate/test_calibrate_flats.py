"""Flat stacks folded into the calibration (hsiffc.calibrate.flats): the calibration alone
carries the responsivity the flat stack improves, its dark combined with the dark frames of
the stack's exposure."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from hsiffc.calibrate import Calibration, calibrate
from hsiffc.calibrate.flats import FLAT_ARRAYS, add_flat_stacks, combined_dark
from hsiffc.cli import main
from hsiffc.data.frame import Frame
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import create
from hsiffc.data.sweep import Sweep

SHARED = Path(os.environ.get("HSIFFC_SHARED_DATA",
                             Path(__file__).resolve().parents[3] / "shared" / "data"))
FLAT_MS = 8.0


@pytest.fixture(scope="module")
def sim():
    sensor = MosaicSensor.default((24, 32), seed=5)
    light = PAPER_LIGHT_W_M2["training"]
    sweep = sensor.sweep(np.geomspace(0.5, 60, 12), "lamp A", irradiance_w_m2=light,
                         n_frames=2, seed=1)
    cal = calibrate(sweep)
    flat = sensor.capture(FLAT_MS, "lamp A", irradiance_w_m2=light, n_frames=24, seed=2)
    dark = sensor.capture(FLAT_MS, None, n_frames=24, seed=3)
    stack = Sweep(np.concatenate([flat.frames, dark.frames]), FLAT_MS,
                  ["light"] * 24 + ["dark"] * 24, 10, illumination=["lamp A"] * 24 + [""] * 24,
                  mosaic=sensor.mosaic)
    return sensor, cal, stack, flat, dark


def test_the_calibration_carries_the_flat_stack(sim, tmp_path):
    sensor, cal, stack, flat, dark = sim
    with_flat = add_flat_stacks(cal, stack)
    assert set(FLAT_ARRAYS) <= set(with_flat.arrays) and not set(FLAT_ARRAYS) & set(cal.arrays)
    info = with_flat.fitted_on["flat_stacks"]
    assert [s["n_frames"] for s in info] == [24] and "24 dark frames" in info[0]["dark"]
    # the combined factor is more certain than the sweep's alone, and closer to the truth
    good = with_flat["flat_dq"] == 0
    s_sweep = np.sqrt(np.mean(cal["sigma_ln_g"][good] ** 2))
    s_comb = np.sqrt(np.mean(with_flat["sigma_ln_flat_gain"][good] ** 2))
    assert s_comb < 0.8 * s_sweep
    truth = np.zeros(sensor.shape)
    for b in range(sensor.mosaic.n_bands):
        sel = sensor.band_map == b
        truth[sel] = sensor.gain[sel].mean() / sensor.gain[sel]
    err = lambda g: np.std(np.log(g / truth)[good])  # noqa: E731
    assert err(with_flat["flat_gain"]) < err(with_flat["flat_gain_sweep"])
    # model_ffc from the calibration alone (hsiffc correct's default) = fitted on the stack
    alone = create("model_ffc", calibration=with_flat).fit([])
    trained = create("model_ffc", calibration=cal).fit(
        flat.to_frames("light") + dark.to_frames("dark"))
    np.testing.assert_allclose(alone.gain_, trained.gain_, rtol=1e-6)
    np.testing.assert_array_equal(alone.dq_, trained.dq_)
    # kept through the file
    path = with_flat.save(tmp_path / "cal.npz")
    loaded = Calibration.load(path)
    np.testing.assert_array_equal(loaded["flat_gain"], with_flat["flat_gain"])
    assert loaded.fitted_on["flat_stacks"] == info
    # a sweep without a flat stack leaves the calibration as it is
    assert add_flat_stacks(cal, stack.select(stack.kind == "dark")) is cal


def test_combined_dark_weights_by_variance(sim):
    sensor, cal, stack, flat, dark = sim
    d_cal = cal.dark_at(FLAT_MS)
    assert np.array_equal(combined_dark(cal, FLAT_MS), np.asarray(d_cal, np.float64))
    d = combined_dark(cal, FLAT_MS, dark.frames)
    master = dark.frames.mean(axis=0)
    # between the two, closer to the one with the smaller variance, and closer to the truth
    lo, hi = np.minimum(master, d_cal), np.maximum(master, d_cal)
    assert np.all((d >= lo - 1e-9) & (d <= hi + 1e-9))
    truth = sensor.dark_dn + sensor.dark_current * FLAT_MS
    assert np.std(d - truth) < min(np.std(master - truth), np.std(d_cal - truth))


def test_calibrate_command_folds_the_emva_flat_stack(tmp_path, capsys):
    folder = SHARED / "emva1288-refsim-linear10-light"
    if not folder.exists():
        pytest.skip(f"{folder} not found: this test needs ../shared/data")
    out = tmp_path / "cal.npz"
    assert main(["calibrate", str(folder), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "flat stack: step" in printed and "20 frames" in printed
    cal = Calibration.load(out)
    assert "flat_gain" in cal.arrays
    frames = Frame.list_from_sweep(Sweep(np.zeros((1, 96, 128), np.uint16), 10.0, "light",
                                         10))
    stage = create("model_ffc", calibration=cal).fit([])
    assert stage.transform(frames[0]).data.shape == (96, 128)
