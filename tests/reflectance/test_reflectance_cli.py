"""The field user's command line, end to end: plain camera TIFFs with a sidecar -> ``hsiffc
reflectance fit`` -> ``hsiffc correct --pipeline`` -> reflectance frames; the leakage-aware path
with a calibration; ``hsiffc reflectance check`` on a grey target; one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from hsiffc.calibrate import calibrate
from hsiffc.cli import main
from hsiffc.io import read_corrected, write_sweep
from hsiffc.data.mosaic import Mosaic
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.spectral import imec_4x4_visible
from hsiffc.data.sweep import Sweep

LIGHT = PAPER_LIGHT_W_M2["training"]


def _sensor(seed=6):
    bands = imec_4x4_visible()
    return MosaicSensor((32, 48), bands=bands,
                        mosaic=Mosaic.square(4, wavelengths_nm=bands.centres_nm), seed=seed)


def _capture(sensor, t, rho, n, seed, dark=False):
    n_l = len(sensor.bands.wavelengths_nm)
    return sensor.capture(t, None if dark else "lamp A", irradiance_w_m2=LIGHT, n_frames=n,
                          reflectance=np.full(n_l, rho), seed=seed).frames


@pytest.mark.filterwarnings("ignore::hsiffc.io.MetadataConflictWarning")
def test_plain_camera_tiffs_to_reflectance(tmp_path, capsys):
    sensor = _sensor()
    t = 12.0
    refs, scenes = tmp_path / "refs", tmp_path / "scenes"
    refs.mkdir()
    scenes.mkdir()
    for i, f in enumerate(_capture(sensor, t, 0, 10, 1, dark=True)):
        tifffile.imwrite(refs / f"dark_{i:02d}.tif", f)
    for i, f in enumerate(_capture(sensor, t, 0.99, 10, 2)):
        tifffile.imwrite(refs / f"white_{i:02d}.tif", f)
    for i, f in enumerate(_capture(sensor, t, 0.3, 2, 3)):
        tifffile.imwrite(scenes / f"scene_{i}.tif", f)
    side = '[defaults]\nbit_depth = 10\nmosaic = "4x4"\nexposure_ms = 12.0\n'
    (refs / "hsiffc.toml").write_text(side)
    (scenes / "hsiffc.toml").write_text(side)
    refl = tmp_path / "refl.npz"
    assert main(["reflectance", "fit", "--dark", *map(str, sorted(refs.glob("dark_*"))),
                 "--white", *map(str, sorted(refs.glob("white_*"))), "--panel", "0.99",
                 "-o", str(refl)]) == 0
    out = capsys.readouterr()
    assert "reflectance from DN above dark per ms; panel 0.99" in out.out
    assert "checks: passed" in out.out and "warning" not in out.err
    assert main(["correct", "--pipeline", str(refl), str(scenes), "-o", str(tmp_path / "out"),
                 "-q"]) == 0
    text = capsys.readouterr().out
    assert "eq. 6" not in text  # no eq. (6) of a scene printed as if it measured the correction
    res = read_corrected(tmp_path / "out" / "scene_0.reflectance.tif")
    good = res.dq[0] == 0
    assert abs(np.median(res.data[0][good]) / 0.3 - 1) < 0.01
    # cubes: reconstruction before the reflectance, written as (H, W, bands) by correct
    assert main(["reflectance", "fit", "--dark", *map(str, sorted(refs.glob("dark_*"))),
                 "--white", *map(str, sorted(refs.glob("white_*"))), "--panel", "0.99",
                 "--cube", "bilinear", "-o", str(tmp_path / "cube.npz")]) == 0
    assert main(["correct", "--pipeline", str(tmp_path / "cube.npz"), str(scenes), "-o",
                 str(tmp_path / "cubes"), "-q"]) == 0
    capsys.readouterr()
    cube = read_corrected(tmp_path / "cubes" / "scene_0.reflectance.tif")
    assert cube.data.shape == (1, 32, 48, 16)
    assert cube.provenance["cube"]["unit"] == "reflectance factor"
    assert abs(np.median(cube.data[cube.dq == 0]) / 0.3 - 1) < 0.01
    # an ENVI export of the same job (a resume) is named and labelled as reflectance
    assert main(["correct", "--pipeline", str(tmp_path / "cube.npz"), str(scenes), "-o",
                 str(tmp_path / "cubes"), "--format", "envi", "-q"]) == 0
    header = (tmp_path / "cubes" / "scene_0.reflectance.hdr").read_text()
    assert "reflectance scale factor = 1.0" in header and "data units = reflectance factor" in header
    capsys.readouterr()
    assert main(["info", str(tmp_path / "cubes" / "scene_0.reflectance.hdr")]) == 0
    assert "ENVI cube, 32 x 48 px, 16 bands, float32 reflectance factor" in capsys.readouterr().out
    # the same reference checks a grey target: its mean against its value, its uniformity
    assert main(["reflectance", "check", str(scenes), "--pipeline", str(refl), "--expected",
                 "0.3", "--json", str(tmp_path / "target.json")]) == 0
    text = capsys.readouterr().out
    assert "bias %" in text and "worst: band " in text
    import json
    doc = json.loads((tmp_path / "target.json").read_text())
    assert max(abs(b) for b in doc["bias_percent"]) < 1.5 and doc["n_frames"] == 2


def test_leakage_aware_from_the_command_line_and_its_warnings(tmp_path, capsys):
    """With --calibration the reference is the model's light rate; a panel in strong leakage
    and a dark one are reported on stderr as one line each, and fit still writes the file."""
    sensor = _sensor(seed=8)
    ms = np.tile(np.geomspace(0.5, 80, 16), 3)
    levels = np.repeat([0.5, 1.0, 1.6], 16)
    sweep = sensor.sweep_varying_light(ms, levels, "lamp A", irradiance_w_m2=LIGHT, n_frames=3,
                                       seed=2)
    calibrate(sweep).save(tmp_path / "cal.npz")

    def write(name, frames, t, kind):
        n = len(frames)
        write_sweep(tmp_path / name, Sweep(frames, [t] * n, [kind] * n, 10,
                                           mosaic=sensor.mosaic, source=name))

    t = 27.0
    write("dark.tif", _capture(sensor, t, 0, 10, 3, dark=True), t, "dark")
    write("white.tif", _capture(sensor, t, 0.99, 10, 4), t, "light")
    write("scene.tif", _capture(sensor, t, 0.2, 2, 5), t, "light")
    refl = tmp_path / "refl.npz"
    assert main(["reflectance", "fit", "--dark", str(tmp_path / "dark.tif"), "--white",
                 str(tmp_path / "white.tif"), "--panel", "0.99", "--calibration",
                 str(tmp_path / "cal.npz"), "-o", str(refl)]) == 0
    out = capsys.readouterr()
    assert "light rates through the leakage model" in out.out
    assert "hsiffc reflectance: warning: white reference (27 ms) in strong leakage" in out.err
    assert f"--calibration {tmp_path / 'cal.npz'}" in out.out  # how to apply it
    assert main(["correct", "--pipeline", str(refl), "--calibration", str(tmp_path / "cal.npz"),
                 str(tmp_path / "scene.tif"), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = read_corrected(tmp_path / "out" / "scene.reflectance.tif")
    good = (res.dq == 0)
    assert abs(np.median(res.data[good]) / 0.2 - 1) < 0.02
    # a dark panel: one line with its numbers
    write("dim.tif", _capture(sensor, 0.5, 0.99, 10, 6), 0.5, "light")
    write("dark05.tif", _capture(sensor, 0.5, 0, 10, 7, dark=True), 0.5, "dark")
    assert main(["reflectance", "fit", "--dark", str(tmp_path / "dark05.tif"), "--white",
                 str(tmp_path / "dim.tif"), "--panel", "0.99", "-o",
                 str(tmp_path / "dim.npz")]) == 0
    err = capsys.readouterr().err
    line = [x for x in err.splitlines() if "too dark" in x][0]
    assert "DN above dark" in line and "in reflectance" in line


def test_bad_options_are_one_line(tmp_path, capsys):
    assert main(["reflectance", "fit", "--dark", "d.tif", "--white", "w.tif", "--panel", "0.99",
                 "--method", "model", "-o", str(tmp_path / "r.npz")]) == 2
    err = capsys.readouterr().err
    assert "--method model needs --calibration" in err and len(err.strip().splitlines()) == 1
    assert main(["reflectance", "fit", "--dark", "d.tif", "--white", "w.tif", "--panel", "0.99",
                 "-o", str(tmp_path / "r.txt")]) == 2
    assert "ends in .npz" in capsys.readouterr().err
    assert main(["reflectance", "fit", "--dark", "d.tif", "--white", "w.tif", "-o",
                 str(tmp_path / "r.npz")]) == 2
    assert "--panel" in capsys.readouterr().err
