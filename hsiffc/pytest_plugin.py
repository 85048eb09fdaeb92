"""pytest plugin: the ``golden`` fixture and the ``--regen-golden`` option.

Enable it in your top-level ``conftest.py``::

    pytest_plugins = ["hsiffc.pytest_plugin"]

(or with ``pytest -p hsiffc.pytest_plugin``). Then, in a test::

    def test_flat_field(golden):
        corrected = my_pipeline(...)
        golden("flat_field", {"data": corrected.data, "dq": corrected.dq}, rtol=1e-5)

compares with ``golden/flat_field.npz`` next to the test file (see
:func:`hsiffc.testing.assert_golden`). ``pytest --regen-golden`` writes the golden files
instead of comparing and lists them at the end of the run for review. The ini option
``golden_dir`` puts every golden file in one folder (relative to the ini file).
"""

from __future__ import annotations

from pathlib import Path

import pytest

# hsiffc.testing (numpy, numba, scipy through the stages) is imported by the fixture when a
# test uses it, not when pytest loads the plugin in every session of an environment

_REGENERATED = pytest.StashKey[list]()


def pytest_addoption(parser):
    """Add ``--regen-golden`` and the ``golden_dir`` ini option."""
    group = parser.getgroup("hsiffc", "hsiffc golden-image regression tests")
    group.addoption("--regen-golden", action="store_true", default=False, dest="regen_golden",
                    help="write the arrays passed to the `golden` fixture as new golden files "
                         "instead of comparing (review the files before committing them)")
    parser.addini("golden_dir", type="string", default="",
                  help="folder of the golden .npz files, relative to the ini file "
                       "(default: a golden/ folder next to each test file)")


def pytest_configure(config):
    """Register the plugin's state for this test session."""
    config.stash[_REGENERATED] = []


def _golden_dir(request) -> Path:
    config = request.config
    configured = config.getini("golden_dir")
    if not configured:
        return request.path.parent / "golden"
    folder = Path(configured)
    if not folder.is_absolute():
        base = config.inipath.parent if config.inipath is not None else config.rootpath
        folder = base / folder
    return folder


@pytest.fixture
def golden(request):
    """Check arrays against a golden file: ``golden(name, arrays, rtol=1e-6, atol=0.0)``.

    Fails (AssertionError) when the file is missing or an array differs beyond the
    tolerances; under ``--regen-golden`` writes the file instead and reports it at the end of
    the run. Returns True when the file was written. ``golden.golden_dir`` is the folder used.
    """
    folder = _golden_dir(request)
    regenerate = bool(request.config.getoption("regen_golden"))

    def check(name: str, arrays: dict, *, rtol: float = 1e-6, atol: float = 0.0) -> bool:
        from .testing import assert_golden

        written = assert_golden(name, arrays, golden_dir=folder, rtol=rtol, atol=atol,
                                regenerate=regenerate)
        if written:
            request.config.stash[_REGENERATED].append((request.node.nodeid,
                                                       str(folder / f"{name}.npz")))
        return written

    check.golden_dir = folder
    return check


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """List the golden files regenerated in this session."""
    regenerated = config.stash.get(_REGENERATED, [])
    if not regenerated:
        return
    terminalreporter.section("hsiffc golden files regenerated (--regen-golden)", yellow=True)
    for nodeid, path in regenerated:
        terminalreporter.line(f"wrote {path}  ({nodeid})")
    terminalreporter.line(f"{len(regenerated)} golden file(s) regenerated: nothing was compared. "
                          "Review them (e.g. git diff) before committing, then rerun without "
                          "--regen-golden.")
