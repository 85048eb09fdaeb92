"""Shared fixtures. Real measured data are read from ../shared/data and never copied here."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("HSIFFC_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLE_CUBES = REPO / "sample_cubes"


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
def imec_xml() -> Path:
    """The real IMEC 5x5 sensor calibration XML (skips when absent)."""
    return _require(SHARED_DATA / "imec-ssm5x5" / "CMV2K-SSM5x5-600_875-5.5.9.2.xml",
                    "IMEC sensor calibration XML")


@pytest.fixture(scope="session")
def sample_cubes() -> Path:
    return SAMPLE_CUBES


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
