"""Whether a sequence of stages makes sense: each stage's ``requires`` against what the stages
before it ``produce`` and ``remove`` (the frame states of :data:`hsiffc.data.frame.STATES`)."""

from __future__ import annotations

from ..errors import ParameterError
from ..data.frame import INPUT_STATE

WORDS = {"mosaic": "2-D mosaic frames", "cube": "reconstructed cubes",
         "raw": "raw frames (no dark removed)", "dark_subtracted": "dark-subtracted frames",
         "response": "the uncorrected sensor response", "alpha": "an alpha plane"}
HINTS = {"dark_subtracted": "put a 'dark' step before it",
         "alpha": "put an 'alpha_mask' step before it",
         "mosaic": "it must come before reconstruction"}


def check_order(steps, start=INPUT_STATE) -> None:
    """Raise :class:`~hsiffc.errors.ParameterError` naming two steps when a step needs a frame
    state that an earlier step took away or that only a later step gives.

    Parameters
    ----------
    steps : list of (name, Stage)
    start : set of str
        States of the pipeline's input (frames read from files: raw 2-D mosaics).
    """
    state = set(start)
    removed_by: dict[str, str] = {}
    for i, (name, stage) in enumerate(steps):
        label = f"step {name!r} ({stage.name or type(stage).__name__})"
        for need in sorted(set(stage.requires) - state):
            what = WORDS.get(need, need)
            if need in removed_by:
                raise ParameterError(f"{label} needs {what}, but step {removed_by[need]!r} "
                                     f"before it takes that away: put {name!r} before "
                                     f"{removed_by[need]!r}")
            later = next((n for n, s in steps[i + 1:] if need in s.produces), None)
            if later is not None:
                raise ParameterError(f"{label} needs {what}, which step {later!r} only gives "
                                     f"after it: put {later!r} before {name!r}")
            raise ParameterError(f"{label} needs {what} and no step before it gives them"
                                 + (f": {HINTS[need]}" if need in HINTS else ""))
        state -= set(stage.removes)
        state |= set(stage.produces)
        for gone in stage.removes:
            removed_by[gone] = name
        for new in stage.produces:
            removed_by.pop(new, None)
