"""Helpers shared by the built-in stages (training-frame bookkeeping only; no maths)."""

from __future__ import annotations

import math

from ..data.frame import Frame
from ..data.params import Param

#: parameter declarations several stages share
AVERAGE = Param("choice", choices=("median", "mean"))
CALIBRATION = Param("calibration", optional=True)
THRESHOLD = Param("number", low=0, low_open=True, unit="percent")


def group_by_exposure(frames, kind: str) -> dict[float, list[Frame]]:
    """Frames of one kind ("light"/"dark") grouped by exposure (ms), in order of exposure."""
    groups: dict[float, list[Frame]] = {}
    for f in frames:
        if f.kind == kind and not f.is_cube:
            groups.setdefault(f.exposure_ms, []).append(f)
    return dict(sorted(groups.items()))


def find_exposure(exposures, t_ms: float, rtol: float = 1e-6):
    """The entry of ``exposures`` equal to ``t_ms`` within ``rtol`` (or None; never for a
    NaN or infinite ``t_ms``, which the tolerance test would match to any entry)."""
    if not math.isfinite(t_ms):
        return None
    for e in exposures:
        if abs(e - t_ms) <= rtol * max(abs(t_ms), 1e-12):
            return e
    return None


#: how a stage's error asks for a calibration, for every way of giving one
GIVE_CALIBRATION = ("give a calibration: --calibration FILE (hsiffc correct), calibration = "
                    "\"FILE\" in the step's [[step]] table (hsiffc fit), calibration= in Python")


def unit_hint(t_ms: float, exposures) -> str:
    """``"; ..."`` suggesting the unit when ``t_ms`` is exactly 1000x or 1/1000x of one of
    ``exposures`` (an exposure given in seconds where milliseconds are expected, or the
    reverse), else "".

    >>> unit_hint(0.1, [100.0])[:59]
    '; 0.1 ms is 100 ms / 1000: was the exposure given in second'
    >>> unit_hint(12.0, [100.0])
    ''
    """
    for e in exposures:
        for factor, sign, unit in ((1e-3, "/", "seconds"), (1e3, "x", "microseconds")):
            if find_exposure([e * factor], t_ms) is not None:
                return (f"; {t_ms:g} ms is {e:g} ms {sign} 1000: was the exposure given in "
                        f"{unit}? hsiffc takes milliseconds (--exposure-ms, exposure_ms in a "
                        "sidecar)")
    return ""
