"""EMVA 1288 Release 4.0 beyond the classic figures, against independent invariants on
simulated sensors whose truth is known: the streamed statistics equal the in-memory ones (and
the compiled kernels the numpy ones), the row/column/pixel split recovers a known row and
column pattern, the high-pass PRNU ignores a smooth illumination fall-off, the General module
gives the linear module's answer on a linear camera and follows the leakage model on a leaky
one. (The agreement with the reference implementation itself: test_emva_reference.py.)"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hsiffc.data.sweep import Sweep
from hsiffc.emva1288 import characterise, run_characterisation, step_statistics
from hsiffc.emva1288.general import general_curves
from hsiffc.errors import DataFormatError
from hsiffc.io import open_source, read_emva1288
from test_emva1288 import leaky_sweep, simulate, write_descriptor


@pytest.fixture(scope="module")
def linear():
    return simulate(seed=11, shape=(40, 48), n_steps=20, stack=16)


def test_streamed_statistics_equal_the_in_memory_ones(linear, tmp_path):
    sweep, _ = linear
    desc = write_descriptor(sweep, tmp_path / "set")
    mem = characterise(read_emva1288(desc))  # every frame held
    with open_source(desc) as src:
        streamed = characterise(src)  # one frame at a time
    for name, f in mem["figures"].items():
        if f["value"] is None:
            assert streamed["figures"][name]["value"] is None, name
            continue
        assert streamed["figures"][name]["value"] == pytest.approx(f["value"], rel=1e-12,
                                                                   abs=1e-15), name
    np.testing.assert_array_equal(streamed["defect_pixels"]["DSNU"]["values"],
                                  mem["defect_pixels"]["DSNU"]["values"])


def test_compiled_and_numpy_kernels_give_the_same_statistics(linear, monkeypatch):
    from hsiffc.emva1288 import stream

    sweep, _ = linear
    sweep = replace(sweep, mosaic=__import__("hsiffc.data.mosaic", fromlist=["Mosaic"])
                    .Mosaic.square(2))
    a = step_statistics(sweep, keep_step_means=True)
    monkeypatch.setattr(stream, "COMPILED_FROM", 0.0)
    monkeypatch.setattr(stream, "COMPILED_FRAME_PIXELS", 0)
    b = step_statistics(sweep, keep_step_means=True)
    for ga, gb in zip(a["groups"], b["groups"]):
        np.testing.assert_allclose(gb["mean_dn"], ga["mean_dn"], rtol=1e-13)
        np.testing.assert_allclose(gb["var_dn2"], ga["var_dn2"], rtol=1e-11)
    np.testing.assert_allclose(b["step_means"], a["step_means"], rtol=1e-6)
    np.testing.assert_allclose(b["pairs"], a["pairs"], rtol=1e-13)


def _command_modules(sweep, folder, options, modules):
    """Run ``hsiffc emva1288`` on ``sweep`` (written into ``folder``) with ``options`` in a
    fresh process; which of ``modules`` that process imported, its return code, the JSON."""
    import json
    import subprocess
    import sys

    desc = write_descriptor(sweep, folder / "set")
    out = folder / "out.json"
    code = ("import sys\nfrom hsiffc.cli import main\n"
            f"rc = main(['emva1288', {str(desc)!r}, *{options!r}, '--json', {str(out)!r}])\n"
            f"print(*[m in sys.modules for m in {modules!r}], rc)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=folder, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    *loaded, rc = run.stdout.split()[-len(modules) - 1:]
    return [v == "True" for v in loaded], int(rc), json.loads(out.read_text())


def test_the_figures_of_a_small_set_never_load_numba(linear, tmp_path):
    """Loading numba's code generator costs more than a small set's whole reduction: the
    command's figures alone run on numpy (the kernel choice, the package face, the status
    line's compile listener all leave numba unloaded)."""
    loaded, rc, doc = _command_modules(linear[0], tmp_path, ["--no-leakage"], ["numba"])
    assert (loaded, rc) == ([False], 0)
    assert doc["figures"]["K"]["value"] > 0


def test_the_leakage_account_runs_in_a_child_and_the_command_never_loads_it(linear, tmp_path):
    """The default command computes the leakage account in a forked child (numba and the
    calibration load there while the frames are read): the command's own process never imports
    the calibration, and the JSON holds the same account as one computed in this process."""
    sweep = linear[0]
    loaded, rc, doc = _command_modules(sweep, tmp_path, [], ["hsiffc.calibrate", "numba"])
    assert (loaded, rc) == ([False, False], 0)
    with open_source(tmp_path / "set") as src:
        _, here, _ = run_characterisation(src, background=False)
    child = doc["leakage"]
    assert child["calibration"]["n_pixels"] == sweep.frame_shape[0] * sweep.frame_shape[1]
    assert child["evidence"] == here["evidence"]
    assert child["evidence"]["verdict"] == "noise"  # a linear camera: nothing to explain
    assert child["linearity"]["share_explained_model"] == pytest.approx(
        here["linearity"]["share_explained_model"], rel=1e-9)
    assert child["alpha"]["saturation"]["p50"] == pytest.approx(
        here["alpha"]["saturation"]["p50"], rel=1e-9)
    assert child["temporal_variance"]["at_saturation_dn2"] == pytest.approx(
        here["temporal_variance"]["at_saturation_dn2"], rel=1e-9)


def test_a_process_with_numba_loaded_keeps_the_account(tmp_path):
    """Once numba's OpenMP threads run in a process, a forked child that uses them is aborted
    by numba: such a process (numba loaded) computes the account itself, without a child."""
    import subprocess
    import sys

    code = ("import sys\nsys.path[:0] = sys.argv[1:]\nimport numpy as np\n"
            "from hsiffc.leakage import model\n"
            "model.response(np.ones(100000), 1.0, 0.0, 0.01, 0.0)\n"
            "from test_emva1288 import leaky_sweep\n"
            "from hsiffc.emva1288 import run_characterisation\n"
            "import multiprocessing.process as mpp\n"
            "started, start = [], mpp.BaseProcess.start\n"
            "mpp.BaseProcess.start = lambda self: started.append(self) or start(self)\n"
            "_, leak, _ = run_characterisation(leaky_sweep(shape=(8, 12)))\n"
            "print(len(started), leak['alpha']['saturation']['p50'] > 0)\n")
    import os

    here = Path(__file__).resolve().parent
    # two numba threads (the test processes run on one, tests/conftest.py): the response of
    # 100000 values then runs the parallel build and starts numba's OpenMP threads
    run = subprocess.run([sys.executable, "-c", code, str(here), str(here.parent)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300,
                         env={**os.environ, "NUMBA_NUM_THREADS": "2"})
    assert run.stdout.split()[-2:] == ["0", "True"], run.stdout + run.stderr  # no child
    assert "fork" not in run.stderr, run.stderr


def test_the_calibration_pilot_takes_the_pixels_asked_for():
    """The calibration makes its sensor-wide choices on ``pilot_pixels`` pixels (the leakage
    account asks for a quarter of its drawn ones); without it, on all of a sensor smaller than
    the default 4096."""
    from hsiffc.calibrate import LEAKAGE_ACCOUNT, calibrate
    from hsiffc.emva1288 import LEAKAGE_PILOT_PIXELS, step_mean_sweep

    sweep = leaky_sweep(shape=(16, 24))
    means, ptc = step_mean_sweep(step_statistics(sweep, keep_step_means=True), sweep)
    for asked, used in ((100, 100), (None, 384)):
        kw = {} if asked is None else {"pilot_pixels": asked}
        cal = calibrate(means, method="joint", ptc=ptc, **kw, **LEAKAGE_ACCOUNT)
        assert cal.fitted_on["dark_model"]["n_pilot_pixels"] == used
    assert 0 < LEAKAGE_PILOT_PIXELS < 4096


def test_temporal_variance_of_a_step_is_the_standards_frame_pair_formula(linear):
    sweep, _ = linear
    stats = step_statistics(sweep)
    s = int(sweep.steps()[3])
    a, b = sweep.data[sweep.step == s].astype(np.float64)
    d = a - b
    expected = 0.5 * np.mean((d - d.mean()) ** 2)
    i = int(np.flatnonzero(stats["steps"]["step"] == s)[0])
    assert stats["groups"][0]["var_dn2"][i] == pytest.approx(expected, rel=1e-12)


def test_non_contiguous_steps_are_refused_with_the_fix():
    sweep, _ = simulate(seed=2, shape=(8, 8), n_steps=4, stack=4)
    order = np.r_[np.arange(1, sweep.n_frames), 0]  # first frame moved to the end

    class Stream:  # a FrameSource-like stream in that order
        frame_shape, bit_depth, mosaic, meta = sweep.frame_shape, sweep.bit_depth, None, {}
        step, n_frames, source = sweep.step, sweep.n_frames, "reordered"

        def __iter__(self):
            from types import SimpleNamespace

            for i in order:
                yield sweep.data[i], SimpleNamespace(
                    step=int(sweep.step[i]), kind=str(sweep.kind[i]),
                    exposure_ms=float(sweep.exposure_ms[i]), photons=float(sweep.photons[i]))

    with pytest.raises(DataFormatError, match="not one after the other"):
        step_statistics(Stream())


def _stack_sweep(light_img, dark_img, rng, L=24, noise=0.5):
    """A spatial stack (one light, one dark step of L frames) and a light sweep, for the
    nonuniformity figures: frames = image + read noise + shot noise (0.1 DN/e-)."""
    shape = light_img.shape

    def noisy(img, n):
        sd = np.sqrt(noise ** 2 + 0.1 * np.maximum(img - dark_img, 0))
        return img + sd * rng.standard_normal((n,) + shape)

    frames, kind, photons, step = [], [], [], []
    for i, lev in enumerate(np.linspace(0.05, 1.2, 12)):
        for k, img in (("light", dark_img + lev * (light_img - dark_img)), ("dark", dark_img)):
            frames.append(noisy(img, 2))
            kind += [k] * 2
            photons += [1000.0 * lev if k == "light" else np.nan] * 2
            step += [2 * i + (k == "dark")] * 2
    for k, img in (("light", light_img), ("dark", dark_img)):
        frames.append(noisy(img, L))
        kind += [k] * L
        photons += [1000.0 if k == "light" else np.nan] * L
        step += [100 + (k == "dark")] * L
    data = np.concatenate(frames)
    return Sweep(data, 1.0, np.array(kind), 16, step=np.array(step),
                 photons=np.array(photons), meta={"spatial_steps": [100, 101]})


def test_row_column_pixel_split_recovers_a_known_pattern():
    rng = np.random.default_rng(4)
    m, n = 96, 128
    rows = 0.6 * rng.standard_normal(m)[:, None]
    cols = 0.9 * rng.standard_normal(n)[None, :]
    pix = 0.4 * rng.standard_normal((m, n))
    dark = 100.0 + rows + cols + pix
    light = dark + 2000.0 * (1 + 0.01 * rng.standard_normal((m, n)))
    res = characterise(_stack_sweep(light, dark, rng))
    f = {k: v["value"] for k, v in res["figures"].items()}
    assert f["DSNU1288_row_DN"] == pytest.approx(rows.std(ddof=1), rel=0.1)
    assert f["DSNU1288_col_DN"] == pytest.approx(cols.std(ddof=1), rel=0.1)
    assert f["DSNU1288_pixel_DN"] == pytest.approx(pix.std(ddof=1), rel=0.05)
    # the parts add up to the total variance (up to the cross terms of a finite pattern)
    total = f["DSNU1288_row_DN"] ** 2 + f["DSNU1288_col_DN"] ** 2 + f["DSNU1288_pixel_DN"] ** 2
    assert total == pytest.approx(f["DSNU1288_DN"] ** 2, rel=0.05)
    # a pure pixel PRNU pattern: no row or column part beyond what chance leaves
    assert f["PRNU1288_pixel"] == pytest.approx(1.0, rel=0.05)
    assert (f["PRNU1288_row"] or 0.0) < 0.25 and (f["PRNU1288_col"] or 0.0) < 0.25


def test_highpass_prnu_ignores_a_smooth_illumination_fall_off():
    rng = np.random.default_rng(5)
    m, n = 96, 128
    yy, xx = np.mgrid[0:m, 0:n]
    fall = 1 - 0.08 * (((yy - m / 2) / m) ** 2 + ((xx - n / 2) / n) ** 2) * 4
    dark = 100.0 + 0.3 * rng.standard_normal((m, n))
    gain = 1 + 0.01 * rng.standard_normal((m, n))
    light = dark + 2000.0 * gain * fall
    f = characterise(_stack_sweep(light, dark, rng))["figures"]
    assert f["PRNU1288"]["value"] > 1.5  # the reference's PRNU counts the fall-off
    assert f["PRNU1288_highpass"]["value"] == pytest.approx(1.0, rel=0.08)
    # without a fall-off the two agree
    f2 = characterise(_stack_sweep(dark + 2000.0 * gain, dark, rng))["figures"]
    assert f2["PRNU1288_highpass"]["value"] == pytest.approx(f2["PRNU1288"]["value"], rel=0.08)


def test_general_gives_the_linear_answer_on_a_linear_camera(linear):
    sweep, truth = linear
    res = characterise(sweep)
    g = res["general"]["figures"]
    assert g["QE_general"]["value"] == pytest.approx(truth["QE"], rel=0.06)
    c = res["curves"]
    y = np.asarray(c["u_y"]) - np.asarray(c["u_ydark"])
    snr_lin = y / np.sqrt(np.asarray(c["s2_y"]))
    snr = res["general"]["curves"]["SNR"]
    mid = slice(3, res["fit_ranges"]["sensitivity"]["index"][1])
    np.testing.assert_allclose(snr[mid], snr_lin[mid], rtol=0.15)
    assert g["u_p_sat_general"]["value"] == pytest.approx(res["figures"]["u_p_sat"]["value"],
                                                          rel=0.15)
    # a line gives its own slope as the differential responsivity
    cu = general_curves(np.array([1.0, 2.0, 4.0, 8.0, 9.0]), 3 * np.array([1.0, 2, 4, 8, 9]),
                        np.ones(5))
    np.testing.assert_allclose(cu["R_diff"], 3.0)


def test_general_follows_the_leakage_model_on_a_leaky_sensor():
    res, leak, note = run_characterisation(leaky_sweep(shape=(16, 24)))
    assert note is None
    g = res["general"]
    assert "model" in g
    assert abs(g["model"]["index_sat"] - g["index_sat"]) <= 3
    r = g["curves"]["R_diff"]
    # the response bends: the differential responsivity falls well below its start
    assert r[g["index_sat"]] < 0.9 * np.nanmedian(r[:5])
    m = g["model"]["figures"]["SNR_max_general"]["value"]
    assert m == pytest.approx(g["figures"]["SNR_max_general"]["value"], rel=0.15)


def test_leakage_account_on_drawn_pixels():
    """The leakage account calibrates the step means of pixels drawn at random: the stream keeps
    those pixels' means only (the same values as the whole images there), and the account's
    figures (means, percentiles and shares over pixels) stay close to the all-pixel ones."""
    from hsiffc.emva1288 import leakage_pixels

    sweep = leaky_sweep(shape=(16, 24))
    pix = leakage_pixels(sweep.frame_shape, 192)
    assert pix.size == 192 and np.all(np.diff(pix) > 0)
    assert leakage_pixels(sweep.frame_shape, 384) is None  # a small sensor: every pixel
    whole = step_statistics(sweep, keep_step_means=True)
    part = step_statistics(sweep, keep_step_means=pix)
    n_steps = whole["step_means"].shape[0]
    assert part["step_means"].shape == (n_steps, 1, 192)
    np.testing.assert_array_equal(part["step_means"][:, 0],
                                  whole["step_means"].reshape(n_steps, -1)[:, pix])
    np.testing.assert_array_equal(part["pairs"], whole["pairs"])  # over all pixels
    _, all_px, _ = run_characterisation(sweep, n_leakage_pixels=None)
    _, drawn, _ = run_characterisation(sweep, n_leakage_pixels=192)
    assert all_px["calibration"]["drawn_seed"] is None
    cal = drawn["calibration"]
    assert (cal["n_pixels"], cal["sensor_pixels"], cal["drawn_seed"]) == (192, 384, 0)
    for key in ("leaked_share", "generated_dn", "stored_dn"):
        assert drawn["saturation_budget"][key] == pytest.approx(
            all_px["saturation_budget"][key], rel=0.02), key
    assert drawn["alpha"]["saturation"]["p50"] == pytest.approx(
        all_px["alpha"]["saturation"]["p50"], rel=0.05)
    tv_all, tv = all_px["temporal_variance"], drawn["temporal_variance"]
    assert abs(tv["saturation_index_predicted"] - tv_all["saturation_index_predicted"]) <= 1
