"""The pipeline: named stages fitted on training frames and applied to test frames.

``Pipeline.fit(frames)`` trains each stage on the training frames passed through the stages
already fitted before it; ``transform(frame)`` runs them in order and records one history entry
per stage in ``frame.meta["history"]`` (stage, parameters, status) - in this one place, not in
every stage. A fitted pipeline saves to one versioned ``.npz`` (arrays plus a JSON manifest,
no pickle) and loads by registered stage names; a small TOML file describes one for the CLI.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np

from .. import __version__
from ..atomic import atomic_path
from ..errors import DataFormatError
from ..frame import Frame
from . import registry
from .base import Stage

FORMAT = "hsiffc-pipeline"
FORMAT_VERSION = 1


def _json_params(params: dict) -> dict:
    """Parameters as JSON: paths become strings; objects with a ``to_reference()`` (e.g. a
    calibration loaded from a file) become that reference."""
    out = {}
    for k, v in params.items():
        if isinstance(v, Path):
            v = str(v)
        elif hasattr(v, "to_reference"):
            v = v.to_reference()
        elif isinstance(v, np.generic):
            v = v.item()
        try:
            json.dumps(v)
        except TypeError as exc:
            raise TypeError(f"parameter {k}={v!r} cannot be saved; give a path or a plain "
                            "value") from exc
        out[k] = v
    return out


class Pipeline:
    """A sequence of named stages.

    Parameters
    ----------
    steps : list of (name, Stage)

    Examples
    --------
    >>> from hsiffc.stages import Pipeline, create
    >>> p = Pipeline([("dark", create("dark")), ("ffc", create("two_point_ffc"))])
    >>> p.set_params(ffc__normalisation="mean_gain").named_steps["ffc"].normalisation
    'mean_gain'
    """

    def __init__(self, steps):
        steps = list(steps)
        names = [n for n, _ in steps]
        if len(set(names)) != len(names):
            raise ValueError(f"step names must be unique, got {names}")
        for name, stage in steps:
            if not isinstance(stage, Stage):
                raise TypeError(f"step {name!r} is {type(stage).__name__}, not a hsiffc Stage")
            if "__" in name:
                raise ValueError(f"step name {name!r} must not contain '__'")
        self.steps = steps

    @property
    def named_steps(self) -> dict:
        return dict(self.steps)

    def __repr__(self):
        return "Pipeline([" + ", ".join(f"({n!r}, {s!r})" for n, s in self.steps) + "])"

    # -- parameters ----------------------------------------------------------------------------
    def get_params(self) -> dict:
        return {f"{n}__{k}": v for n, s in self.steps for k, v in s.get_params().items()}

    def set_params(self, **params) -> "Pipeline":
        """Set stage parameters as ``step__param=value``."""
        steps = self.named_steps
        for key, value in params.items():
            name, sep, param = key.partition("__")
            if not sep or name not in steps:
                raise ValueError(f"{key!r}: use step__param with a step of {list(steps)}")
            steps[name].set_params(**{param: value})
        return self

    # -- fit / transform -----------------------------------------------------------------------
    def fit(self, frames) -> "Pipeline":
        """Fit every stage on ``frames`` (a list of Frames, or a Sweep) passed through the stages
        fitted before it."""
        from ..sweep import Sweep

        current = Frame.list_from_sweep(frames) if isinstance(frames, Sweep) else list(frames)
        if not current:
            raise ValueError("fit needs training frames (darks and flats); got none")
        for i, (name, stage) in enumerate(self.steps):
            stage.fit(current)
            if i < len(self.steps) - 1:
                current = [stage.transform(f) for f in current]
        return self

    def transform(self, frame: Frame) -> Frame:
        """Run every stage on ``frame`` and record each in its history."""
        for name, stage in self.steps:
            stage.check_is_fitted()
            frame = stage.transform(frame)
            entry = {"step": name, "stage": stage.name or type(stage).__name__,
                     "params": _json_params(stage.get_params()), "status": "ok"}
            frame = frame.replace(meta={"history": frame.history + (entry,)})
        return frame

    def fit_transform(self, frames, test: Frame) -> Frame:
        return self.fit(frames).transform(test)

    # -- persistence ---------------------------------------------------------------------------
    def manifest(self) -> dict:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "hsiffc_version": __version__,
                "steps": [{"name": n, "stage": s.name or type(s).__name__,
                           "params": _json_params(s.get_params()),
                           "state": s.get_state()[0] if s.is_fitted() else None}
                          for n, s in self.steps]}

    def save(self, path, *, overwrite: bool = False) -> Path:
        """Write the (fitted) pipeline to one ``.npz`` atomically."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"pipeline files end in .npz, got {path.name!r}")
        payload = {}
        for name, stage in self.steps:
            if stage.is_fitted():
                for key, arr in stage.get_state()[1].items():
                    payload[f"{name}/{key}"] = np.ascontiguousarray(arr)
        payload["manifest.json"] = np.frombuffer(json.dumps(self.manifest()).encode(), np.uint8)
        with atomic_path(path, overwrite=overwrite) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **payload)
        return path

    @classmethod
    def load(cls, path) -> "Pipeline":
        """Read a pipeline file; stages are resolved by their registered names only."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as npz:
                contents = {k: npz[k] for k in npz.files}
        except FileNotFoundError:
            raise DataFormatError("pipeline file not found", path=path) from None
        except (ValueError, OSError, EOFError) as exc:
            raise DataFormatError(f"not a readable pipeline file ({exc})", path=path) from exc
        if "manifest.json" not in contents:
            raise DataFormatError("no manifest.json inside: not an hsiffc pipeline", path=path)
        man = json.loads(contents.pop("manifest.json").tobytes().decode())
        if man.get("format") != FORMAT:
            raise DataFormatError(f"format is {man.get('format')!r}, expected {FORMAT!r}",
                                  path=path)
        if int(man.get("format_version", 0)) > FORMAT_VERSION:
            raise DataFormatError("pipeline format is newer than this hsiffc reads; upgrade "
                                  "hsiffc", path=path)
        steps = []
        for spec in man["steps"]:
            try:
                stage = registry.create(spec["stage"], **spec["params"])
            except KeyError as exc:
                raise DataFormatError(f"step {spec['name']!r}: {exc.args[0]}", path=path) from exc
            if spec.get("state") is not None:
                prefix = f"{spec['name']}/"
                arrays = {k[len(prefix):]: v for k, v in contents.items() if k.startswith(prefix)}
                stage.set_state(spec["state"], arrays)
            steps.append((spec["name"], stage))
        return cls(steps)

    @classmethod
    def from_toml(cls, path) -> "Pipeline":
        """Build an unfitted pipeline from a TOML description::

            [[step]]
            name = "dark"
            stage = "dark"

            [[step]]
            name = "ffc"
            stage = "two_point_ffc"
            calibration = "cal.npz"      # paths are relative to the TOML file
            threshold_percent = 12
        """
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise DataFormatError("pipeline description not found", path=path) from None
        except tomllib.TOMLDecodeError as exc:
            raise DataFormatError(f"not valid TOML: {exc}", path=path) from exc
        specs = doc.get("step")
        if not specs:
            raise DataFormatError("no [[step]] tables: describe each stage as [[step]] with "
                                  "name = ... and stage = ...", path=path)
        steps = []
        for i, spec in enumerate(specs):
            spec = dict(spec)
            try:
                name = spec.pop("name", None) or spec["stage"]
                stage_name = spec.pop("stage")
            except KeyError:
                raise DataFormatError(f"step {i + 1} has no stage = \"...\"", path=path) from None
            for key in ("calibration", "imec_xml"):
                if isinstance(spec.get(key), str) and not Path(spec[key]).is_absolute():
                    spec[key] = str((path.parent / spec[key]).resolve())
            try:
                steps.append((name, registry.create(stage_name, **spec)))
            except KeyError as exc:
                raise DataFormatError(f"step {name!r}: {exc.args[0]}", path=path) from exc
            except TypeError as exc:
                raise DataFormatError(f"step {name!r}: {exc}", path=path) from exc
        return cls(steps)
