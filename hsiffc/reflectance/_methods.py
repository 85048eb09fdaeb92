"""The reflectance methods: one registry, one signature for the rate a method divides.

Every concrete method turns one frame into a rate per value (:class:`Rates`); the reflectance
is the scene's rate over the white reference's. ``"auto"`` is no rate of its own: it runs as
the first leakage-aware method with a calibration, else as the first other one
(:func:`resolve_method`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..data.params import validate_method

__all__ = ["REFLECTANCE_METHODS", "Rates", "ReflectanceMethod", "resolve_method"]


class Rates(NamedTuple):
    """What a reflectance method's ``rate`` returns for one frame.

    Attributes
    ----------
    rate : array, DN/ms
        The rate of every value the reflectance divides.
    dq : (H, W) uint32 or None
        Flags the method adds (the model's inversion and LEAKAGE flags); None: none.
    alpha : (H, W) float32, percent, or None
        The model alpha of every value (leakage-aware methods), else None.
    signal : array, DN
        The frame's DN above dark (the checks compare it with the rate).
    """

    rate: np.ndarray
    dq: np.ndarray | None
    alpha: np.ndarray | None
    signal: np.ndarray


@dataclass(frozen=True)
class ReflectanceMethod:
    """A registered reflectance method.

    Attributes
    ----------
    summary : str
        What the method divides, in one line (help texts, the fit's report).
    rate : callable or None
        ``rate(frame, calibration, *, prepared, alpha_limit_percent) -> Rates`` for a frame
        with an exposure > 0 ms (``calibration`` None for a method that is not leakage-aware;
        ``prepared``: the calibration prepared, or None). None: a choice between the other
        methods (:func:`resolve_method`).
    leakage_aware : bool
        The rate is the light rate of the calibrated leakage model: the method needs a
        calibration and inverts raw mosaic pixels (before reconstruction).
    requires : frozenset of str
        What the frame must be for the ``reflectance`` stage (its ``requires``).
    """

    summary: str
    rate: Callable | None = None
    leakage_aware: bool = False
    requires: frozenset = frozenset()


def _ratio_rate(frame, calibration=None, *, prepared=None, alpha_limit_percent=None) -> Rates:
    """DN above dark per ms."""
    signal = frame.signal
    return Rates(signal / np.float32(frame.exposure_ms), None, None, signal)


def _model_rate(frame, calibration, *, prepared=None, alpha_limit_percent: float) -> Rates:
    """The light rate k: the leakage model inverted per pixel (:mod:`hsiffc.leakage.linearise`)."""
    from ..leakage.linearise import linearise

    cal, t = calibration, frame.exposure_ms
    cal.check_frame(frame)
    if frame.dark_removed is not None:
        dark, current = frame.dark_removed, 0.0
    else:
        dark, current = cal.dark, cal.dark_current
    raw = frame.raw
    lin = linearise(raw, t, cal.a, cal.b, dark, current, full_scale_dn=2 ** frame.bit_depth - 1,
                    alpha_limit_percent=float(alpha_limit_percent))
    signal = raw - (dark if frame.dark_removed is not None else (prepared or cal).dark_at(t))
    return Rates(lin.light_rate, lin.dq, lin.alpha, signal)


#: Registered reflectance methods: name -> :class:`ReflectanceMethod`.
#:
#: Adding a method: write its ``rate`` with the signature of :class:`ReflectanceMethod` and
#: register it here; the ``reflectance`` stage (its ``method`` parameter) and ``hsiffc
#: reflectance fit --method`` take their choices from this mapping, and look a name up with
#: :func:`~hsiffc.data.params.validate_method`.
REFLECTANCE_METHODS = {
    "auto": ReflectanceMethod("model with a calibration, else ratio"),
    "model": ReflectanceMethod("light rates through the leakage model", _model_rate,
                               leakage_aware=True, requires=frozenset({"mosaic", "response"})),
    "ratio": ReflectanceMethod("DN above dark per ms", _ratio_rate,
                               requires=frozenset({"dark_subtracted"})),
}


def resolve_method(name: str, calibrated: bool) -> str:
    """The method ``name`` runs as: itself, or for a choice (``"auto"``) the first registered
    leakage-aware method when a calibration is given, else the first other one.

    Parameters
    ----------
    name : str
        One of :data:`REFLECTANCE_METHODS`.
    calibrated : bool
        Whether a leakage calibration is given.

    Returns
    -------
    str
        A method with a ``rate``.

    Raises
    ------
    ParameterError
        ``name`` is not registered (one line with the valid names).

    Examples
    --------
    >>> resolve_method("auto", calibrated=True), resolve_method("auto", calibrated=False)
    ('model', 'ratio')
    >>> resolve_method("ratio", calibrated=True)
    'ratio'
    """
    how = validate_method(name, REFLECTANCE_METHODS, "reflectance method")
    if how.rate is not None:
        return name
    return next(n for n, m in REFLECTANCE_METHODS.items()
                if m.rate is not None and m.leakage_aware == bool(calibrated))
