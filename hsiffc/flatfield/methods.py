"""The flat-field correction family: one registry, one signature, one result type.

Every registered method corrects one raw frame with what it learnt from the training data
(its *flat*) and returns a :class:`Corrected`; :func:`correct_flat` picks the method by name.
The array functions of each method (:mod:`.two_point`, :mod:`.polynomial`, :mod:`.model_based`)
stay as they are; the entries here adapt them to the common signature.

Examples
--------
>>> import numpy as np
>>> from hsiffc.flatfield.two_point import two_point_fit
>>> dark = np.zeros((2, 2), np.float32)
>>> flat = two_point_fit(np.array([[90.0, 110.0], [100.0, 100.0]]))
>>> res = correct_flat("two_point", np.full((2, 2), 50.0), dark, flat, normalisation="mean_gain")
>>> [round(v, 2) for v in res.out.ravel().tolist()], int(res.dq.max()), res.alpha
([55.56, 45.45, 50.0, 50.0], 0, None)
>>> correct_flat("two-point", np.ones((2, 2)), dark, flat)
Traceback (most recent call last):
...
hsiffc.errors.ParameterError: unknown flat-field method 'two-point'; did you mean 'two_point'? valid: two_point, polynomial, model
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from ..data.dark import subtract_dark
from ..data.dq import DQ_DTYPE
from ..data.params import LiveChoices, validate_method
from ..errors import ParameterError
from .model_based import ModelFlat, model_ffc_apply, model_flat_of
from .polynomial import PolynomialFlat, polynomial_apply
from .two_point import FlatField, two_point_correct_with

__all__ = ["FFC_METHODS", "FROM_CALIBRATION", "Corrected", "FFCMethod", "correct_flat"]


class Corrected(NamedTuple):
    """What every flat-field method returns.

    Attributes
    ----------
    out : (H, W) float32, DN
        The corrected frame (finite everywhere; 0 DN where flagged NONFINITE).
    dq : (H, W) uint32
        The frame's DQ (if given), the flat's own flags and the method's.
    alpha : (H, W) float32, percent, or None
        The model alpha of each response for a method that computes it ("model"); None for
        the others.
    """

    out: np.ndarray
    dq: np.ndarray
    alpha: np.ndarray | None


@dataclass(frozen=True)
class FFCMethod:
    """A registered flat-field correction method.

    Attributes
    ----------
    summary : str
        What the method does, in one line.
    correct : callable
        ``correct(raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None,
        calibration=None, **options) -> Corrected``: ``raw`` the frame's raw response (H, W)
        in DN, ``dark`` the (H, W) dark under it in DN, ``flat`` what the method learnt
        (``learnt``), ``dq`` the frame's DQ, ``band_map`` its band of every pixel,
        ``exposure_ms`` its exposure, ``calibration`` the calibration of the pipeline (or
        None); ``options`` the method's own settings.
    learnt : type
        The type of ``flat`` the method applies (how to make it: its docstring).
    stage : str
        The registered stage that learns and applies the method in a pipeline
        (:mod:`hsiffc.stages`); ``"flat_field"``, the default, is the stage that runs any
        method of this registry with a ``learn``.
    learn : callable or None
        ``learn(calibration) -> learnt``: the method learnt from a calibration alone, without
        training frames; a method that has one is a choice of ``hsiffc correct --ffc``
        (:data:`FROM_CALIBRATION`). None: it learns from training frames only (its stage's
        ``fit``).
    state_schema : mapping
        Its stage's fitted state as a pipeline file stores it: field name -> JSON kind or
        array spec (:func:`hsiffc.data.products.check_product`). For the ``"flat_field"``
        stage: one array per field of ``learnt``, named ``<field>_``.
    """

    summary: str
    correct: Callable[..., Corrected]
    learnt: type
    stage: str = "flat_field"
    learn: Callable[[Any], Any] | None = None
    state_schema: Mapping = field(default_factory=dict)


def _merged(dq, *planes):
    """``dq`` (a new plane the method made) with the bits of ``planes`` (None: none) merged in."""
    for plane in planes:
        if plane is not None:
            dq |= np.asarray(plane, DQ_DTYPE)
    return dq


def _two_point(raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None, calibration=None,
               normalisation: str = "paper") -> Corrected:
    """The paper's eq. (5) (:func:`~hsiffc.flatfield.two_point.two_point_correct_with`);
    ``normalisation``: "paper" or "mean_gain"."""
    out, out_dq = two_point_correct_with(raw, dark, flat, normalisation=normalisation,
                                         band_map=band_map, dq=dq)
    return Corrected(out, out_dq, None)


def _polynomial(raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None, calibration=None,
                margin: float = 0.05) -> Corrected:
    """Per-pixel polynomials on ``raw - dark``
    (:func:`~hsiffc.flatfield.polynomial.polynomial_apply`); ``margin``: relative slack of
    the trained range."""
    out, out_dq = polynomial_apply(subtract_dark(raw, dark), flat, margin=margin)
    return Corrected(out, _merged(out_dq, dq), None)


def _model(raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None, calibration=None,
           a=None, b=None, **options) -> Corrected:
    """The leakage model inverted per pixel, times the responsivity factor
    (:func:`~hsiffc.flatfield.model_based.model_ffc_apply`); ``a``, ``b``: the calibration's
    leakage amplitude (DN/ms) and exponent (1/DN), required (default: ``calibration``'s);
    ``options``: the keywords of ``model_ffc_apply``."""
    if calibration is not None:
        a = calibration.a if a is None else a
        b = calibration.b if b is None else b
    missing = [name for name, v in (("exposure_ms", exposure_ms), ("a", a), ("b", b))
               if v is None]
    if missing:
        raise ParameterError(f"flat-field method 'model' needs {'=, '.join(missing)}= (the "
                             "frame's exposure in ms and the calibration's leakage a and b)")
    out, out_dq, alpha = model_ffc_apply(raw, exposure_ms, a, b, dark, flat.gain,
                                         gain_sweep=flat.gain_sweep, **options)
    return Corrected(out, _merged(out_dq, flat.dq, dq), alpha)


_DQ = ("u", ("H", "W"))
_PLANE = ("f", ("H", "W"))

#: Registered flat-field correction methods: name -> :class:`FFCMethod`.
#:
#: Adding a method: write its array functions in a module of this package (what it learnt: a
#: frozen dataclass of arrays; how to learn it from a calibration, ``learn``; how to apply it),
#: an adapter with the signature of :attr:`FFCMethod.correct` that returns a
#: :class:`Corrected`, and register it here. That is all the dispatch there is:
#: :func:`correct_flat` takes its name (an unknown name is one line listing these), the
#: ``flat_field`` stage (:class:`hsiffc.stages.ffc.FlatFieldFFC`) runs it in a pipeline and
#: ``hsiffc correct --ffc NAME`` offers it when it has a ``learn``. A method that learns from
#: training frames in its own way gets its own stage in :mod:`hsiffc.stages` (``stage``).
FFC_METHODS = {
    "two_point": FFCMethod(
        "the paper's eq. (5): per-pixel gain from one dark-subtracted flat", _two_point,
        FlatField, stage="two_point_ffc",
        state_schema={"fitted_": "bool", "selected_ms_": "numbers", "alpha_table_": "dict|null",
                      "gain_": _PLANE,
                      # one value per band; format 1 stored it per pixel
                      "flat_mean_": ("f", [("selected_ms_",), ("H", "W")]), "dq_": _DQ}),
    "polynomial": FFCMethod(
        "per-pixel polynomial from flats at several levels to the band mean", _polynomial,
        PolynomialFlat, stage="polynomial_ffc",
        state_schema={"fitted_": "bool", "n_levels_": "int", "coef_": ("f", ("K", "H", "W")),
                      "scale_": _PLANE, "x_min_": _PLANE, "x_max_": _PLANE, "dq_": _DQ}),
    "model": FFCMethod(
        "the calibrated leakage model inverted per pixel, times the relative responsivity",
        _model, ModelFlat, stage="model_ffc", learn=model_flat_of,
        state_schema={"fitted_": "bool", "uncertainty_": "any", "gain_": _PLANE,
                      "gain_sweep_": _PLANE, "sigma_ln_gain_": _PLANE,
                      "flat_weight_": _PLANE, "dq_": _DQ}),
}

#: The methods learnt from a calibration alone (those with a ``learn``), read from
#: :data:`FFC_METHODS` whenever they are looked at: the flat-field choices of the pipeline
#: ``hsiffc correct`` builds without ``--pipeline``.
FROM_CALIBRATION = LiveChoices(lambda: [n for n, m in FFC_METHODS.items() if m.learn is not None])


def correct_flat(method: str, raw, dark, flat, *, dq=None, band_map=None, exposure_ms=None,
                 calibration=None, **options) -> Corrected:
    """Correct one frame by one of :data:`FFC_METHODS`.

    Parameters
    ----------
    method : str
        ``"two_point"``, ``"polynomial"`` or ``"model"``.
    raw : (H, W) array_like, DN
        The frame's raw response.
    dark : (H, W) array_like, DN
        The dark under it.
    flat : FlatField, PolynomialFlat or ModelFlat
        What the method learnt (:func:`~hsiffc.flatfield.two_point.two_point_fit`,
        :func:`~hsiffc.flatfield.polynomial.polynomial_fit`,
        :func:`~hsiffc.flatfield.model_based.model_flat_fit`).
    dq : (H, W) uint32, optional
        The frame's DQ; its bits are kept in the result's.
    band_map : (H, W) int, optional
        Band of every pixel ("two_point" takes its means per band).
    exposure_ms : float, optional
        The frame's exposure (ms); "model" needs it.
    calibration : Calibration, optional
        The pipeline's calibration ("model" takes its ``a`` and ``b`` where not given).
    **options
        The method's own settings ("two_point": ``normalisation``; "polynomial":
        ``margin``; "model": ``a`` and ``b`` (required) and the keywords of
        :func:`~hsiffc.flatfield.model_based.model_ffc_apply`).

    Returns
    -------
    Corrected
        ``(out, dq, alpha)``; ``alpha`` is None except for "model".

    Raises
    ------
    ParameterError
        Unknown ``method``: one line with the closest and the valid names.
    """
    how = validate_method(method, FFC_METHODS, "flat-field method")
    if not isinstance(flat, how.learnt):
        raise ParameterError(f"flat-field method {method!r}: flat= must be a "
                             f"{how.learnt.__name__} (what the method learnt), got "
                             f"{type(flat).__name__}")
    return how.correct(raw, dark, flat, dq=dq, band_map=band_map, exposure_ms=exposure_ms,
                       calibration=calibration, **options)
