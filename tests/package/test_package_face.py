"""The package's face (issue 54): ``hsiffc.__all__`` holds what a newcomer needs first, imported
lazily, so that ``import hsiffc`` and ``hsiffc --version`` import neither numba nor hsiffc's
kernels; the command line imports a command's modules only when that command runs."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

import hsiffc

REPO = Path(__file__).resolve().parents[2]
#: what no light start may import
HEAVY = ("numba", "hsiffc.kernels", "hsiffc.batch", "hsiffc.calibrate")


def modules_after(code: str) -> list[str]:
    """The modules of ``sys.modules`` after ``code`` runs in a fresh interpreter."""
    script = (f"import sys\n{code}\n"
              "import json; print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if m.split(".")[0] == "numba" or m.startswith(HEAVY[1:])]


def test_import_hsiffc_imports_neither_numba_nor_the_kernels():
    loaded = modules_after("import hsiffc; hsiffc.__version__")
    assert heavy(loaded) == []
    assert "numpy" not in loaded  # nothing numerical at all until a name is used


def test_version_imports_neither_numba_nor_the_kernels():
    code = ("import runpy\nsys.argv = ['hsiffc', '--version']\n"
            "try:\n    runpy.run_module('hsiffc', run_name='__main__')\n"
            "except SystemExit as exc:\n    assert exc.code == 0, exc.code")
    loaded = modules_after(code)
    assert heavy(loaded) == []
    assert [m for m in loaded if m.startswith("hsiffc.cli.") and m not in
            ("hsiffc.cli.args", "hsiffc.cli.examples")] == []
    out = subprocess.run([sys.executable, "-m", "hsiffc", "--version"], capture_output=True,
                         text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == f"hsiffc {hsiffc.__version__}"


def test_a_command_imports_its_own_module_only():
    code = ("from hsiffc.cli import build_parser\n"
            "args = build_parser().parse_args(['quicklook', 'x.hdr', '-o', 'x.png'])\n"
            "assert args.command == 'quicklook' and callable(args.func)")
    loaded = modules_after(code)
    assert "hsiffc.cli.cubes" in loaded
    assert [m for m in loaded if m.startswith("hsiffc.cli.") and m not in
            ("hsiffc.cli.args", "hsiffc.cli.examples", "hsiffc.cli.common",
             "hsiffc.cli.cubes")] == []
    assert heavy(loaded) == []


def test_dir_shows_the_face_and_nothing_it_imported():
    names = dir(hsiffc)
    assert names == sorted(hsiffc.__all__)
    assert {"Frame", "Pipeline", "create", "calibrate", "read_sweep", "read_cube",
            "open_source", "DQ", "Sweep", "Mosaic", "__version__"} <= set(names)
    assert not {"PackageNotFoundError", "annotations", "version"} & set(names)
    assert isinstance(hsiffc.__version__, str) and hsiffc.__version__


@pytest.mark.parametrize("name, module", [("DQ", "hsiffc.data.dq"), ("Sweep", "hsiffc.data.sweep"),
                                          ("Mosaic", "hsiffc.data.mosaic"),
                                          ("Frame", "hsiffc.data.frame"),
                                          ("read_sweep", "hsiffc.io"), ("open_source", "hsiffc.io"),
                                          ("read_cube", "hsiffc.cubes"),
                                          ("Pipeline", "hsiffc.stages"),
                                          ("create", "hsiffc.stages")])
def test_each_name_of_the_face_is_the_object_of_its_module(name, module):
    assert getattr(hsiffc, name) is getattr(importlib.import_module(module), name)
    exec(f"from hsiffc import {name} as got", scope := {})
    assert scope["got"] is getattr(importlib.import_module(module), name)


def test_calibrate_is_its_package_callable_as_its_function(sample_cubes):
    import inspect
    from unittest import mock

    import hsiffc.calibrate.joint as joint  # the package's modules import by their path

    package = sys.modules["hsiffc.calibrate"]
    assert hsiffc.calibrate is package and joint is sys.modules["hsiffc.calibrate.joint"]
    exec("from hsiffc import calibrate as got", scope := {})
    assert scope["got"] is package
    assert inspect.signature(hsiffc.calibrate) == inspect.signature(package.calibrate)
    with mock.patch("hsiffc.calibrate.calibrate", return_value="patched") as fake:
        assert hsiffc.calibrate("a sweep", method="paper") == "patched"  # calls the function
    fake.assert_called_once_with("a sweep", method="paper")
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        hsiffc.nope  # noqa: B018


def test_calibrate_is_the_callable_package_whichever_is_imported_first():
    # the face's calibrate first, the package imported after it, and the other way round (the
    # README's example calls it on a sweep: tests/package/test_docs.py)
    for code in ("import hsiffc; f = hsiffc.calibrate; import hsiffc.calibrate.joint as j",
                 "import hsiffc.calibrate.joint as j, hsiffc; f = hsiffc.calibrate"):
        loaded = modules_after(code + "\npackage = sys.modules['hsiffc.calibrate']\n"
                               "assert f is package and hsiffc.calibrate is package\n"
                               "assert j is package.joint and callable(f)")
        assert "hsiffc.calibrate.joint" in loaded


def test_a_stand_in_for_calibrate_can_be_set_and_undone(monkeypatch):
    monkeypatch.setattr(hsiffc, "calibrate", lambda sweep: "stand-in")
    assert hsiffc.calibrate(None) == "stand-in"
    monkeypatch.undo()
    assert hsiffc.calibrate is sys.modules["hsiffc.calibrate"]


def test_the_command_table_says_which_module_registers_each_command():
    from hsiffc.cli import COMMAND_MODULES, COMMANDS

    for module in COMMAND_MODULES:
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(f"hsiffc.cli.{module}").register(sub)
        assert list(sub.choices) == [c for c, m in COMMANDS.items() if m == module], module


def test_help_lists_every_command_in_the_table_order(capsys):
    from hsiffc.cli import COMMANDS, build_parser

    text = build_parser().format_help()
    at = [text.index(f"\n    {name} ") for name in COMMANDS]
    assert at == sorted(at)
