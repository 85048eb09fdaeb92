"""Per-pixel calibration of the leakage model from exposure sweeps.

Two methods:

- ``"joint"`` (beyond the paper; :mod:`hsiffc.calibrate.sensor`): one weighted least-squares fit
  per pixel of the responsivity (light rate per unit of the step's relative light rate), a, b
  and the dark level, with the dark current measured from the dark frames, using every valid
  sample of one sweep whose light may change from step to step (EMVA 1288 photons / exposure).
  A numba kernel fits each pixel with a fallback to the linear model; every pixel carries its
  fit status, residual RMS (DN) and parameter uncertainties.
- ``"paper"`` (section III.C; :mod:`hsiffc.calibrate.paper`): k per illumination from the
  linear part of its exposure sweep, a and b from the dynamic saturation levels reached under
  several illuminations, the dark level (the paper's constant c) from the shortest exposure.

Both leave out and count clipped samples (any frame of the step at full scale) and samples at or
above the full-well level.

The per-pixel fit is public for other analyses (``hsiffc.diagnose``): :func:`fit_pixels`,
:func:`initial_guess`, :func:`model_and_jacobian`, :func:`predict`, :func:`residuals`.
"""

from __future__ import annotations

from ..sweep import Sweep
from .joint import (
    B_GRID,
    DARK_MODELS,
    JointFit,
    fit_pixels,
    initial_guess,
    model_and_jacobian,
    predict,
    residuals,
)
from .paper import calibrate_paper
from .pixelfit import STATUS_REASONS
from .product import Calibration
from .samples import PhotonTransfer, Samples, collect_samples, photon_transfer
from .sensor import calibrate_joint, check_design

__all__ = [
    "B_GRID",
    "DARK_MODELS",
    "STATUS_REASONS",
    "Calibration",
    "JointFit",
    "PhotonTransfer",
    "Samples",
    "calibrate",
    "calibrate_joint",
    "calibrate_paper",
    "check_design",
    "collect_samples",
    "fit_pixels",
    "initial_guess",
    "model_and_jacobian",
    "photon_transfer",
    "predict",
    "residuals",
    "sample_weights",
]

METHODS = ("joint", "paper")


def calibrate(sweep: Sweep, *, method: str = "joint", **kwargs) -> Calibration:
    """Calibrate every pixel of ``sweep``; ``method`` is ``"joint"`` or ``"paper"``.

    Keyword arguments go to :func:`calibrate_joint` or :func:`calibrate_paper`.
    """
    if method == "joint":
        return calibrate_joint(sweep, **kwargs)
    if method == "paper":
        return calibrate_paper(sweep, **kwargs)
    raise ValueError(f"unknown calibration method {method!r}; choose one of {METHODS}")
