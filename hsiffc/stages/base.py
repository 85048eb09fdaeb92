"""The stage contract (scikit-learn style) and the helper that checks it.

A stage's ``__init__`` takes keyword-only parameters and stores them unchanged. ``fit(frames)``
validates, learns, stores fitted attributes whose names end in ``_`` and returns ``self``.
``transform(frame)`` checks it is fitted, never mutates its input and returns a new Frame.
Fitted state is saved without pickle: ``get_state()`` returns a JSON-safe dict and a dict of
arrays; ``set_state(json, arrays)`` restores them. ``prepare()`` makes, once, what a fitted
stage's per-frame work reads (float32 calibration planes, a dark line...): a :class:`Prepared`
that a :class:`~hsiffc.stages.Pipeline` builds when it is built, fitted or loaded and holds in
its plan; ``transform(frame)`` alone prepares on each call.
"""

from __future__ import annotations

import copy
import functools
import inspect
import json
from pathlib import Path

import numpy as np

from ..errors import HsiffcError, ParameterError
from ..data.params import check_params, short_repr, unknown_parameters


class NotFittedError(HsiffcError, RuntimeError):
    """A stage was used before ``fit``."""


@functools.cache
def _init_parameters(init) -> tuple[str, ...]:
    """The keyword parameters of a stage class's ``__init__`` (read once per class: a
    pipeline records every stage's parameters for every frame)."""
    sig = inspect.signature(init)
    return tuple(p.name for p in sig.parameters.values()
                 if p.name != "self" and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD))


class Prepared:
    """A fitted stage made ready for frames: what its per-frame work reads, made once
    (:meth:`Stage.prepare`). This base holds nothing more than the stage; stages with
    something to prepare return a subclass (e.g. :class:`hsiffc.stages.dark.PreparedDark`).

    Attributes
    ----------
    stage : Stage
        The stage it was made from.
    """

    __slots__ = ("stage",)

    def __init__(self, stage: "Stage"):
        self.stage = stage

    def __repr__(self) -> str:
        return f"<{type(self).__name__} of {type(self.stage).__name__}>"

    def transform(self, frame):
        """The stage's transform of ``frame`` (a new Frame)."""
        return self.stage.transform(frame)


class PreparedWithCalibration(Prepared):
    """A :class:`Prepared` that also holds the stage's calibration, prepared
    (:meth:`hsiffc.calibrate.Calibration.prepare`; None where the stage has none).

    Attributes
    ----------
    stage : Stage
    calibration : PreparedCalibration or None
    """

    __slots__ = ("calibration",)

    def __init__(self, stage: "Stage", calibration):
        super().__init__(stage)
        self.calibration = calibration


class Stage:
    """Base class of every pipeline stage."""

    #: registered name (set by the registry for built-ins; plugins set it themselves)
    name: str = ""
    #: True for filters with nothing to learn
    stateless: bool = False
    #: frame states (:data:`hsiffc.data.frame.STATES`) the stage needs, adds and takes away; a
    #: :class:`~hsiffc.stages.Pipeline` whose order breaks them fails when it is built
    requires: frozenset = frozenset()
    produces: frozenset = frozenset()
    removes: frozenset = frozenset()
    #: declared parameters (name -> :class:`hsiffc.data.params.Param`), checked by
    #: :meth:`validate_params` at fit and when a pipeline is built or loaded
    param_spec: dict = {}
    #: the part this stage plays in a fused front end (:class:`hsiffc.stages.fusion.FusedFrontEnd`:
    #: ``"dark"``, ``"alpha_mask"``, ``"two_point_ffc"``), None for a stage that does not
    #: fuse. A subclass that changes what ``transform`` computes sets it to None.
    fuses_as: str | None = None
    #: what the stage computes in the terms of the GPU pipeline (:func:`hsiffc.gpu.pipeline.plan`:
    #: ``"dark"``, ``"alpha_mask"``, ``"model_ffc"``, ``"two_point_ffc"``, ``"reconstruct"``),
    #: None for a stage the GPU does not run. A subclass that changes what ``transform``
    #: computes sets it to None.
    gpu_as: str | None = None

    # -- parameters ----------------------------------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        return list(_init_parameters(cls.__init__))

    def get_params(self) -> dict:
        """Constructor parameters and their current values."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params) -> "Stage":
        """Set constructor parameters by name; returns ``self`` (checked at ``fit``)."""
        unknown_parameters(f"stage {self.name or type(self).__name__!r}", params,
                           self._param_names())  # a ParameterError: closest and valid names
        for key, value in params.items():
            setattr(self, key, value)
        return self

    def json_params(self) -> dict:
        """The parameters as JSON (what a pipeline file and a frame's history record): paths
        become strings, a calibration its :meth:`~hsiffc.calibrate.Calibration.reference`
        (identity and path).

        Raises
        ------
        ParameterError
            A value that cannot be saved (neither a path nor a plain value).
        """
        from ..calibrate.product import Calibration

        out = {}
        for key, value in self.get_params().items():
            if key == "calibration" and value is not None:
                value = self.calibration_product()  # a path is recorded by identity
            if isinstance(value, Calibration):
                value = value.reference()
            elif isinstance(value, Path):
                value = str(value)
            elif isinstance(value, np.generic):
                value = value.item()
            elif not isinstance(value, (str, int, float, bool, type(None), list, dict)):
                raise ParameterError(f"{self.name}: parameter {key}={value!r} cannot be saved; "
                                     "give a path or a plain value")
            out[key] = value
        return out

    def __repr__(self):  # one line: arrays by shape, a calibration by its key figures
        args = ", ".join(f"{k}={short_repr(v)}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    def validate_params(self) -> None:
        """Raise :class:`hsiffc.errors.ParameterError` (one line: parameter, value, what is
        valid) when a parameter breaks its declaration in :attr:`param_spec`."""
        check_params(self.name or type(self).__name__, self.param_spec, self.get_params())

    def calibration_product(self):
        """The :class:`~hsiffc.calibrate.Calibration` of the ``calibration`` parameter (None if
        unset). A path is read on each call: a :class:`~hsiffc.stages.Pipeline` reads every
        calibration file once, when it is built, and gives its stages the calibration it read
        (:meth:`hsiffc.stages.Pipeline.read_calibrations`); a stage used alone reads its file
        at ``fit`` and at every ``prepare`` (give it a Calibration to read it once)."""
        from ..calibrate.product import Calibration

        return Calibration.resolve(getattr(self, "calibration", None))

    def require_calibration(self):
        """:meth:`calibration_product`, or a ParameterError saying the stage needs one."""
        cal = self.calibration_product()
        if cal is None:
            from .common import GIVE_CALIBRATION

            raise ParameterError(f"{self.name or type(self).__name__} needs a calibration (a "
                                 f"file from 'hsiffc calibrate'): {GIVE_CALIBRATION}")
        return cal

    # -- fitting -------------------------------------------------------------------------------
    def fit(self, frames) -> "Stage":
        """Learn from training frames (a list of :class:`hsiffc.data.frame.Frame`). Stateless stages
        only check their parameters and mark themselves fitted."""
        self.validate_params()
        self.fitted_ = True
        return self

    def is_fitted(self) -> bool:
        """Whether :meth:`fit` has run."""
        return self.stateless or bool(getattr(self, "fitted_", False))

    def check_is_fitted(self) -> None:
        """Raise :class:`NotFittedError` unless :meth:`fit` has run."""
        if not self.is_fitted():
            raise NotFittedError(f"{type(self).__name__} is not fitted yet; call fit(frames) "
                                 "first (or load a fitted pipeline)")

    def transform(self, frame):  # pragma: no cover - abstract
        """A new, corrected Frame (the input is not modified)."""
        raise NotImplementedError

    def prepare(self) -> Prepared:
        """What the per-frame work of this fitted stage reads, made now (a :class:`Prepared`;
        this base: the stage itself, nothing to make). A pipeline calls it once when it is
        built, fitted or loaded and holds the result in its plan.

        Raises
        ------
        NotFittedError
            The stage is not fitted.
        """
        self.check_is_fitted()
        return Prepared(self)

    # -- state without pickle ------------------------------------------------------------------
    def get_state(self) -> tuple[dict, dict]:
        """(JSON-safe dict, dict of arrays) of the fitted attributes (names ending in ``_``)."""
        js, arrays = {}, {}
        for key, value in vars(self).items():
            if not key.endswith("_") or key.startswith("_"):
                continue
            if isinstance(value, np.ndarray):
                arrays[key] = value
            else:
                json.dumps(value)  # raises TypeError for state that cannot be saved safely
                js[key] = value
        return js, arrays

    def set_state(self, js: dict, arrays: dict) -> "Stage":
        """Restore the fitted state written by :meth:`get_state` (JSON part and arrays); returns ``self``."""
        for key, value in {**js, **arrays}.items():
            if not key.endswith("_"):
                raise ValueError(f"state key {key!r} is not a fitted attribute")
            setattr(self, key, value)
        return self

    def clone(self) -> "Stage":
        """An unfitted copy with the same parameters."""
        return type(self)(**copy.deepcopy(self.get_params()))
