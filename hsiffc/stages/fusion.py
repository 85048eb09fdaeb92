"""The fused front end: a dark, an alpha mask and a two-point FFC whose per-pixel work runs as
one compiled pass.

A pipeline runs its stages one after the other, and each reads and writes whole frames. For
the front end of a correction, dark subtraction, the alpha mask and the two-point FFC, the
per-pixel work is a few operations on planes that each stage reads again. Stages say which
part of such a front end they can be (:attr:`hsiffc.stages.base.Stage.fuses_as`: ``"dark"``,
``"alpha_mask"`` with the paper's alpha, ``"two_point_ffc"``); where a pipeline's steps line up
so, :meth:`hsiffc.stages.Pipeline.prepare` puts a :class:`FusedFrontEnd` in its plan (it shows
in the pipeline's ``repr``). On a raw frame it does the stages' per-pixel work in one pass
(:func:`hsiffc.leakage.validity.subtract_dark_and_flag`, which with the two-point FFC's
``"paper"`` normalisation also takes the test frame's per-band level of eq. 5, the sums
:func:`hsiffc.spectral.bandstats.band_reduce` would take, in its order) and then lets every stage
finish its frame as its own ``transform`` would. The result is the same frame, bit for bit,
with the same history (``tests/kernels/test_fusion.py`` compares them on simulated and real data).

Only what the stages' own methods compute is computed here: a fused run calls the same
array functions and kernels as the stages (one implementation of each correction).
"""

from __future__ import annotations

import numpy as np

from ..data.dark import subtract_dark
from ..data.dq import DQ_DTYPE

__all__ = ["FusedFrontEnd", "front_end_length", "fusable", "fused_pass"]

#: the parts of a front end, in their order
ROLES = ("dark", "alpha_mask", "two_point_ffc")


def front_end_length(steps) -> int:
    """How many stages from the start of ``steps`` (a list of ``(name, stage)``) make a front
    end by what they declare (``fuses_as``): 3 (dark, alpha mask, two-point FFC), 2 (dark and
    alpha mask) or 0."""
    roles = tuple(getattr(stage, "fuses_as", None) for _, stage in steps[:3])
    if roles[:2] != ROLES[:2]:
        return 0
    return 3 if roles == ROLES else 2


def fusable(steps, frame) -> int:
    """How many stages from the start of ``steps`` run fused on ``frame``: 3 for a dark, an
    alpha mask (paper alpha) and a fitted two-point FFC of the frame's shape; 2 for a dark and
    an alpha mask followed by anything else; 0 otherwise (the stages then run one by one).
    Only a raw frame (no dark removed, not corrected, not a cube) is fused."""
    n = front_end_length(steps)
    if n == 0 or frame.is_cube or frame.dark_removed is not None:
        return 0
    if frame.corrected_by is not None:
        return 0
    ffc = steps[2][1] if n == 3 else None
    if ffc is not None and ffc.is_fitted() and ffc.gain_.shape == frame.data.shape:
        return 3
    return 2  # a two-point FFC of another shape, or not fitted, raises its own error


class FusedFrontEnd:
    """A dark, an alpha mask and (optionally) a two-point FFC of a fitted pipeline, run as one
    pass on raw frames (see the module); made by :meth:`hsiffc.stages.Pipeline.prepare`.

    Parameters
    ----------
    steps : list of (name, Stage, Prepared)
        The 2 or 3 fitted steps (:func:`front_end_length`) with their prepared state
        (:meth:`hsiffc.stages.base.Stage.prepare`).

    Attributes
    ----------
    steps : tuple of (name, Stage, Prepared)
    calibration : PreparedCalibration
        The alpha mask's calibration, prepared.
    calibration_with_flat : PreparedCalibration or None
        The same with the two-point FFC's flat flags merged into its flag plane, so the pass
        reads one plane for both (:meth:`~hsiffc.calibrate.prepared.PreparedCalibration.with_flags`);
        made when the FFC's ``dq_`` is fixed (read-only, as fitted or loaded) and the
        calibration has flags; None otherwise (the flat flags are then read as their own plane,
        frame by frame).
    """

    def __init__(self, steps):
        self.steps = tuple(steps)
        if len(self.steps) not in (2, 3) or front_end_length(
                [(n, s) for n, s, _ in self.steps]) != len(self.steps):
            raise ValueError("a fused front end is a dark, an alpha mask (paper alpha) and "
                             "optionally a two-point FFC, in this order")
        self.calibration = self.steps[1][2].calibration
        self.calibration_with_flat = None
        if len(self.steps) == 3:
            flat = self.steps[2][1].dq_
            cal = self.calibration
            if (isinstance(flat, np.ndarray) and not flat.flags.writeable
                    and flat.dtype == DQ_DTYPE and flat.shape == cal.frame_shape
                    and cal.flags is not None):
                self.calibration_with_flat = cal.with_flags(flat)

    @classmethod
    def starting(cls, prepared) -> "FusedFrontEnd | None":
        """The front end at the start of ``prepared`` (a list of ``(name, stage, Prepared)``),
        or None where its steps do not make one."""
        n = front_end_length([(name, stage) for name, stage, _ in prepared[:3]])
        return cls(prepared[:n]) if n else None

    def __repr__(self) -> str:
        return f"FusedFrontEnd({' + '.join(name for name, _, _ in self.steps)})"

    def accepts(self, frame) -> int:
        """How many of its stages run fused on ``frame`` (:func:`fusable`: 3, 2 or 0)."""
        return fusable([(name, stage) for name, stage, _ in self.steps], frame)

    def fused_pass(self, frame, n: int):
        """The one compiled pass of the first ``n`` (2 or 3, :meth:`accepts`) stages over
        ``frame``: returns ``(dark plane, its source, signal, alpha, dq, test_mean)``,
        ``test_mean`` being the two-point FFC's eq. (5) level of the frame (None without
        the FFC)."""
        from ..leakage.validity import subtract_dark_and_flag  # compiled: imported when run

        (_, _, dark), (_, mask, _) = self.steps[:2]
        ffc = self.steps[2][1] if n == 3 else None
        plane, how = dark.dark_for(frame.exposure_ms, frame.data.shape)
        if np.shape(plane) != frame.data.shape:
            subtract_dark(frame.data, plane)  # raises the dark stage's own error
        self.calibration.check_frame(frame)
        cal, extra_dq, band_map, n_bands = self.calibration, None, None, None
        if ffc is not None:
            if self.calibration_with_flat is not None:
                cal = self.calibration_with_flat
            else:
                extra_dq = ffc.dq_
            if ffc.normalisation == "paper":  # eq. (5)'s test level, same pass
                band_map = frame.band_map()
                n_bands = len(ffc.band_flat_mean(band_map))
        signal, alpha, dq, test_mean = subtract_dark_and_flag(
            frame.data, plane, frame.exposure_ms, cal,
            threshold_percent=float(mask.threshold_percent), dq=frame.dq, extra_dq=extra_dq,
            band_map=band_map, n_bands=n_bands)
        return plane, how, signal, alpha, dq, test_mean

    def run(self, frame, record, *, fuse: bool = True):
        """Run its stages on ``frame``: the first :meth:`accepts` of them in one pass, the
        others each by its prepared ``transform`` (all of them so with ``fuse=False``).

        ``record(name, stage, frame)`` is called after each stage with the frame that stage
        returns (the pipeline adds the stage's history entry there) and returns the frame to
        go on with. Returns the frame after the last stage."""
        n = self.accepts(frame) if fuse else 0
        if n:
            (dark_name, dark, _), (mask_name, mask, _) = self.steps[:2]
            plane, how, signal, alpha, dq, test_mean = self.fused_pass(frame, n)
            frame = record(dark_name, dark, frame.dark_subtracted(plane, signal=signal,
                                                                  dark_source=how))
            frame = record(mask_name, mask, mask.flagged(frame, alpha, dq))
            if n == 3:
                ffc_name, ffc, _ = self.steps[2]
                frame = record(ffc_name, ffc, ffc.corrected(frame, dq, test_mean))
        for name, stage, prepared in self.steps[n:]:
            frame = record(name, stage, prepared.transform(frame))
        return frame


def fused_pass(steps, frame):
    """:meth:`FusedFrontEnd.fused_pass` of the fitted ``steps`` (a list of ``(name, stage)``
    that :func:`fusable` accepts for ``frame``), prepared now."""
    n = fusable(steps, frame)
    if not n:
        raise ValueError("these steps do not run fused on this frame (see fusable)")
    front = FusedFrontEnd.starting([(name, stage, stage.prepare()) for name, stage in steps[:n]])
    return front.fused_pass(frame, n)
