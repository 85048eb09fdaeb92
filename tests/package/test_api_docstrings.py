"""The public API's docstrings: numpydoc with an Examples section whose examples run.

The public API is what ``hsiffc`` and its io and files faces export (``__all__``). Each class
or function there has an Examples section; its examples run here with the globals of the
module that defines it, as ``--doctest-modules`` runs them."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest
from griffe import Docstring

import hsiffc
import hsiffc.files
import hsiffc.io


def public_objects() -> list[tuple[str, object]]:
    """(name, object) of every class and function the package faces export."""
    found = []
    for face in (hsiffc, hsiffc.io, hsiffc.files):
        for name in face.__all__:
            obj = getattr(face, name)
            if inspect.isclass(obj) or inspect.isfunction(obj):
                found.append((f"{face.__name__}.{name}", obj))
    return found


PUBLIC = public_objects()


def test_the_faces_export_what_the_api_promises():
    names = {name for name, _ in PUBLIC}
    assert {"hsiffc.Sweep", "hsiffc.DQ", "hsiffc.io.open_source", "hsiffc.io.read_corrected",
            "hsiffc.io.write_cube", "hsiffc.files.atomic_path",
            "hsiffc.files.folder_lock"} <= names
    # the values without a docstring of their own are described in the face's docstring
    values = [n for n in hsiffc.io.__all__ if not callable(getattr(hsiffc.io, n))]
    assert values and [n for n in values if n not in hsiffc.io.__doc__] == []


@pytest.mark.parametrize("name, obj", PUBLIC, ids=[n for n, _ in PUBLIC])
def test_public_docstring_is_numpydoc_with_examples_that_run(name, obj):
    doc = inspect.getdoc(obj)
    assert doc, f"{name} has no docstring"
    kinds = [section.kind.value for section in Docstring(doc).parse("numpy")]
    assert "examples" in kinds, f"{name}: no numpydoc Examples section (found {kinds})"
    module = importlib.import_module(obj.__module__)
    tests = doctest.DocTestFinder(recurse=False).find(obj, name, globs=dict(vars(module)))
    examples = sum(len(t.examples) for t in tests)
    assert examples >= 2, f"{name}: its Examples section holds {examples} doctest lines"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    failures = []
    for test in tests:
        runner.run(test, out=failures.append)
    assert runner.failures == 0, "".join(failures)


def test_a_failing_example_is_reported():
    # the check itself can fail: an example whose output is wrong counts as a failure
    def wrong():
        """One line.

        Examples
        --------
        >>> 1 + 1
        3
        """
    test, = doctest.DocTestFinder(recurse=False).find(wrong, "wrong", globs={})
    runner = doctest.DocTestRunner()
    runner.run(test, out=lambda s: None)
    assert runner.failures == 1
