"""The pipeline ``hsiffc correct`` applies without ``--pipeline``: built from a calibration
alone, with no training frames."""

from __future__ import annotations

from ..calibrate.product import Calibration
from .ffc import from_calibration
from .pipeline import Pipeline
from .registry import create

__all__ = ["default_pipeline"]


def default_pipeline(calibration, *, threshold_percent: float = 12.0,
                     linearise: bool = False, ffc: str = "model") -> Pipeline:
    """The default correction of a calibration: dark, alpha mask and model-based flat field.

    ``dark`` (the calibration's dark level plus dark current times the exposure), ``mask``
    (``alpha_mask``: alpha per pixel, LEAKAGE above ``threshold_percent``, OUT_OF_DOMAIN and
    the calibration's pixel flags), then ``ffc``: the flat-field method of that name learnt
    from the calibration alone (:func:`hsiffc.stages.ffc.from_calibration`, one of
    :data:`hsiffc.flatfield.FROM_CALIBRATION`). The default, ``"model"``, is ``model_ffc``:
    leakage inversion and the calibration's per-pixel responsivity, so a uniform scene gives
    a uniform frame, DN above dark on the band-mean scale. With ``ffc="none"`` there is no
    flat-field step; ``linearise`` then adds ``linearise`` (the leakage inversion without a
    flat field). The command line checks the combination first
    (:func:`hsiffc.batch.check_ffc`).

    Parameters
    ----------
    calibration : Calibration or path-like
    threshold_percent : float
        Alpha above which a pixel is flagged LEAKAGE.
    linearise : bool
        With ``ffc="none"``: add the leakage inversion.
    ffc : str
        A name of :data:`hsiffc.flatfield.FROM_CALIBRATION`, or ``"none"``.

    Returns
    -------
    Pipeline
        Fitted, ready to transform frames.
    """
    cal = calibration if isinstance(calibration, Calibration) else Calibration.load(calibration)
    steps = [("dark", create("dark", calibration=cal).fit([])),
             ("mask", create("alpha_mask", calibration=cal,
                             threshold_percent=float(threshold_percent)).fit([]))]
    if ffc != "none":
        steps.append(("ffc", from_calibration(ffc, cal)))
    elif linearise:
        steps.append(("linearise", create("linearise", calibration=cal).fit([])))
    return Pipeline(steps)
