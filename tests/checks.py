"""Checks shared by test modules of several folders (tests/ is on sys.path through its
conftest): ``from checks import one_line``."""

from __future__ import annotations


def one_line(capsys, *names) -> str:
    """The one line a command wrote to stderr: no traceback, no internal error, naming each of
    ``names``."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]
