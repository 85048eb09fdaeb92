"""Checks shared by test modules of several folders (tests/ is on sys.path through its
conftest): ``from checks import one_line``."""

from __future__ import annotations


import re

from hsiffc.cli.status import COMPILE_NOTICE

#: the status lines a command prints off a terminal when its kernels compile (a cold numba
#: cache: which test compiles a kernel first depends on the order the tests ran in)
_COMPILING = re.compile(re.escape(COMPILE_NOTICE) + r"|: compiled \d+ kernel functions in ")


def one_line(capsys, *names) -> str:
    """The one line a command wrote to stderr, leaving out the compile notice: no traceback,
    no internal error, naming each of ``names``."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and not _COMPILING.search(ln)]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]
