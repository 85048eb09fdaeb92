"""Settings of the paper's experiment (Liu et al., section V), the numbers the paper gives, and
small helpers shared by the report's modules."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["CANDIDATES_MS", "EMVA_MAX_CLIPPED", "EMVA_MIN_SIGNAL_DN", "EMVA_N_CANDIDATES",
           "FIG2_LAST_MS", "FIG4_LEVELS", "FIG5_EXPOSURES_MS", "GRID_MS", "N_TEST_FRAMES",
           "N_TRAIN_FRAMES", "PAPER_VALUES", "SPECTRA_MS", "SPECTRA_PEAK_K", "STEP_MS", "TEST_MS",
           "THRESHOLDS", "THRESHOLD_PERCENT", "WEIGHT_KEYS", "find_emva_dir", "index_of",
           "parse_weights", "select_longest", "spectral_angle_deg"]

STEP_MS = 3.225  # the paper's exposures are multiples of 3.225 ms
CANDIDATES_MS = (6.45, 12.9, 19.35, 25.8, 32.25)  # Table I / II
GRID_MS = tuple(round(STEP_MS * n, 4) for n in range(1, 13))  # training grid 3.225-38.7 ms
SPECTRA_MS = tuple(round(STEP_MS * n, 4) for n in range(1, 12))  # Fig. 6: 11 exposures
TEST_MS = 16.125
THRESHOLD_PERCENT = 12.0
N_TRAIN_FRAMES = 10
N_TEST_FRAMES = 8
FIG4_LEVELS = tuple(np.geomspace(0.03, 0.8, 16))  # lamp A, relative to the training light
FIG5_EXPOSURES_MS = tuple(float(t) for t in np.arange(20.0, 1000.1, 20.0))
FIG2_LAST_MS = 700.0
SPECTRA_PEAK_K = 30.0  # Fig. 6 light: brightest band at the training light rate of band 1
THRESHOLDS = tuple(float(t) for t in range(1, 101))
WEIGHT_KEYS = ("snr", "sc", "ru")
EMVA_N_CANDIDATES = 11
EMVA_MIN_SIGNAL_DN = 10.0
EMVA_MAX_CLIPPED = 0.01

#: Numbers the paper gives (percent for alpha and Table II; DN, DN/ms, ms elsewhere).
PAPER_VALUES = {
    "table1_alpha_percent": {1: [0.04, 0.11, 0.47, 5.15, 37.15],
                             2: [0.01, 0.13, 10.40, 12.92, 66.97],
                             3: [0.01, 0.09, 1.39, 17.93, 76.44]},
    "table2_improvement_pp": {1: [0.03, 0.14, 0.16, 0.17, -0.20],
                              2: [0.03, 0.15, 0.18, 0.13, -0.90],
                              3: [0.04, 0.11, 0.16, 0.03, -1.16]},
    "fig2": {"pentagram_alpha_percent": 0.12, "circle_alpha_percent": 74.63,
             "triangle_alpha_percent": 173.5, "triangle_ms": 700.0, "saturated_near_ms": 600.0},
    "fig5": {"k_dn_per_ms": 2.0, "saturation_dn": 800.0, "leak_rate_at_800_dn_per_ms": 2.0,
             "leakage_visible_after_ms": 430.0},
    "fig4_n_illuminations": 16,
    "fig6": {"n_exposures": 11, "deformed_above_ms": 29.0},
}


def parse_weights(weights=None) -> dict:
    """User weights of the trade-off criteria as a dict ``{"snr", "sc", "ru"}``.

    Accepts None (all 1), a dict, or text like ``"snr=1,sc=2,ru=0"``. Criteria not named get
    weight 1. Weights must be finite and >= 0, and not all 0.
    """
    out = {k: 1.0 for k in WEIGHT_KEYS}
    if weights is None:
        return out
    if isinstance(weights, str):
        items = {}
        for part in (p.strip() for p in weights.split(",")):
            if not part:
                continue
            if "=" not in part:
                raise ValueError(f"weights must look like 'snr=1,sc=1,ru=1'; got {part!r}")
            key, val = (s.strip() for s in part.split("=", 1))
            try:
                items[key.lower()] = float(val)
            except ValueError:
                raise ValueError(f"weight {key!r} must be a number, got {val!r}") from None
        weights = items
    for key, val in dict(weights).items():
        if key not in WEIGHT_KEYS:
            raise ValueError(f"unknown weight {key!r}; use {', '.join(WEIGHT_KEYS)} (SNR, "
                             "spectral correctness, response uniformity)")
        val = float(val)
        if not np.isfinite(val) or val < 0:
            raise ValueError(f"weight {key}={val} must be finite and >= 0")
        out[key] = val
    if sum(out.values()) <= 0:
        raise ValueError("at least one weight must be > 0")
    return out


def find_emva_dir(start=None) -> Path | None:
    """The real EMVA 1288 sweep folder (``shared/data/emva1288-cmos8-roi``), or None.

    Looked for under ``$HSIFFC_SHARED_DATA``, beside the repository (``../shared/data``) and
    relative to the working directory (``../shared/data``, ``shared/data``).
    """
    name = "emva1288-cmos8-roi"
    roots = []
    if os.environ.get("HSIFFC_SHARED_DATA"):
        roots.append(Path(os.environ["HSIFFC_SHARED_DATA"]))
    repo = Path(__file__).resolve().parents[3]
    cwd = Path(start) if start is not None else Path.cwd()
    roots += [repo.parent / "shared" / "data", cwd.parent / "shared" / "data",
              cwd / "shared" / "data"]
    for root in roots:
        cand = root / name
        if (cand / "EMVA1288_Data.txt").exists():
            return cand
    return None


def spectral_angle_deg(x, y) -> np.ndarray:
    """Spectral angle between spectra along the last axis: 0 for the same shape at any scale.

    Parameters
    ----------
    x, y : (..., bands) array_like
        Spectra (any unit; broadcast against each other).

    Returns
    -------
    ndarray, float64, degrees
        Shape of the broadcast leading axes; NaN where a spectrum is all zeros.

    Examples
    --------
    >>> float(spectral_angle_deg([1, 2, 3], [2, 4, 6]))
    0.0
    >>> round(float(spectral_angle_deg([1, 0], [0, 1])), 6)
    90.0
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    num = (x * y).sum(axis=-1)
    den = np.sqrt((x * x).sum(axis=-1) * (y * y).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.clip(num / den, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def index_of(values, target) -> int:
    """Index of ``target`` in ``values`` (within 1e-6); ValueError if it is not there.

    Parameters
    ----------
    values : (n,) array_like
        E.g. exposures in ms.
    target : float

    Examples
    --------
    >>> index_of([6.45, 12.9, 19.35], 12.9)
    1
    """
    values = np.asarray(values, np.float64)
    j = int(np.argmin(np.abs(values - target)))
    if not np.isclose(values[j], target, rtol=0, atol=1e-6):
        raise ValueError(f"{target} not among {values.tolist()}")
    return j


def select_longest(alpha_row, exposures, threshold):
    """Index of the longest exposure with alpha under the threshold (None if none): the
    paper's training selection rule.

    Parameters
    ----------
    alpha_row : (n,) array_like, percent
        alpha of one band at each exposure.
    exposures : (n,) array_like, ms
    threshold : float, percent

    Examples
    --------
    >>> select_longest([0.1, 5.0, 40.0], [6.45, 12.9, 19.35], 12.0)
    1
    """
    ok = np.flatnonzero(np.asarray(alpha_row) < threshold)
    if not ok.size:
        return None
    return int(ok[np.argmax(np.asarray(exposures)[ok])])


