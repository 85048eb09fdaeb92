"""Stage fusion: consecutive stages whose per-pixel work runs as one compiled pass.

A pipeline runs its stages one after the other, and each reads and writes whole frames. For
the front end of a correction, dark subtraction, the alpha mask and the two-point FFC, the
per-pixel work is a few operations on planes that each stage reads again; :class:`Pipeline`
therefore hands such a run of stages to :func:`run_fused`, which does their per-pixel work in
one pass (:func:`hsiffc.leakage.validity.subtract_dark_and_flag`, which with the two-point FFC's
``"paper"`` normalisation also takes the test frame's per-band level of eq. 5, the sums
:func:`hsiffc.data.bandstats.band_reduce` would take, in its order) and then lets every stage finish
its frame as its own ``transform`` would. The result is the same frame, bit for bit, with the
same history (``tests/test_fusion.py`` compares them on simulated and real data), in less time
(the pipeline benchmark times both in turn; ``docs/results/benchmarks.md`` gives the figures).

Only what the stages' own methods compute is computed here: a fused run calls the same
array functions and kernels as the stages (one implementation of each correction).
"""

from __future__ import annotations

import numpy as np

from ..data.dark import subtract_dark
from ..leakage.validity import subtract_dark_and_flag
from .alpha import AlphaMask
from .dark import DarkSubtract
from .ffc import TwoPointFFC

__all__ = ["fusable", "fused_pass", "run_fused"]


def fusable(steps, frame) -> int:
    """How many stages from the start of ``steps`` (a list of ``(name, stage)``) run fused on
    ``frame``: 3 for a dark, an alpha mask (paper alpha) and a two-point FFC of the frame's
    shape; 2 for a dark and an alpha mask followed by anything else; 0 otherwise (the stages
    then run one by one). Only a raw frame (no dark removed, not corrected, not a cube) is
    fused."""
    if len(steps) < 2 or frame.is_cube or frame.dark_removed is not None:
        return 0
    if frame.corrected_by is not None:
        return 0
    (_, dark), (_, mask) = steps[:2]
    if (type(dark), type(mask)) != (DarkSubtract, AlphaMask) or mask.method != "paper":
        return 0
    ffc = steps[2][1] if len(steps) > 2 else None
    if type(ffc) is TwoPointFFC and ffc.is_fitted() and ffc.gain_.shape == frame.data.shape:
        return 3
    return 2  # a two-point FFC of another shape, or not fitted, raises its own error


def fused_pass(steps, frame):
    """The one compiled pass of ``steps`` (a run :func:`fusable` accepted) over ``frame``:
    returns ``(dark plane, its source, signal, alpha, dq, test_mean)``, ``test_mean`` being
    the two-point FFC's eq. (5) level of the frame (None without such an FFC)."""
    (_, dark), (_, mask) = steps[:2]
    ffc = steps[2][1] if len(steps) == 3 else None
    plane, how = dark.dark_for(frame.exposure_ms, frame.data.shape)
    if np.shape(plane) != frame.data.shape:
        subtract_dark(frame.data, plane)  # raises the dark stage's own error
    band_map, n_bands = None, None
    if ffc is not None and ffc.normalisation == "paper":  # eq. (5)'s test level, same pass
        band_map = frame.band_map()
        n_bands = len(ffc.band_flat_mean(band_map))
    signal, alpha, dq, *test_mean = subtract_dark_and_flag(
        frame.data, plane, frame.exposure_ms, mask.calibration_for(frame),
        threshold_percent=float(mask.threshold_percent), dq=frame.dq,
        extra_dq=None if ffc is None else ffc.dq_, band_map=band_map, n_bands=n_bands)
    return plane, how, signal, alpha, dq, (test_mean or [None])[0]


def run_fused(steps, frame, record):
    """Run ``steps``, a run of stages :func:`fusable` accepted for ``frame`` (its first 2 or
    3), on ``frame`` in one pass (:func:`fused_pass`).

    ``record(name, stage, frame)`` is called after each stage with the frame that stage
    returns (the pipeline adds the stage's history entry there) and returns the frame to go
    on with. Returns the frame after the last fused stage."""
    (dark_name, dark), (mask_name, mask) = steps[:2]
    ffc_name, ffc = steps[2] if len(steps) == 3 else (None, None)
    for _, stage in steps:
        stage.check_is_fitted()
    plane, how, signal, alpha, dq, test_mean = fused_pass(steps, frame)
    frame = record(dark_name, dark, frame.dark_subtracted(plane, signal=signal,
                                                          dark_source=how))
    frame = record(mask_name, mask, mask.flagged(frame, alpha, dq))
    if ffc is None:
        return frame
    return record(ffc_name, ffc, ffc.corrected(frame, dq, test_mean))
