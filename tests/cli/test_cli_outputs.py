"""Every output option of every command: an existing file (or report folder) is refused without
--overwrite before any work, an input is never written, a symbolic link is never written through,
and write failures (permission, folder, disk full) are one line with exit status 2."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from hsiffc.files import atomic
from hsiffc.cli import main


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


SAMPLES = Path(__file__).resolve().parents[2] / "sample_cubes"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_outputs")
    sweep = root / "sweep.tif"
    assert main(["simulate", str(sweep), "--exposures-ms", "2", "4", "--shape", "8", "8"]) == 0
    cal = root / "cal.npz"
    cal.write_bytes(b"not read: outputs are checked before any input is read")
    toml = root / "pipe.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n')
    return {"root": root, "sweep": sweep, "cal": cal, "toml": toml}


def _commands(f, out):
    """Every (command line, output) pair: FILE outputs and report folders."""
    s, c, t = str(f["sweep"]), str(f["cal"]), str(f["toml"])
    return {
        "info --json": ["info", s, "--json", out],
        "simulate OUTPUT": ["simulate", out, "--exposures-ms", "5", "--shape", "8", "8"],
        "calibrate -o": ["calibrate", s, "-o", out],
        "calibrate --json": ["calibrate", s, "-o", str(f["root"] / "new_cal.npz"), "--json", out],
        "select --json": ["select", s, "--calibration", c, "--threshold", "12", "--json", out],
        "stages --json": ["stages", "--json", out],
        "fit -o": ["fit", t, s, "-o", out],
        "correct --json": ["correct", s, "--calibration", c, "-o", str(f["root"] / "o"),
                           "--json", out],
        "diagnose --json": ["diagnose", s, "--json", out],
        "diagnose --report": ["diagnose", s, "--report", out],
        "paper OUTDIR": ["paper", out],
        # the demo checks its samples first (a missing sample is the more basic mistake)
        "demo -o": ["demo", str(SAMPLES), "-o", out],
        "import -o": ["import", s, "-o", out],
        "uniformity --json": ["uniformity", s, "--calibration", c, "--json", out],
        "uniformity --plot": ["uniformity", s, "--calibration", c, "--json",
                              str(f["root"] / "u.json"), "--plot", out],
        "study-ffc OUTDIR": ["study-ffc", out],
    }


FOLDER_OUTPUTS = {"diagnose --report", "paper OUTDIR", "demo -o", "study-ffc OUTDIR"}
OPTIONS = list(_commands({"sweep": "", "cal": "", "toml": "", "root": Path()}, "x"))


@pytest.mark.parametrize("option", OPTIONS)
def test_existing_output_is_refused_without_overwrite(files, tmp_path, capsys, option):
    if option in FOLDER_OUTPUTS:
        out = tmp_path / "report"
        out.mkdir()
        kept = out / "report.md"
    else:
        out = kept = tmp_path / ("out.npz" if option in ("calibrate -o", "fit -o") else
                                 "out.tif" if option in ("simulate OUTPUT", "import -o") else
                                 "out.png" if option == "uniformity --plot" else "out.json")
    kept.write_text("an earlier result")
    before = {p: p.stat().st_mtime_ns for p in files["root"].iterdir()}
    assert main(_commands(files, str(out))[option]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(out) in line and "--overwrite" in line
    assert kept.read_text() == "an earlier result"
    assert {p: p.stat().st_mtime_ns for p in files["root"].iterdir()} == before


@pytest.mark.parametrize("option", ["info --json", "stages --json", "simulate OUTPUT"])
def test_overwrite_replaces_an_existing_output(files, tmp_path, option):
    out = tmp_path / ("out.tif" if option == "simulate OUTPUT" else "out.json")
    out.write_text("an earlier result")
    assert main(_commands(files, str(out))[option] + ["--overwrite"]) == 0
    assert out.read_bytes() != b"an earlier result"


@pytest.mark.parametrize("option", ["info --json", "simulate OUTPUT", "stages --json"])
def test_symlink_at_an_output_is_never_written_through(files, tmp_path, capsys, option):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    link = tmp_path / ("link.tif" if option == "simulate OUTPUT" else "link.json")
    link.symlink_to(victim)
    assert main(_commands(files, str(link))[option]) == 2
    assert "symbolic link" in _one_line(capsys.readouterr().err)
    assert victim.read_text() == "precious" and link.is_symlink()
    assert main(_commands(files, str(link))[option] + ["--overwrite"]) == 0
    assert victim.read_text() == "precious" and not link.is_symlink()


def test_the_commands_own_input_is_never_written(files, tmp_path, capsys):
    sweep = tmp_path / "s.tif"
    sweep.write_bytes(files["sweep"].read_bytes())
    os.link(sweep, tmp_path / "hard.json")
    for out in (sweep, tmp_path / "hard.json"):
        assert main(["info", str(sweep), "--json", str(out), "--overwrite"]) == 2
        assert "input of this command" in _one_line(capsys.readouterr().err)
    assert sweep.read_bytes() == files["sweep"].read_bytes()


@pytest.mark.parametrize("given", ["folder", "glob"])
def test_files_found_in_a_folder_or_glob_input_are_never_written(files, tmp_path, capsys, given):
    # the input typed is a folder or a glob: the files it stands for are inputs as well
    sweep = tmp_path / "d" / "s.tif"
    sweep.parent.mkdir()
    sweep.write_bytes(files["sweep"].read_bytes())
    arg = str(sweep.parent) if given == "folder" else str(sweep.parent / "*.tif")
    assert main(["info", arg, "--json", str(sweep), "--overwrite"]) == 2
    assert "input of this command" in _one_line(capsys.readouterr().err)
    assert sweep.read_bytes() == files["sweep"].read_bytes()


def test_the_data_file_beside_an_envi_header_input_is_never_written(files, tmp_path, capsys):
    import numpy as np

    from hsiffc.io.envi import write_envi

    header, data = write_envi(tmp_path / "cube.hdr", np.ones((6, 5, 4), np.uint16))
    assert data != header and data.stem == header.stem
    before = data.read_bytes()
    assert main(["info", str(header), "--json", str(data), "--overwrite"]) == 2
    assert "input of this command" in _one_line(capsys.readouterr().err)
    assert data.read_bytes() == before


@pytest.mark.parametrize("given", ["folder", "descriptor"])
def test_the_images_of_an_emva_measurement_input_are_never_written(tmp_path, capsys, given):
    from hsiffc.diagnose.simulated import simulated_sweep, write_emva1288
    from hsiffc.io.emva import emva_files

    folder = tmp_path / "emva"
    descriptor = write_emva1288(simulated_sweep("mixed", seed=0, n_steps=4), folder)
    images = emva_files(folder)[1:]
    assert images and all(p.is_file() and p.suffix == ".png" for p in images)
    (folder / "notes.md").write_text("not part of the measurement")  # not listed, not read
    before = images[-1].read_bytes()
    arg = folder if given == "folder" else descriptor
    assert main(["info", str(arg), "--json", str(images[-1]), "--overwrite"]) == 2
    assert "input of this command" in _one_line(capsys.readouterr().err)
    assert images[-1].read_bytes() == before


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes on this system")
def test_a_pipe_or_device_is_never_replaced_even_with_overwrite(files, tmp_path, capsys):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    assert main(["info", str(files["sweep"]), "--json", str(fifo), "--overwrite"]) == 2
    assert "not a regular file" in _one_line(capsys.readouterr().err)
    assert fifo.is_fifo()


def test_one_file_for_two_outputs_is_refused(files, tmp_path, capsys):
    out = tmp_path / "x.npz"
    assert main(["calibrate", str(files["sweep"]), "-o", str(out), "--json", str(out)]) == 2
    assert "two outputs" in _one_line(capsys.readouterr().err)


def test_a_folder_as_output_file_is_one_line(files, tmp_path, capsys):
    assert main(["info", str(files["sweep"]), "--json", str(tmp_path), "--overwrite"]) == 2
    assert "is a folder" in _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("option", ["info --json", "simulate OUTPUT", "stages --json"])
def test_disk_full_is_one_line_naming_the_output(files, tmp_path, capsys, monkeypatch, option):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    out = tmp_path / ("o.tif" if option == "simulate OUTPUT" else "o.json")
    assert main(_commands(files, str(out))[option]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(out) in line and "disk space" in line
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


@pytest.mark.parametrize("option", ["info --json", "simulate OUTPUT", "stages --json"])
def test_permission_denied_is_one_line_naming_the_output(files, tmp_path, capsys, monkeypatch,
                                                         option):
    real_open = os.open

    def denied(path, *a, **k):  # as a read-only folder would (root ignores chmod)
        if str(path).endswith(".part"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(atomic.os, "open", denied)
    out = tmp_path / ("o.tif" if option == "simulate OUTPUT" else "o.json")
    assert main(_commands(files, str(out))[option]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(out) in line and "permission" in line.lower() and ".part" not in line


def test_overwrite_replaces_an_earlier_report(tmp_path):
    sweep = tmp_path / "s.tif"
    assert main(["simulate", str(sweep), "--exposures-ms", "2", "4", "8", "16", "32",
                 "--shape", "8", "8"]) == 0
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "report.md").write_text("old")
    assert main(["diagnose", str(sweep), "--report", str(rep), "--pixels", "16",
                 "--overwrite"]) == 0
    assert (rep / "report.md").read_text() != "old" and (rep / "diagnosis.json").is_file()
    assert not [p for p in rep.iterdir() if p.name.endswith(".part")]


def test_json_outputs_hold_no_nan(tmp_path):
    """``info --json`` on a plain TIFF without the metadata it needs (exit 0, the missing fields
    listed): unknown values are null, not the bare word NaN that strict JSON readers refuse."""
    import json

    import numpy as np
    import tifffile

    frames = np.random.default_rng(0).integers(300, 900, (4, 8, 16)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "plain.tif", frames, photometric="minisblack", metadata=None)
    assert main(["info", str(tmp_path / "plain.tif"), "--json", str(tmp_path / "info.json")]) == 0

    def refuse(name):
        raise AssertionError(f"{name} in the JSON output")

    json.loads((tmp_path / "info.json").read_text(encoding="utf-8"), parse_constant=refuse)
