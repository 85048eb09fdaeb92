"""Golden-image regression checks for users' own tests (no pytest needed here).

:func:`assert_golden` compares a dict of arrays with the ones stored in ``golden_dir/name.npz``
and fails with a message naming every array that differs, by how much and how many elements.
A golden file is only ever written on purpose (``regenerate=True``; with the pytest plugin
:mod:`hsiffc.pytest_plugin`, ``pytest --regen-golden``), atomically and without pickle.

Examples
--------
>>> import tempfile, numpy as np
>>> from hsiffc.testing import assert_golden
>>> with tempfile.TemporaryDirectory() as d:
...     assert_golden("flat", {"gain": np.ones(3)}, golden_dir=d, regenerate=True)
...     assert_golden("flat", {"gain": np.ones(3) + 1e-9}, golden_dir=d)
True
False
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import numpy as np

from .files.atomic import atomic_path
from .stages.contract import check_stage  # noqa: F401 (the stage contract tests, for plugin authors)

__all__ = ["assert_golden", "check_stage", "golden_path", "REGEN_HINT"]

#: How to regenerate golden files on purpose (appended to every failure message).
REGEN_HINT = ("If the change is intended, regenerate on purpose with `pytest --regen-golden` "
              "(or assert_golden(..., regenerate=True)) and review the new file before "
              "committing it.")

_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_FIXED_TIME = (1980, 1, 1, 0, 0, 0)  # zip entries carry no wall-clock time: same data, same bytes


def golden_path(name: str, golden_dir) -> Path:
    """``golden_dir / (name + ".npz")``, after checking ``name`` is a plain file name."""
    if not isinstance(name, str) or not _NAME.match(name) or name.endswith(".npz"):
        raise ValueError(f"golden name {name!r} must be a plain file name without '.npz' "
                         "(letters, digits, '_', '-', '.'; no folders)")
    return Path(golden_dir) / f"{name}.npz"


def _as_arrays(arrays) -> dict[str, np.ndarray]:
    if not isinstance(arrays, dict) or not arrays:
        raise TypeError("arrays must be a non-empty dict {name: array}")
    out = {}
    for key, value in arrays.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise ValueError(f"array name {key!r} must be a non-empty string without '/'")
        arr = np.asarray(value)
        if arr.dtype.hasobject:
            raise TypeError(f"array {key!r} has dtype object; golden files hold plain numeric, "
                            "boolean or string arrays (no pickle)")
        out[key] = arr
    return out


def _write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path, overwrite=True) as tmp:  # only on purpose: regenerate=True
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for key in sorted(arrays):
                info = zipfile.ZipInfo(f"{key}.npy", date_time=_FIXED_TIME)
                info.compress_type = zipfile.ZIP_DEFLATED
                with zf.open(info, "w") as fh:
                    np.lib.format.write_array(fh, np.ascontiguousarray(arrays[key]),
                                              allow_pickle=False)


def _compare(key: str, actual: np.ndarray, expected: np.ndarray, rtol: float,
             atol: float) -> str | None:
    """A description of how ``actual`` differs from ``expected``, or None if it matches."""
    if actual.shape != expected.shape:
        return f"array {key!r}: shape {actual.shape} but the golden one is {expected.shape}"
    if actual.dtype != expected.dtype:
        return f"array {key!r}: dtype {actual.dtype} but the golden one is {expected.dtype}"
    if not np.issubdtype(actual.dtype, np.number):  # bool, str: exact
        bad = actual != expected
        if not np.any(bad):
            return None
        return (f"array {key!r}: {int(np.sum(bad))} of {actual.size} elements differ "
                f"(exact comparison for dtype {actual.dtype})")
    a = actual.astype(np.complex128 if np.iscomplexobj(actual) else np.float64)
    e = expected.astype(a.dtype)
    nan_a, nan_e = np.isnan(a), np.isnan(e)
    with np.errstate(invalid="ignore", over="ignore"):
        diff = np.abs(a - e)
        same_inf = np.isinf(a) & np.isinf(e) & (a == e)
        ok = (diff <= atol + rtol * np.abs(e)) | (nan_a & nan_e) | same_inf
    bad = ~ok
    n_bad = int(bad.sum())
    if n_bad == 0:
        return None
    finite = bad & np.isfinite(diff)
    msg = (f"array {key!r}: {n_bad} of {actual.size} elements ({100.0 * n_bad / actual.size:.3g} %)"
           f" differ beyond rtol={rtol:g}, atol={atol:g}")
    if finite.any():
        d = np.where(finite, diff, -1.0)
        worst = np.unravel_index(int(np.argmax(d)), d.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(finite, diff / np.abs(e), 0.0)
        msg += (f"; max abs difference {float(diff[worst]):.6g} at index {tuple(map(int, worst))}"
                f" (actual {a[worst]:.6g}, golden {e[worst]:.6g}); max rel difference "
                f"{float(np.max(rel)):.6g}")
    n_nan = int((bad & (nan_a ^ nan_e)).sum())
    if n_nan:
        msg += f"; {n_nan} elements are NaN in only one of the two"
    return msg


def assert_golden(name: str, arrays: dict, *, golden_dir, rtol: float = 1e-6, atol: float = 0.0,
                  regenerate: bool = False) -> bool:
    """Compare ``arrays`` with the golden file ``golden_dir/name.npz``.

    Each array must have the golden array's shape and dtype, and agree elementwise within
    ``|actual - golden| <= atol + rtol * |golden|`` (NaN matches NaN, as in
    :func:`numpy.testing.assert_allclose`); non-numeric arrays must be equal. The file must
    hold exactly the arrays given.

    Parameters
    ----------
    name : str
        File name of the golden set without ``.npz`` (no folders).
    arrays : dict of str to array_like
        The arrays to check (numeric, boolean or string; never object).
    golden_dir : path-like
        Folder of the golden files.
    rtol, atol : float
        Relative and absolute tolerances.
    regenerate : bool
        Write ``arrays`` as the new golden file (atomically) instead of comparing.

    Returns
    -------
    bool
        True when the file was (re)generated, False when the arrays were compared and match.

    Raises
    ------
    AssertionError
        The golden file is missing (it is never created silently), holds other arrays, or an
        array differs; the message says how and how to regenerate on purpose.
    """
    path = golden_path(name, golden_dir)
    arrays = _as_arrays(arrays)
    if rtol < 0 or atol < 0:
        raise ValueError(f"tolerances must be >= 0, got rtol={rtol}, atol={atol}")
    if regenerate:
        _write(path, arrays)
        return True
    if not path.exists():
        raise AssertionError(f"golden file {path} does not exist. Create it on purpose with "
                             "`pytest --regen-golden` (or assert_golden(..., regenerate=True)), "
                             "check the arrays it holds, and commit it.")
    try:
        with np.load(path, allow_pickle=False) as npz:
            golden = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        raise AssertionError(f"golden file {path} cannot be read ({exc}). {REGEN_HINT}") from exc
    problems = []
    missing, extra = sorted(set(golden) - set(arrays)), sorted(set(arrays) - set(golden))
    if missing:
        problems.append(f"arrays in the golden file but not given: {missing}")
    if extra:
        problems.append(f"arrays given but not in the golden file: {extra}")
    for key in sorted(set(arrays) & set(golden)):
        problem = _compare(key, arrays[key], golden[key], float(rtol), float(atol))
        if problem:
            problems.append(problem)
    if problems:
        raise AssertionError(f"golden {name!r} ({path}) does not match:\n  - "
                             + "\n  - ".join(problems) + f"\n{REGEN_HINT}")
    return False
