"""benchmarks/compare_revisions.py: the verdict on a head / base ratio of two revisions."""

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "compare_revisions.py"


@pytest.fixture(scope="module")
def cmp():
    spec = importlib.util.spec_from_file_location("compare_revisions", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("unit, ratio, noise, word", [
    ("s", 1.30, 1.10, "slower"),        # a time up by more than the rounds' spread
    ("s", 1.05, 1.10, "same"),          # within the spread
    ("s", 0.80, 1.10, "faster"),
    ("Mpx/s", 0.80, 1.10, "slower"),    # a rate down is slower
    ("Mpx/s", 1.30, 1.10, "faster"),
    ("frames/s", 0.95, 1.10, "same"),
    ("x", 3.0, 1.0, ""),                # no direction known: not judged
])
def test_the_verdict_reads_the_ratio_by_the_unit_against_the_noise(cmp, unit, ratio, noise, word):
    assert cmp.verdict(unit, ratio, noise) == word


def test_only_figures_both_revisions_measured_are_compared(cmp):
    base = {"a": [10.0, 12.0, 11.0], "gone": [1.0]}
    head = {"a": [22.0, 20.0, 24.0], "new": [2.0]}
    (row,) = cmp.compare(base, head, {"a": "s", "gone": "s", "new": "s"})
    name, unit, b, h, ratio, noise, word = row
    assert (name, b, h) == ("a", 11.0, 22.0)
    assert ratio == pytest.approx(2.0)
    assert noise == pytest.approx(24.0 / 20.0)  # the larger spread of the two revisions
    assert word == "slower"
