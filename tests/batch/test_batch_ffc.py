"""``hsiffc correct``'s default flat field: model_ffc from the calibration alone (``--ffc``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hsiffc import batch
from hsiffc.calibrate import calibrate
from hsiffc.cli import main
from hsiffc.data.dq import DQ
from hsiffc.io import read_sweep, write_sweep
from hsiffc.io.corrected import read_corrected
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.flatfield.uniformity import fixed_pattern_nonuniformity

SHAPE = (48, 64)
LIGHT = PAPER_LIGHT_W_M2["training"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A calibrated simulated sensor and one cube of a uniform scene: 4 frames at each of three
    exposures from weak signal to strong leakage."""
    root = tmp_path_factory.mktemp("batch_ffc")
    sensor = MosaicSensor(SHAPE, seed=5)
    sweep = sensor.sweep(np.linspace(2, 40, 12), "lamp A", irradiance_w_m2=LIGHT, n_frames=4,
                         seed=1)
    cal_path = root / "cal.npz"
    cal = calibrate(sweep)
    cal.save(cal_path)
    cube = sensor.sweep([5.0, 15.0, 30.0], "lamp A", irradiance_w_m2=LIGHT, n_frames=4,
                        darks=False, seed=7)
    path = root / "scene.tif"
    write_sweep(path, replace(cube, meta={}))
    return {"root": root, "cal": cal, "cal_path": cal_path, "cube": path}


def _steps(world, out):
    """Per exposure: (raw, corrected) fixed-pattern non-uniformity (%), pooled over bands, on
    the pixels no DQ bit but LEAKAGE flags in any frame of the step (the values of leaking
    pixels are kept: they are corrected too); and the corrected file."""
    sweep = read_sweep(world["cube"])
    c = read_corrected(out / "scene.corrected.tif")
    band = sweep.mosaic.band_map(sweep.frame_shape)
    rows = {}
    for t in np.unique(sweep.exposure_ms):
        sel = sweep.exposure_ms == t
        good = ((c.dq[sel] & ~np.uint32(DQ.LEAKAGE)) == 0).all(axis=0)
        raw = fixed_pattern_nonuniformity(sweep.data[sel].astype(float), band,
                                          dark=world["cal"].dark_at(float(t)), mask=good)
        cor = fixed_pattern_nonuniformity(c.data[sel], band, mask=good)
        alpha = float(np.median(c.alpha[sel][:, good]))
        rows[float(t)] = (raw.pooled_fpn_percent, cor.pooled_fpn_percent, good.mean(), alpha)
    return rows, c


def test_default_correction_flattens_a_uniform_scene(world, tmp_path):
    out = tmp_path / "out"
    assert main(["correct", str(world["cube"]), "--calibration", str(world["cal_path"]), "-o",
                 str(out), "-q"]) == 0
    rows, c = _steps(world, out)
    steps = [s["stage"] for s in c.provenance["pipeline"]["steps"]]
    assert steps == ["dark", "alpha_mask", "model_ffc"]
    assert np.isfinite(c.data).all() and np.isfinite(c.alpha[c.alpha < 1e30]).all()
    for t, (raw, cor, usable, alpha) in rows.items():
        assert usable > 0.9, t
        # measured: raw ~1.0 %, corrected 0.33 / 0.29 % at 5 / 15 ms and 0.49 % at 30 ms,
        # where the median alpha is 30 % (what limits it: docstring of hsiffc.flatfield.model_based)
        assert cor < (0.4 if alpha < 12 else 0.6) * raw, (t, alpha, raw, cor)
    assert max(a for *_, a in rows.values()) > 12  # the strong-leakage case was tested
    assert (c.dq & int(DQ.LEAKAGE)).any()  # the 30 ms frames leak: flagged, values kept
    leaking = (c.dq & int(DQ.LEAKAGE)) != 0
    assert (c.data[leaking] > 0).all()


def test_ffc_none_is_the_pipeline_without_flat_field(world, tmp_path):
    out = tmp_path / "none"
    assert main(["correct", str(world["cube"]), "--calibration", str(world["cal_path"]), "-o",
                 str(out), "-q", "--ffc", "none"]) == 0
    rows, c = _steps(world, out)
    assert [s["stage"] for s in c.provenance["pipeline"]["steps"]] == ["dark", "alpha_mask"]
    for raw, cor, *_ in rows.values():  # dark subtraction alone leaves the pattern
        assert cor == pytest.approx(raw, rel=0.05)
    pipe = batch.default_pipeline(world["cal"], ffc="none", linearise=True)
    assert [s.name for _, s in pipe.steps] == ["dark", "alpha_mask", "linearise"]


def test_linearise_with_model_ffc_is_refused_naming_the_options(world, tmp_path, capsys):
    code = main(["correct", str(world["cube"]), "--calibration", str(world["cal_path"]), "-o",
                 str(tmp_path / "o"), "--linearise"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--linearise" in err and "--ffc none" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
    with pytest.raises(batch.BatchError, match="--ffc"):
        batch.default_pipeline(world["cal"], ffc="flat")


def test_ffc_with_a_pipeline_file_is_refused(world, tmp_path, capsys):
    pipe = batch.default_pipeline(world["cal"])
    pipe.save(tmp_path / "pipe.npz")
    code = main(["correct", str(world["cube"]), "--calibration", str(world["cal_path"]), "-o",
                 str(tmp_path / "o"), "--pipeline", str(tmp_path / "pipe.npz"), "--ffc", "none"])
    assert code == 2 and "--pipeline" in capsys.readouterr().err
