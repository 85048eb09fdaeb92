"""A calibration prepared for correcting frames: what the per-frame work reads, made once.

A :class:`~hsiffc.calibrate.Calibration` is plain data (its arrays as fitted and saved). The
hot path of a correction works in single precision and reads one flag plane per pixel; a
:class:`PreparedCalibration` holds exactly that: float32 copies of the leakage parameters, the
calibration's DQ flags (merged, where a pipeline asks for it, with a fixed plane such as a
fitted two-point FFC's flat flags) and the dark line ``d0 + dark current * t``
(:class:`hsiffc.data.dark.DarkLine`). A pipeline makes it once when it is built, fitted or
loaded (:meth:`hsiffc.stages.Pipeline.prepare`) and holds it in its plan.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..data.dark import DarkLine
from ..data.dq import DQ_DTYPE

__all__ = ["PreparedCalibration"]


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class PreparedCalibration:
    """A calibration's planes as the per-frame correction reads them (read-only; shared).

    Made by :meth:`hsiffc.calibrate.Calibration.prepare`; the functions of
    :mod:`hsiffc.leakage.validity` take it wherever they take a calibration (a plain
    calibration is prepared on each call).

    Attributes
    ----------
    calibration : Calibration
        The calibration it was made from (its checks, domain and identity).
    a : (H, W) float32, DN/ms
        Leakage amplitude.
    b : (H, W) float32, 1/DN
        Leakage exponent.
    dark_line : DarkLine
        Dark level and dark current (zeros when the calibration has none), float32.
    flags : (H, W) uint32 or None
        The calibration's pixel flags, OR-ed with :attr:`merged_with` when that is set.
    merged_with : (H, W) uint32 or None
        The fixed plane merged into :attr:`flags` (:meth:`with_flags`), else None.

    Examples
    --------
    >>> from hsiffc.calibrate import Calibration
    >>> cal = Calibration(arrays={k: np.full((1, 2), v) for k, v in
    ...                           (("a_dn_per_ms", 1e-3), ("b_per_dn", 0.01), ("dark_dn", 30.0))},
    ...                   domain={"frame_shape": [1, 2], "bit_depth": 10}, method="paper")
    >>> p = cal.prepare()
    >>> p.a.dtype.name, p.dark_at(5.0).tolist(), p.flags
    ('float32', [[30.0, 30.0]], None)
    """

    calibration: object
    a: np.ndarray
    b: np.ndarray
    dark_line: DarkLine
    flags: np.ndarray | None = None
    merged_with: np.ndarray | None = None

    @classmethod
    def of(cls, calibration) -> "PreparedCalibration":
        """Prepare ``calibration`` (a :class:`~hsiffc.calibrate.Calibration`)."""
        arr = calibration.arrays
        flags = arr.get("flags")
        return cls(calibration=calibration,
                   a=_read_only(np.asarray(arr["a_dn_per_ms"], np.float32)),
                   b=_read_only(np.asarray(arr["b_per_dn"], np.float32)),
                   dark_line=DarkLine(arr["dark_dn"], calibration.dark_current),
                   flags=None if flags is None else _read_only(np.asarray(flags, DQ_DTYPE)))

    def __repr__(self) -> str:
        merged = ", flags merged with a fixed plane" if self.merged_with is not None else ""
        return f"<PreparedCalibration of {self.calibration.identity}{merged}>"

    def prepare(self) -> "PreparedCalibration":
        """Itself (already prepared): code that takes either form calls ``prepare()``."""
        return self

    def with_flags(self, other: np.ndarray) -> "PreparedCalibration":
        """This prepared calibration with ``other`` (an (H, W) uint32 plane that does not
        change: a fitted two-point FFC's flat flags) merged into :attr:`flags`, so that a
        fused front end reads one flag plane instead of two
        (:func:`hsiffc.leakage.validity.subtract_dark_and_flag`).

        Raises
        ------
        ValueError
            ``other`` is writable (it could change under the merged plane), not uint32 or
            not of the calibration's frame shape.
        """
        if (other.flags.writeable or other.dtype != DQ_DTYPE
                or other.shape != self.calibration.frame_shape):
            raise ValueError(f"with_flags needs a read-only uint32 plane of shape "
                             f"{self.calibration.frame_shape} (one that cannot change under "
                             f"the merged plane), got {other.dtype} {other.shape}"
                             + (", writable" if other.flags.writeable else ""))
        base = self.flags if self.merged_with is None else np.asarray(
            self.calibration.arrays["flags"], DQ_DTYPE)
        merged = other.copy() if base is None else np.bitwise_or(base, other)
        merged.flags.writeable = False
        return replace(self, flags=merged, merged_with=other)

    def dark_at(self, exposure_ms: float) -> np.ndarray:
        """The calibrated dark (DN, float32, (H, W), read-only) at ``exposure_ms``
        (:meth:`hsiffc.data.dark.DarkLine.at`)."""
        return self.dark_line.at(exposure_ms)

    # -- what the checks read: the calibration's ----------------------------------------------
    @property
    def domain(self) -> dict:
        """The calibration's validity domain."""
        return self.calibration.domain

    @property
    def frame_shape(self) -> tuple[int, int]:
        """(H, W) of the calibration."""
        return self.calibration.frame_shape

    @property
    def identity(self) -> str:
        """The calibration's identity."""
        return self.calibration.identity

    def in_domain(self, exposure_ms):
        """:meth:`hsiffc.calibrate.Calibration.in_domain`."""
        return self.calibration.in_domain(exposure_ms)

    def check_compatible(self, data=None, **facts) -> None:
        """:meth:`hsiffc.calibrate.Calibration.check_compatible`."""
        self.calibration.check_compatible(data, **facts)

    def check_frame(self, frame, what: str = "the frame") -> None:
        """:meth:`hsiffc.calibrate.Calibration.check_frame`."""
        self.calibration.check_frame(frame, what)
