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

from collections.abc import Callable
from dataclasses import dataclass

from ..data.params import validate_method
from ..data.sweep import Sweep
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
from ..kernels.pixelfit import STATUS_REASONS
from .product import Calibration
from .samples import PhotonTransfer, Samples, collect_samples, photon_transfer
from .sensor import calibrate_joint, check_design

__all__ = [
    "B_GRID",
    "CALIBRATION_METHODS",
    "DARK_MODELS",
    "LEAKAGE_ACCOUNT",
    "STATUS_REASONS",
    "Calibration",
    "CalibrationMethod",
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



@dataclass(frozen=True)
class CalibrationMethod:
    """A registered calibration method.

    Attributes
    ----------
    summary : str
        What the method fits, in one line.
    fit : callable
        ``fit(sweep, **kwargs) -> Calibration``: the method's own keywords after the sweep.
    reports_progress : bool
        ``fit`` takes ``progress=`` (a callable told the rows done, for a status line).
    """

    summary: str
    fit: Callable[..., Calibration]
    reports_progress: bool = False


#: Registered calibration methods: name -> :class:`CalibrationMethod`.
#:
#: Adding a method: a function ``fit(sweep, **kwargs) -> Calibration`` in its own module of
#: this package, registered here; :func:`calibrate` looks the name up with
#: :func:`~hsiffc.data.params.validate_method` (an unknown name: one line with the valid
#: ones and the closest) and ``hsiffc calibrate --method`` takes its choices from here.
CALIBRATION_METHODS = {
    "joint": CalibrationMethod("one weighted per-pixel fit of responsivity, a, b and the dark "
                               "model over the whole sweep", calibrate_joint,
                               reports_progress=True),
    "paper": CalibrationMethod("the paper's section III.C: k per illumination, a and b from "
                               "the dynamic saturation levels", calibrate_paper),
}
#: Keywords of :func:`calibrate` (method "joint") that give the leakage model's own account of
#: a sweep: each pixel's leakage wherever its fit converged, its dark the intercept of its own
#: fit, no exposure offset, no held-out model choice. What the EMVA 1288 leakage analysis and
#: the paper's reproduction study; a correction uses the default instead.
LEAKAGE_ACCOUNT = {"choose": False, "dark_from": "fit", "exposure_offset_ms": 0.0}
#: The registered names (kept for code that imported them before the registry).
METHODS = tuple(CALIBRATION_METHODS)


def calibrate(sweep: Sweep, *, method: str = "joint", **kwargs) -> Calibration:
    """Calibrate every pixel of ``sweep`` by one of :data:`CALIBRATION_METHODS`.

    Parameters
    ----------
    sweep : Sweep
        Raw frames (N, H, W) in DN with their exposures (ms), kinds (light/dark) and, for
        EMVA 1288 data, photon counts: light steps over a range of exposures, ideally into
        dynamic saturation, and dark steps.
    method : {"joint", "paper"}
        ``"joint"`` (default): one per-pixel fit of responsivity, a, b and the dark model over
        the whole sweep (:func:`calibrate_joint`); ``"paper"``: the paper's section III.C
        from sweeps under several illuminations (:func:`calibrate_paper`).
    **kwargs
        Passed to :func:`calibrate_joint` or :func:`calibrate_paper`.

    Returns
    -------
    Calibration
        Per-pixel (H, W) arrays (``dark_dn`` in DN, ``a_dn_per_ms`` in DN/ms, ``b_per_dn`` in
        1/DN, ``responsivity``, uncertainties, DQ ``flags``), the validity domain and what it
        was fitted on; save it with :meth:`Calibration.save`.

    Raises
    ------
    ParameterError
        Unknown ``method`` (a ValueError; one line naming it, the closest and the valid
        ones).
    DataFormatError
        A sweep the method cannot calibrate (the message says what is missing).

    Examples
    --------
    >>> import numpy as np
    >>> from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
    >>> sensor = MosaicSensor((8, 8), seed=0)                  # a simulated 8 x 8 px sensor
    >>> sweep = sensor.sweep(np.geomspace(2.0, 400.0, 12), "lamp A", n_frames=2, seed=1,
    ...                      irradiance_w_m2=PAPER_LIGHT_W_M2["training"] / 4)
    >>> cal = calibrate(sweep)
    >>> cal.b.shape, cal.fitted_on["fit_status"]
    ((8, 8), {'leakage model fitted': 64})
    >>> truth = sweep.meta["truth"]                              # the simulator's parameters
    >>> bool(np.median(np.abs(cal.dark - truth.dark_dn)) < 1.0)   # DN
    True
    """
    how = validate_method(method, CALIBRATION_METHODS, "calibration method")
    return how.fit(sweep, **kwargs)
