"""The golden-image regression helper (hsiffc.testing) and its pytest plugin."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from hsiffc.testing import assert_golden, golden_path

pytest_plugins = ["pytester"]


@pytest.fixture
def arrays():
    rng = np.random.default_rng(0)
    return {"data": rng.normal(100.0, 5.0, (16, 16)).astype(np.float32),
            "dq": (rng.random((16, 16)) < 0.1).astype(np.uint32),
            "mask": rng.random(5) < 0.5}


def test_regenerate_writes_then_passes(tmp_path, arrays):
    assert assert_golden("case", arrays, golden_dir=tmp_path / "g", regenerate=True) is True
    path = tmp_path / "g" / "case.npz"
    assert path.exists() and not list(path.parent.glob(".*.part"))
    with np.load(path, allow_pickle=False) as npz:
        assert sorted(npz.files) == ["data", "dq", "mask"]
        assert npz["data"].dtype == np.float32
    assert assert_golden("case", arrays, golden_dir=tmp_path / "g") is False
    first = path.read_bytes()
    assert_golden("case", arrays, golden_dir=tmp_path / "g", regenerate=True)
    assert path.read_bytes() == first  # same arrays, same bytes: no churn in version control


def test_within_tolerance_passes(tmp_path, arrays):
    assert_golden("t", arrays, golden_dir=tmp_path, regenerate=True)
    near = dict(arrays, data=arrays["data"] * np.float32(1 + 2e-7))
    assert_golden("t", near, golden_dir=tmp_path)
    shifted = dict(arrays, data=arrays["data"] + np.float32(0.01))
    assert_golden("t", shifted, golden_dir=tmp_path, atol=0.02)
    assert_golden("t", shifted, golden_dir=tmp_path, rtol=1e-3)


def test_outside_tolerance_fails_with_helpful_message(tmp_path, arrays):
    assert_golden("t", arrays, golden_dir=tmp_path, regenerate=True)
    changed = dict(arrays, data=arrays["data"].copy())
    changed["data"][3, 4] += 0.5
    changed["data"][7, 1] -= 0.1
    with pytest.raises(AssertionError) as info:
        assert_golden("t", changed, golden_dir=tmp_path, rtol=1e-4)
    msg = str(info.value)
    assert "array 'data'" in msg and "2 of 256 elements" in msg
    assert "max abs difference 0.5" in msg and "(3, 4)" in msg and "max rel difference" in msg
    assert "rtol=0.0001" in msg and "--regen-golden" in msg and "'dq'" not in msg
    assert_golden("t", changed, golden_dir=tmp_path, atol=0.6)  # looser tolerance passes
    flipped = dict(arrays, mask=~arrays["mask"])
    with pytest.raises(AssertionError, match=r"array 'mask': 5 of 5 elements differ \(exact"):
        assert_golden("t", flipped, golden_dir=tmp_path, rtol=10.0)


def test_nan_matches_nan_only(tmp_path):
    ref = np.array([1.0, np.nan, np.inf])
    assert_golden("n", {"x": ref}, golden_dir=tmp_path, regenerate=True)
    assert_golden("n", {"x": ref.copy()}, golden_dir=tmp_path)
    with pytest.raises(AssertionError, match="1 elements are NaN in only one"):
        assert_golden("n", {"x": np.array([np.nan, np.nan, np.inf])}, golden_dir=tmp_path)


def test_shape_dtype_and_names_mismatch(tmp_path, arrays):
    assert_golden("t", arrays, golden_dir=tmp_path, regenerate=True)
    with pytest.raises(AssertionError, match=r"array 'data': shape \(16, 15\) but the golden "
                                             r"one is \(16, 16\)"):
        assert_golden("t", dict(arrays, data=arrays["data"][:, :15]), golden_dir=tmp_path)
    with pytest.raises(AssertionError, match="array 'data': dtype float64 but the golden one "
                                             "is float32"):
        assert_golden("t", dict(arrays, data=arrays["data"].astype(np.float64)),
                      golden_dir=tmp_path)
    with pytest.raises(AssertionError, match=r"not given: \['mask'\]"):
        assert_golden("t", {k: arrays[k] for k in ("data", "dq")}, golden_dir=tmp_path)
    with pytest.raises(AssertionError, match=r"not in the golden file: \['extra'\]"):
        assert_golden("t", dict(arrays, extra=np.zeros(2)), golden_dir=tmp_path)


def test_missing_file_fails_and_is_not_created(tmp_path, arrays):
    with pytest.raises(AssertionError, match=r"does not exist.*--regen-golden"):
        assert_golden("absent", arrays, golden_dir=tmp_path)
    assert not (tmp_path / "absent.npz").exists()


def test_bad_inputs(tmp_path, arrays):
    for name in ("../escape", "a/b", "x.npz", ""):
        with pytest.raises(ValueError, match="plain file name"):
            golden_path(name, tmp_path)
    with pytest.raises(TypeError, match="object"):
        assert_golden("o", {"x": np.array([{}, 1], dtype=object)}, golden_dir=tmp_path,
                      regenerate=True)
    with pytest.raises(TypeError):
        assert_golden("e", {}, golden_dir=tmp_path, regenerate=True)
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(AssertionError, match="cannot be read"):
        assert_golden("broken", arrays, golden_dir=tmp_path)


# -- the pytest plugin ---------------------------------------------------------------------------
USER_TEST = """
    import numpy as np

    def test_product(golden):
        data = np.linspace(0.0, 1.0, 12, dtype=np.float32).reshape(3, 4) * SCALE
        golden("product", {"data": data, "dq": np.zeros((3, 4), np.uint32)}, rtol=1e-6)
"""


def _run(pytester, *args):
    # the inner runs do not need hypothesis' plugin (importing it dominates their run time)
    return pytester.runpytest("-p", "no:hypothesispytest", "-p", "no:cacheprovider", *args)


def _user_project(pytester, scale="1.0", conftest=True):
    if conftest:
        pytester.makeconftest('pytest_plugins = ["hsiffc.pytest_plugin"]\n')
    return pytester.makepyfile(test_user=textwrap.dedent(USER_TEST).replace("SCALE", scale))


def test_fixture_missing_golden_then_regen_then_compare(pytester):
    _user_project(pytester)
    result = _run(pytester)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*golden file*product.npz does not exist*--regen-golden*"])
    assert not (pytester.path / "golden" / "product.npz").exists()

    result = _run(pytester, "--regen-golden")
    result.assert_outcomes(passed=1)
    result.stdout.fnmatch_lines(["*hsiffc golden files regenerated*",
                                 "wrote *golden*product.npz*test_user.py::test_product*",
                                 "*Review them*"])
    assert (pytester.path / "golden" / "product.npz").exists()

    result = _run(pytester)
    result.assert_outcomes(passed=1)
    assert "regenerated" not in result.stdout.str()


def test_fixture_reports_differences(pytester):
    _user_project(pytester)
    _run(pytester, "--regen-golden").assert_outcomes(passed=1)
    _user_project(pytester, scale="1.001")
    result = _run(pytester)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*array 'data': 11 of 12 elements*rtol=1e-06*",
                                 "*--regen-golden*"])


def test_fixture_ini_golden_dir_and_p_option(pytester):
    pytester.makeini("[pytest]\ngolden_dir = refdata/golden\n")
    _user_project(pytester, conftest=False)
    _run(pytester, "-p", "hsiffc.pytest_plugin", "--regen-golden").assert_outcomes(passed=1)
    assert (pytester.path / "refdata" / "golden" / "product.npz").exists()
    assert not (pytester.path / "golden").exists()
    _run(pytester, "-p", "hsiffc.pytest_plugin").assert_outcomes(passed=1)
    help_text = _run(pytester, "-p", "hsiffc.pytest_plugin", "--help").stdout.str()
    assert "--regen-golden" in help_text and "golden_dir" in help_text


def test_entry_point_name_lets_conftest_registration_coexist(pytester):
    """If hsiffc declares the plugin as a pytest11 entry point, the entry point must be named
    after the module: under any other name, a conftest's ``pytest_plugins =
    ["hsiffc.pytest_plugin"]`` registers the module a second time and pytest stops with
    "Plugin already registered under a different name"."""
    import importlib.metadata

    names = [ep.name for ep in importlib.metadata.entry_points(group="pytest11")
             if ep.value == "hsiffc.pytest_plugin"]
    assert all(name == "hsiffc.pytest_plugin" for name in names), names
    _user_project(pytester)  # conftest registration (plus the entry point, when installed)
    _run(pytester, "--regen-golden").assert_outcomes(passed=1)
