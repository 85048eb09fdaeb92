"""CLI review fixes: mosaics are written width x height everywhere and checked against the
calibration by every command, `fit` refuses a wrong output name before reading anything, and a
short write says the disk is full."""

from __future__ import annotations

from dataclasses import replace

import pytest

from hsiffc.calibrate import calibrate
from hsiffc.cli import main
from hsiffc.io import read_sweep, write_sweep
from hsiffc.io.metadata import parse_mosaic
from hsiffc.mosaic import Mosaic


@pytest.fixture(scope="module")
def world(sample_cubes, tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_fixes")
    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    cal = root / "cal.npz"
    calibrate(sweep).save(cal)
    other = root / "mosaic4x4.tif"  # the same frames declared with another mosaic
    write_sweep(other, replace(sweep, mosaic=Mosaic.square(4)))
    toml = root / "dark.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n')
    return {"sweep": sample_cubes / "sweep_2900K.tif", "cal": cal, "other": other,
            "toml": toml, "root": root}


def test_a_tile_is_written_width_x_height_as_mosaic_takes_it():
    # "2x4" named two different tiles: the simulator's 2 rows x 4 columns and --mosaic 2x4
    # (2 wide, 4 high); every display now says W x H
    wide = Mosaic.rectangular(2, 4)
    given, _ = parse_mosaic("4x2")
    assert wide == given and wide.describe() == given.describe() == "4x2 (W x H)"
    assert parse_mosaic("2x4")[0].tile_shape == (4, 2)
    assert Mosaic.square(5, name="IMEC 5x5 NIR").describe() == "5x5 (W x H) IMEC 5x5 NIR"
    legacy = Mosaic(wide.pattern, name="2x4")  # a file written before: name not repeated
    assert legacy.describe() == "4x2 (W x H)"


def test_info_prints_the_tile_as_width_x_height(world, capsys):
    assert main(["info", str(world["sweep"])]) == 0
    assert "mosaic 4x2 (W x H)" in capsys.readouterr().out  # 2 rows of 4 bands


def test_uniformity_refuses_a_sweep_of_another_mosaic(world, tmp_path, capsys):
    assert main(["uniformity", str(world["other"]), "--calibration", str(world["cal"]),
                 "--json", str(tmp_path / "u.json")]) == 2
    err = capsys.readouterr().err
    assert str(world["other"]) in err and "mosaic 4x4 (W x H) differs" in err
    assert not (tmp_path / "u.json").exists()


def test_fit_refuses_training_frames_of_two_mosaics(world, tmp_path, capsys):
    out = tmp_path / "p.npz"
    assert main(["fit", str(world["toml"]), str(world["sweep"]), str(world["other"]), "-o",
                 str(out)]) == 2
    assert "mosaic 4x4 (W x H), but" in capsys.readouterr().err and not out.exists()


def test_fit_refuses_an_output_that_is_not_npz_before_reading_inputs(world, tmp_path, capsys):
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"not a tiff")
    assert main(["fit", str(world["toml"]), str(garbage), "-o", str(tmp_path / "p.tif")]) == 2
    err = capsys.readouterr().err
    assert "ends in .npz" in err and "garbage" not in err
