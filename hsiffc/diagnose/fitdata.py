"""The samples a fit of :mod:`hsiffc.diagnose` works on (:class:`Data`), in a module of their
own so that the fit (:mod:`hsiffc.diagnose.fitting`) and its least-squares pieces
(:mod:`hsiffc.diagnose.effectfit`) both import it and not each other."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Data"]


@dataclass
class Data:
    """Everything a fit needs; arrays (P, S) unless stated.

    The fields (commented in the class body) are the fit-half and held-out step means (DN),
    exposures (ms), relative light rates, validity masks, weights (1/DN^2), acquisition order,
    previous step, light mask, full scale (DN), the frame gap between the two halves and the
    frames averaged in each fit-half sample, and whether the frame differences failed the
    noise model's test.
    """

    y: np.ndarray  # fit-half step means, DN
    y_ho: np.ndarray  # held-out step means, DN
    t: np.ndarray  # (S,) exposure, ms
    r: np.ndarray  # (S,) relative light rate (0 for darks)
    valid: np.ndarray  # fit samples
    valid_ho: np.ndarray  # held-out samples
    w: np.ndarray  # fit weights, 1/DN^2
    order: np.ndarray  # (S,) acquisition order in [-1, 1]
    prev_index: np.ndarray  # (S,) previous step in acquisition order (-1: none)
    light: np.ndarray  # (S,) bool
    full_scale: float
    frame_gap: float  # mean frame index of the held-out half minus that of the fit half
    n_fit: np.ndarray | None = None  # (S,) frames averaged in each fit-half sample
    order_ho: np.ndarray | None = None  # (S,) acquisition order of the held-out frames
    # the frame differences failed the noise model's test: the frames of a step are not
    # exchangeable, and a floor measured on them holds what changes from frame to frame
    frames_differ: bool = False
