"""Shared fixtures. Real measured data are read from ../shared/data and never copied here."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

#: numba threads of each test process (and of the processes a test starts), unless the
#: environment sets ``NUMBA_NUM_THREADS``: the test processes already take one core each
#: (``-n auto``), so more threads would only contend for them, and with one thread every
#: :class:`~hsiffc.kernels.launch.Kernel` runs its serial build. The parallel builds then
#: compile only where a test asks for them: their equality with the serial builds is tested
#: on their own (``tests/kernels``, ``-m slow``) and by the benchmarks on full frames. Set
#: before numba is imported (numba reads it once); ``tests/kernels/test_threads.py`` checks it took.
TEST_NUMBA_THREADS = "1"
if "numba" not in sys.modules:
    os.environ.setdefault("NUMBA_NUM_THREADS", TEST_NUMBA_THREADS)
#: BLAS and LAPACK threads (numpy.linalg, scipy) of each test process, for the same reason:
#: OpenBLAS starts one thread per core in every process and its idle threads spin, so the
#: test processes of ``-n auto`` took each other's cores (diagnose's SVDs and solves). Set
#: before numpy is imported (OpenBLAS reads it when it loads); the processes a test starts
#: inherit it. tests/diagnose/test_diagnose.py -k library_effect, ``-n 2 --dist load``, warm
#: numba cache, twice each: CPU (user + system) 134 and 140 s with 2 BLAS threads (OpenBLAS's
#: default on 2 cores), 98 and 99 s with 1; wall 136 and 142 s, 85 and 100 s (load 3-6).
TEST_BLAS_THREADS = "1"
if "numpy" not in sys.modules:
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, TEST_BLAS_THREADS)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("HSIFFC_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLE_CUBES = REPO / "sample_cubes"

#: what test tools (not the tests) may leave in the working directory: git-ignored caches
TOOL_CACHES = frozenset({".pytest_cache", ".hypothesis", "__pycache__"})


#: at most this many test processes for ``-n auto`` (the README's test command): each compiles
#: the kernels it needs that no other has cached yet and holds its own frames
MAX_TEST_WORKERS = 4


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one test process per core, at most :data:`MAX_TEST_WORKERS`."""
    return max(1, min(os.cpu_count() or 1, MAX_TEST_WORKERS))


#: ``workerinput`` key of the folder of the compile locks the test processes share
COMPILE_LOCKS = "hsiffc_compile_locks"
_LOCK_FOLDER = pytest.StashKey[str]()


def pytest_configure(config):
    """A test process of ``-n`` compiles each cached numba build once for the whole run: see
    :mod:`compilelock` (measured: the test processes of a cold run on 2 cores compiled 107 s of
    their 353 s twice, counted by numba's ``numba:compile`` event per signature and process)."""
    folder = getattr(config, "workerinput", {}).get(COMPILE_LOCKS)
    if folder:
        from compilelock import install

        install(folder)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """``-n``: the controller makes one folder of compile locks for its test processes."""
    stash = node.config.stash
    if _LOCK_FOLDER not in stash:
        stash[_LOCK_FOLDER] = tempfile.mkdtemp(prefix="hsiffc-test-compile-locks-")
    node.workerinput[COMPILE_LOCKS] = stash[_LOCK_FOLDER]


def pytest_unconfigure(config):
    if _LOCK_FOLDER in config.stash:
        shutil.rmtree(config.stash[_LOCK_FOLDER], ignore_errors=True)


def _names(folder: Path) -> set[str]:
    """The names in ``folder`` (top level only: cheap enough to take around every test;
    ``.ci/run`` checks the whole tree with ``git status``)."""
    try:
        return {name for name in os.listdir(folder) if name not in TOOL_CACHES}
    except OSError:  # the working directory is gone or unreadable: nothing to compare
        return set()


@pytest.fixture(autouse=True)
def _working_directory_untouched(request):
    """Fail a test that creates a file or folder in the current directory: tests read and
    write under ``tmp_path`` (a ``monkeypatch.chdir(tmp_path)`` is fine: the directory checked
    is the one the test started in). Only new names are checked, not edits: people editing
    the checkout while tests run must not fail them; ``.ci/run``'s ``git status`` sees the
    rest."""
    cwd = Path.cwd()
    before = _names(cwd)
    yield
    created = sorted(_names(cwd) - before)
    if created:
        pytest.fail(f"{request.node.nodeid} touched the current directory {cwd}: created "
                    f"{', '.join(created)}; a test writes under tmp_path (and monkeypatch.chdir"
                    "(tmp_path) where code writes relative paths)", pytrace=False)


def _require(path: Path, what: str) -> Path:
    if not path.exists():
        pytest.skip(f"{what} not found at {path}: this test needs the measured data in "
                    "../shared/data (set HSIFFC_SHARED_DATA to its folder to run it)")
    return path


@pytest.fixture(scope="session")
def emva_dir() -> Path:
    """Folder of the real EMVA 1288 sweep (skips when absent)."""
    return _require(SHARED_DATA / "emva1288-cmos8-roi" / "EMVA1288_Data.txt",
                    "EMVA 1288 descriptor").parent


@pytest.fixture(scope="session")
def shared_set():
    """``get(name)``: the folder of a data set in ../shared/data (skips when absent)."""
    return lambda name: _require(SHARED_DATA / name, f"the {name} set")


@pytest.fixture(scope="session")
def imec_xml() -> Path:
    """The real IMEC 5x5 sensor calibration XML (skips when absent)."""
    return _require(SHARED_DATA / "imec-ssm5x5" / "CMV2K-SSM5x5-600_875-5.5.9.2.xml",
                    "IMEC sensor calibration XML")


@pytest.fixture(scope="session")
def sample_cubes() -> Path:
    return SAMPLE_CUBES


@pytest.fixture(scope="session")
def demo_result(sample_cubes):
    """The demo's result on the sample cubes, computed once per session (read it, do not
    change it)."""
    from hsiffc.reports.demo import compute_demo

    return compute_demo(sample_cubes)


@pytest.fixture(scope="session")
def elementwise():
    """``elementwise(fn)(x, out)`` sets ``out[i] = fn(x[i])`` in a compiled loop: a
    :mod:`hsiffc.kernels.vmath` function run the way the kernels run it (inlined, vectorised)."""
    from numba import njit

    def make(fn):
        @njit(error_model="numpy")
        def run(x, out):
            for i in range(x.shape[0]):
                out[i] = fn(x[i])
        return run
    return make
