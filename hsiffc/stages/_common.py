"""Helpers shared by the built-in stages."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from ..calibrate.product import Calibration
from ..frame import Frame


def load_calibration(value) -> Calibration | None:
    """A Calibration from a path or an object (None stays None).

    Files are read once per process and version: stages that hold a path call this for every
    frame, so the loaded calibration is cached by resolved path, size and modification time (a
    rewritten file is read again)."""
    if value is None or isinstance(value, Calibration):
        return value
    path = Path(value).resolve()
    try:
        st = path.stat()
    except OSError:
        return Calibration.load(path)  # raises the clear "not found" error
    return _load_cached(str(path), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, size: int, mtime_ns: int) -> Calibration:
    return Calibration.load(Path(path))


def group_by_exposure(frames, kind: str) -> dict[float, list[Frame]]:
    """Frames of one kind ("light"/"dark") grouped by exposure (ms), in order of exposure."""
    groups: dict[float, list[Frame]] = {}
    for f in frames:
        if f.kind == kind and not f.is_cube:
            groups.setdefault(f.exposure_ms, []).append(f)
    return dict(sorted(groups.items()))


def find_exposure(exposures, t_ms: float, rtol: float = 1e-6):
    """The entry of ``exposures`` equal to ``t_ms`` within ``rtol`` (or None)."""
    for e in exposures:
        if abs(e - t_ms) <= rtol * max(abs(t_ms), 1e-12):
            return e
    return None


def raw_response(frame: Frame, calibration: Calibration | None) -> np.ndarray:
    """The raw response Y (DN) of a frame: its data, plus the dark level it had if an earlier
    stage subtracted a dark (the leakage acts on the raw response)."""
    data = frame.data.astype(np.float64)
    if not frame.meta.get("dark_subtracted"):
        return data
    if calibration is None:
        raise ValueError("this frame was dark-subtracted; the stage needs calibration= to know "
                         "the dark level the leakage acts on")
    return data + calibration.dark + calibration.dark_current * frame.exposure_ms


def band_means(values: np.ndarray, band_map: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Mean of ``values`` per band over ``good`` pixels, broadcast back per pixel."""
    n = int(band_map.max()) + 1
    sums = np.bincount(band_map[good], weights=values[good], minlength=n)
    counts = np.bincount(band_map[good], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    return means[band_map]
