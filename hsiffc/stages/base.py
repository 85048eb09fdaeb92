"""The stage contract (scikit-learn style) and the helper that checks it.

A stage's ``__init__`` takes keyword-only parameters and stores them unchanged. ``fit(frames)``
validates, learns, stores fitted attributes whose names end in ``_`` and returns ``self``.
``transform(frame)`` checks it is fitted, never mutates its input and returns a new Frame.
Fitted state is saved without pickle: ``get_state()`` returns a JSON-safe dict and a dict of
arrays; ``set_state(json, arrays)`` restores them.
"""

from __future__ import annotations

import copy
import inspect
import json

import numpy as np

from ..errors import HsiffcError


class NotFittedError(HsiffcError, RuntimeError):
    """A stage was used before ``fit``."""


class Stage:
    """Base class of every pipeline stage."""

    #: registered name (set by the registry for built-ins; plugins set it themselves)
    name: str = ""
    #: True for filters with nothing to learn
    stateless: bool = False

    # -- parameters ----------------------------------------------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values()
                if p.name != "self" and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]

    def get_params(self) -> dict:
        """Constructor parameters and their current values."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params) -> "Stage":
        valid = self._param_names()
        for key, value in params.items():
            if key not in valid:
                raise ValueError(f"{type(self).__name__} has no parameter {key!r}; valid: {valid}")
            setattr(self, key, value)
        return self

    def __repr__(self):
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    # -- fitting -------------------------------------------------------------------------------
    def fit(self, frames) -> "Stage":
        """Learn from training frames (a list of :class:`hsiffc.frame.Frame`). Stateless stages
        only mark themselves fitted."""
        self.fitted_ = True
        return self

    def is_fitted(self) -> bool:
        return self.stateless or bool(getattr(self, "fitted_", False))

    def check_is_fitted(self) -> None:
        if not self.is_fitted():
            raise NotFittedError(f"{type(self).__name__} is not fitted yet; call fit(frames) "
                                 "first (or load a fitted pipeline)")

    def transform(self, frame):  # pragma: no cover - abstract
        raise NotImplementedError

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
        for key, value in {**js, **arrays}.items():
            if not key.endswith("_"):
                raise ValueError(f"state key {key!r} is not a fitted attribute")
            setattr(self, key, value)
        return self

    def clone(self) -> "Stage":
        """An unfitted copy with the same parameters."""
        return type(self)(**copy.deepcopy(self.get_params()))


def check_stage(stage: Stage, train_frames, test_frame) -> None:
    """Run the stage contract tests; raises AssertionError with the broken rule.

    Checks: parameters round-trip through get_params/clone; transform before fit raises
    NotFittedError (unless stateless); fit returns self; transform returns a new Frame and does
    not mutate its input; no NaN or inf appears in the output data; the DQ plane is kept or
    extended (no bit of the input is cleared); the fitted state survives a JSON + npz round
    trip and gives the same output.
    """
    import io

    from ..frame import Frame

    params = stage.get_params()
    fresh = stage.clone()
    assert fresh.get_params().keys() == params.keys(), "clone() changed the parameter names"
    if not stage.stateless:
        try:
            fresh.transform(test_frame)
        except NotFittedError:
            pass
        else:
            raise AssertionError(f"{type(stage).__name__}.transform ran before fit")
    before_data = test_frame.data.copy()
    before_dq = test_frame.dq.copy()
    fitted = fresh.fit(train_frames)
    assert fitted is fresh, "fit() must return self"
    out = fresh.transform(test_frame)
    assert isinstance(out, Frame), "transform() must return a Frame"
    assert out is not test_frame, "transform() must return a new Frame"
    assert np.array_equal(test_frame.data, before_data), "transform() mutated its input data"
    assert np.array_equal(test_frame.dq, before_dq), "transform() mutated its input dq"
    assert np.all(np.isfinite(out.data)), "transform() produced NaN or inf"
    if out.dq.shape == test_frame.dq.shape:
        lost = test_frame.dq & ~out.dq
        assert not lost.any(), "transform() cleared DQ bits of its input"
    js, arrays = fresh.get_state()
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as npz:
        restored = stage.clone().set_state(json.loads(json.dumps(js)),
                                           {k: npz[k] for k in npz.files})
    again = restored.transform(test_frame)
    assert np.array_equal(again.data, out.data), "state round trip changed the output"
    assert np.array_equal(again.dq, out.dq), "state round trip changed the DQ plane"
