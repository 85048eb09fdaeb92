"""What :func:`hsiffc.diagnose.diagnose` returns: a typed :class:`Diagnosis` (read as a dict
too, as ``hsiffc diagnose --json`` writes it) with the arrays the report plots
(:class:`ResidualArrays`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields

import numpy as np

__all__ = ["Diagnosis", "ResidualArrays"]


@dataclass
class ResidualArrays:
    """The held-out residuals before and after, and what the report bins them by; arrays
    (P, S) or (S,) or (P,), DN where they are values.

    Fields: ``res_before``, ``res_after`` (DN), ``valid`` (held-out samples), ``t`` (ms),
    ``signal`` (DN above dark), ``light``, ``order``, ``rows``, ``cols``, ``band``, ``step``.
    """

    res_before: np.ndarray
    res_after: np.ndarray
    valid: np.ndarray
    t: np.ndarray
    signal: np.ndarray
    light: np.ndarray
    order: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    band: np.ndarray
    step: np.ndarray

    def __getitem__(self, key):
        return getattr(self, key)


@dataclass
class Diagnosis(Mapping):
    """The result of :func:`hsiffc.diagnose.diagnose`: figures in DN, the selected effects and
    the verdict. It reads as a dict (``result["after"]``) with the keys of ``hsiffc diagnose
    --json``, plus ``"_arrays"`` (:attr:`arrays`); :meth:`public` is the JSON-safe part.

    The fields are those keys: the data set, base and dark model, design and leakage check;
    pixel and sample counts; the noise floor (DN), where it was measured from and the test of
    the frame differences against the noise model (``noise_test``); the RMS figures before and
    after (DN); ``selected_effects`` (every effect the search kept), ``findings`` (those that
    are not stand-ins), ``stand_ins`` (those reported as stand-ins for what the library lacks:
    the verdict is unexplained, or their parameters are physically implausible), ``effects``
    (one dict each, with ``stand_in_for_unexplained``); the candidates tried and skipped;
    ``unexplained`` with its reason; ties (``ambiguous``); the residual structure before and
    after; the held-out design, the selection rule and the run time (s).
    """

    dataset: str
    base_model: str
    design: dict
    leakage: dict
    dark_model: dict
    n_pixels: int
    n_pixels_sensor: int
    n_samples: int
    n_invalid_samples: int
    noise_floor_dn: float
    noise_source: str
    noise_test: dict
    before: dict
    after: dict
    selected_effects: list
    findings: list
    stand_ins: list
    effects: list
    skipped: list
    candidates: list
    unexplained: bool
    unexplained_reason: str
    ambiguous: list
    residual_structure_after: list
    residual_structure_before: list
    held_out: str
    selection_rule: str
    runtime_s: float
    arrays: ResidualArrays | None = field(default=None, repr=False)

    def _keys(self):
        return [f.name for f in fields(self) if f.name != "arrays"] + ["_arrays"]

    def __getitem__(self, key):
        if key == "_arrays":
            return self.arrays
        if key in self._keys():
            return getattr(self, key)
        raise KeyError(key)

    def __setitem__(self, key, value):
        if key not in self._keys():
            raise KeyError(f"{key!r} is not a field of a Diagnosis")
        setattr(self, "arrays" if key == "_arrays" else key, value)

    def __iter__(self):
        return iter(self._keys())

    def __len__(self):
        return len(self._keys())

    def public(self) -> dict:
        """The JSON-safe part (without the arrays), as ``hsiffc diagnose --json`` writes it.

        Returns
        -------
        dict
        """
        return {k: getattr(self, k) for k in self._keys() if not k.startswith("_")}
