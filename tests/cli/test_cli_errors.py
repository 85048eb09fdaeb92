"""The CLI's one error path: expected errors are one line and exit 2, --debug shows the traceback."""

from __future__ import annotations

import os

import pytest

from hsiffc.cli import main


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_missing_input_is_one_line(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nope.tif")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith("hsiffc info: error:") and "nope.tif" in line


def test_output_in_a_missing_folder_is_created(tmp_path, capsys):
    # as by every writer (calibrate -o, correct -o, --json); simulate alone used to refuse
    out = tmp_path / "no" / "such" / "dir" / "sim.tif"
    assert main(["simulate", str(out), "--exposures-ms", "5", "--shape", "8", "8"]) == 0
    assert out.is_file()


def test_output_folder_that_cannot_be_made_is_one_line(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "dir" / "sim.tif"  # a file where a folder would have to be
    code = main(["simulate", str(out), "--exposures-ms", "5", "--shape", "8", "8"])
    assert code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "hsiffc simulate: error:" in line and "afile" in line and ".part" not in line
    assert "a part of the path is a file" in line
    out = tmp_path / "afile" / "list.json"  # the file is the output's folder itself
    assert main(["stages", "--json", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "a part of the path is a file" in line and "File exists" not in line


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root ignores file permissions")
def test_permission_denied_is_one_line(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        assert main(["simulate", str(locked / "x.tif"), "--exposures-ms", "5",
                     "--shape", "8", "8"]) == 2
    finally:
        locked.chmod(0o700)
    assert "permission" in _one_error_line(capsys.readouterr().err).lower()


def test_unexpected_error_is_one_line_and_debug_shows_traceback(monkeypatch, tmp_path, capsys):
    import hsiffc.cli.data as data

    def boom(args):
        raise ZeroDivisionError("synthetic failure")

    parser_main = main
    monkeypatch.setattr(data, "_cmd_info", boom)
    # the parser binds the function at build time, so rebuild through main()
    code = parser_main(["info", str(tmp_path / "x.tif")])
    assert code == 3
    line = _one_error_line(capsys.readouterr().err)
    assert "internal error" in line and "ZeroDivisionError" in line and "--debug" in line
    with pytest.raises(ZeroDivisionError):
        parser_main(["--debug", "info", str(tmp_path / "x.tif")])
