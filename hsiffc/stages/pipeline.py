"""The pipeline: named stages fitted on training frames and applied to test frames.

``Pipeline.fit(frames)`` trains each stage on the training frames passed through the stages
already fitted before it; ``transform(frame)`` runs them in order and records one history entry
per stage in ``frame.meta["history"]`` (stage, parameters, status) - in this one place, not in
every stage. Building a pipeline checks every stage's parameters, the order of the stages
(what each needs against what the ones before it give) and reads each calibration file once
(giving its steps the calibration read in place of the path);
a fitted pipeline (built from fitted stages, fitted or loaded) then makes its plan
(:meth:`Pipeline.prepare`): each stage's prepared per-frame state and the fused front end,
held in :attr:`Pipeline.plan`.
A fitted pipeline saves to one versioned product file (:mod:`hsiffc.data.products`: arrays plus a
JSON manifest, no pickle) and loads by registered stage names; a small TOML file describes one
for the CLI. Calibrations are recorded by identity (and path, or embedded when they exist only
in memory), so a pipeline built in a notebook saves and loads without saving anything first.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import DataFormatError, HsiffcError, ParameterError
from ..data.frame import Frame
from ..data.params import did_you_mean
from ..data.products import read_product, write_product
from . import registry
from .base import Stage
from .contract import check_frames, check_needs, training_record
from .fusion import FusedFrontEnd
from .order import check_order

if TYPE_CHECKING:  # imported where used: hsiffc.calibrate compiles its fit
    from ..calibrate.product import Calibration

FORMAT = "hsiffc-pipeline"
FORMAT_VERSION = 2  # 2: calibrations as {"identity", "path"[, "embedded"]}; 1 (paths) still read
_MISSING = object()
REMEDY = "fit one with 'hsiffc fit DESCRIPTION.toml TRAINING... -o PIPELINE.npz'"


def json_params(stage: Stage) -> dict:
    """A stage's parameters as JSON (:meth:`hsiffc.stages.base.Stage.json_params`)."""
    return stage.json_params()


#: Where a pipeline runs besides this process's CPU, and its CPU stream: name ->
#: ``"module:function"``, imported when called (as plugin stages are): the GPU backend
#: (:mod:`hsiffc.gpu`) sits above the stages and imports them, so the stages name it instead
#: of importing it.
BACKENDS = {"to_device": "hsiffc.gpu:to_device", "cpu_stream": "hsiffc.gpu.pipeline:cpu_stream"}


def _backend(name: str):
    module, _, attr = BACKENDS[name].partition(":")
    return getattr(importlib.import_module(module), attr)


def _is_calibration(stage_cls, key: str) -> bool:
    spec = getattr(stage_cls, "param_spec", {}).get(key)
    return key == "calibration" or (spec is not None and spec.kind == "calibration")


def _is_file(stage_cls, key: str) -> bool:
    spec = getattr(stage_cls, "param_spec", {}).get(key)
    return _is_calibration(stage_cls, key) or (spec is not None and spec.kind == "path")


def _recorded(name, stage, frame: Frame) -> Frame:
    """``frame`` with the history entry of the step ``name`` that returned it."""
    entry = {"step": name, "stage": stage.name or type(stage).__name__,
             "params": json_params(stage), "status": "ok"}
    return frame.replace(meta={"history": frame.history + (entry,)})


def _state_schema(stage_name: str, params: dict):
    """The schema of the fitted state of a step of a registered stage with ``params``: the
    stage's own ``state_schema`` (a mapping, or a function of the parameters); None for a
    stage that declares none (numbers only) or an unknown stage (Pipeline.load reports it,
    naming the stage)."""
    try:
        stage_cls = registry.get(stage_name)
    except KeyError:
        return None
    schema = getattr(stage_cls, "state_schema", None)
    return schema(params) if callable(schema) else schema


def _made_from(steps) -> tuple:
    """What a plan is made from: every stage and the objects its attributes hold (held, so
    that :meth:`Plan.is_current` compares them by identity)."""
    return tuple((stage, tuple(vars(stage).items())) for _, stage in steps)


class Plan:
    """How a fitted pipeline runs a frame, made once by :meth:`Pipeline.prepare`.

    Attributes
    ----------
    units : tuple
        In order: a :class:`~hsiffc.stages.fusion.FusedFrontEnd`, or a step
        ``(name, stage, prepared)`` with the stage's :meth:`~hsiffc.stages.base.Stage.prepare`.
    made_from : tuple
        The stages and the objects they held when it was made: :meth:`Pipeline.transform`
        makes the plan again when a stage was changed since (``set_params`` on a stage, a
        stage fitted again: :meth:`is_current`).
    """

    def __init__(self, steps):
        self.made_from = _made_from(steps)
        prepared = [(name, stage, stage.prepare()) for name, stage in steps]
        units, i = [], 0
        while i < len(prepared):
            front = FusedFrontEnd.starting(prepared[i:])
            if front is not None:
                units.append(front)
                i += len(front.steps)
            else:
                units.append(prepared[i])
                i += 1
        self.units = tuple(units)

    def is_current(self, steps) -> bool:
        """Whether ``steps`` are the stages it was made from, holding the same objects."""
        if len(steps) != len(self.made_from):
            return False
        for (stage, items), (_, now) in zip(self.made_from, steps):
            attrs = vars(now)
            if stage is not now or len(attrs) != len(items) or any(
                    attrs.get(k, _MISSING) is not v for k, v in items):
                return False
        return True

    def describe(self) -> str:
        """The units in one line, e.g. ``FusedFrontEnd(dark + mask + ffc), cube``."""
        return ", ".join(repr(u) if isinstance(u, FusedFrontEnd) else u[0] for u in self.units)

    def __repr__(self) -> str:
        return f"<Plan: {self.describe()}>"


class Pipeline:
    """A sequence of named stages.

    Parameters
    ----------
    steps : list of (name, Stage)

    Raises
    ------
    ParameterError
        A stage parameter breaks its declaration, or the order makes no sense (the message
        names both steps).

    Examples
    --------
    >>> from hsiffc.stages import Pipeline, create
    >>> p = Pipeline([("dark", create("dark")), ("ffc", create("two_point_ffc"))])
    >>> p.set_params(ffc__normalisation="mean_gain").named_steps["ffc"].normalisation
    'mean_gain'
    >>> Pipeline([("ffc", create("two_point_ffc")), ("dark", create("dark"))])
    Traceback (most recent call last):
    ...
    hsiffc.errors.ParameterError: step 'ffc' (two_point_ffc) needs dark-subtracted frames, which step 'dark' only gives after it: put 'dark' before 'ffc'
    """

    def __init__(self, steps):
        steps = list(steps)
        names = [n for n, _ in steps]
        if len(set(names)) != len(names):
            raise ParameterError(f"step names must be unique, got {names}")
        for name, stage in steps:
            if not isinstance(stage, Stage):
                raise ParameterError(f"step {name!r} is {type(stage).__name__}, not a hsiffc "
                                     "Stage")
            if not isinstance(name, str) or not name or "__" in name:
                raise ParameterError(f"step name {name!r} must be a non-empty string without "
                                     "'__'")
            stage.validate_params()
        check_order(steps)
        self.steps = steps
        self.read_calibrations()
        #: what the pipeline was fitted on (:func:`hsiffc.stages.contract.training_record`;
        #: saved in the manifest): frames are checked against it; None before :meth:`fit`
        self.fitted_on = None
        self._checked = None
        #: how a frame is run (:class:`Plan`), made by :meth:`prepare`; None until fitted
        self.plan = None
        self._prepare_if_fitted()

    @property
    def named_steps(self) -> dict:
        """``{step name: stage}``."""
        return dict(self.steps)

    def __repr__(self):  # one line per step; calibrations and arrays by their key figures
        fitted = all(s.is_fitted() for _, s in self.steps)
        steps = ",\n".join(f"    ({n!r}, {s!r})" for n, s in self.steps)
        runs = f"; runs as {self.plan.describe()}" if fitted and self.plan is not None else ""
        return f"Pipeline([  # {'fitted' if fitted else 'not fitted'}{runs}\n{steps}])"

    # -- parameters ----------------------------------------------------------------------------
    def get_params(self) -> dict:
        """Every stage parameter as ``step__param``."""
        return {f"{n}__{k}": v for n, s in self.steps for k, v in s.get_params().items()}

    def set_params(self, **params) -> "Pipeline":
        """Set stage parameters as ``step__param=value`` (checked as at build time)."""
        steps = self.named_steps
        for key, value in params.items():
            name, sep, param = key.partition("__")
            if not sep or name not in steps:
                raise ParameterError(f"{key!r}: use step__param with a step of {list(steps)}"
                                     + (f"; {did_you_mean(name, steps).strip()}" if sep and
                                        did_you_mean(name, steps) else ""))
            steps[name].set_params(**{param: value})
            steps[name].validate_params()
        check_order(self.steps)
        self.read_calibrations()
        self._prepare_if_fitted()
        return self

    def read_calibrations(self) -> None:
        """Read every calibration file the steps name, once, and give each step the
        :class:`~hsiffc.calibrate.Calibration` read in place of its path (the same object for
        the steps that name the same file). Called when the pipeline is built and by
        :meth:`set_params`; what a step records (:meth:`~hsiffc.stages.base.Stage.json_params`:
        identity and path) is the same for the path and for the calibration read from it.

        Raises
        ------
        DataFormatError
            A file is not a calibration (one line naming it).
        """
        from ..calibrate.product import Calibration

        read: dict = {}
        for _, stage in self.steps:
            for key, value in stage.get_params().items():
                if key == "calibration" and isinstance(value, (str, Path)):
                    where = str(Path(value).resolve())
                    if where not in read:
                        read[where] = Calibration.load(value)
                    stage.set_params(**{key: read[where]})

    def _prepare_if_fitted(self) -> None:
        """:meth:`prepare` where every stage is fitted. A stage that cannot prepare yet (a
        stateless one without its calibration) leaves :attr:`plan` None: :meth:`transform`
        then makes it and raises that stage's error, as it would without a plan."""
        self.plan = None
        if all(s.is_fitted() for _, s in self.steps):
            try:
                self.prepare()
            except HsiffcError:
                self.plan = None

    def prepare(self) -> Plan:
        """Make, once, what running a frame needs: every stage's prepared per-frame state
        (:meth:`hsiffc.stages.base.Stage.prepare`: prepared calibrations, dark lines...) and
        the fused front end (:class:`~hsiffc.stages.fusion.FusedFrontEnd`) where the steps
        make one. Called when a fitted pipeline is built or loaded, after :meth:`fit` and
        :meth:`set_params`; the plan is kept in :attr:`plan`.

        Raises
        ------
        NotFittedError
            A stage is not fitted.
        """
        self.plan = Plan(self.steps)
        return self.plan

    # -- fit / transform -----------------------------------------------------------------------
    def fit(self, frames) -> "Pipeline":
        """Fit every stage on ``frames`` (a list of Frames, or a Sweep) passed through the stages
        fitted before it, and record what they are (:attr:`fitted_on`: shape, mosaic, bit
        depth, the files' dtype where the frames' ``input_dtype`` metadata gives it, exposure
        range).

        Raises
        ------
        ParameterError
            A step whose needs the frames cannot meet (a reconstruct step without a mosaic).
        """
        from ..data.sweep import Sweep

        current = Frame.list_from_sweep(frames) if isinstance(frames, Sweep) else list(frames)
        if not current:
            raise ValueError("fit needs training frames (darks and flats); got none")
        check_needs(self.steps, current)
        record = training_record(current)
        for i, (name, stage) in enumerate(self.steps):
            stage.fit(current)
            if i < len(self.steps) - 1:
                prepared = stage.prepare()
                current = [prepared.transform(f) for f in current]
        self.fitted_on, self._checked = record, None
        self.prepare()
        return self

    def check_frame(self, frame: Frame) -> None:
        """CalibrationMismatchError (one line naming the option that fixes it) when
        ``frame``'s mosaic, shape or bit depth differ from those the pipeline was fitted on
        (:attr:`fitted_on`; :func:`hsiffc.stages.contract.check_frames`). Checked by
        :meth:`transform`, once per kind of frame."""
        key = (frame.data.shape, frame.bit_depth, frame.mosaic)  # the same object: no compare
        if self.fitted_on is None or key == self._checked:
            return
        check_frames(self.fitted_on, shape=frame.data.shape, mosaic=frame.mosaic,
                     bit_depth=frame.bit_depth, what="the frame")
        self._checked = key

    def transform(self, frame: Frame, *, fuse: bool = True) -> Frame:
        """Run every stage on ``frame`` and record each in its history.

        With ``fuse`` (the default) a dark and an alpha mask in a row, and a two-point FFC
        after them, run as one pass over the pixels (:mod:`hsiffc.stages.fusion`): the same
        frame, bit for bit, in less time; ``fuse=False`` runs every stage's own
        ``transform``. Both run the stages as prepared in :attr:`plan` (made again first
        where a stage was changed since it was made)."""
        self.check_frame(frame)
        plan = self.plan
        if plan is None or not plan.is_current(self.steps):
            plan = self.prepare()
        for unit in plan.units:
            if isinstance(unit, FusedFrontEnd):
                frame = unit.run(frame, _recorded, fuse=fuse)
            else:
                name, stage, prepared = unit
                frame = _recorded(name, stage, prepared.transform(frame))
        return frame

    def fit_transform(self, frames, test: Frame) -> Frame:
        """``fit(frames)`` then ``transform(test)``."""
        return self.fit(frames).transform(test)

    # -- devices and live streams (hsiffc.gpu) --------------------------------------------------
    def to(self, device: str):
        """This pipeline for ``device``: ``"cpu"`` (itself) or ``"cuda"`` (a
        :class:`hsiffc.gpu.pipeline.GpuPipeline`; :class:`hsiffc.gpu.GpuUnavailableError`, one
        line, where numba-cuda or a GPU is missing)."""
        return _backend("to_device")(self, device)

    def stream(self, frames, **options):
        """Correct an iterable of frames (or raw arrays) one by one, yielding
        :class:`hsiffc.gpu.pipeline.StreamItem` s; ``options`` as
        :meth:`hsiffc.gpu.pipeline.GpuPipeline.stream` (output types, alpha). On the CPU a
        plain loop over :meth:`transform`."""
        return _backend("cpu_stream")(self, frames, **options)

    # -- persistence ---------------------------------------------------------------------------
    def manifest(self) -> dict:
        """The JSON manifest :meth:`save` writes (format, versions, steps with parameters)."""
        man = {"steps": [{"name": n, "stage": s.name or type(s).__name__,
                          "params": json_params(s),
                          "state": s.get_state()[0] if s.is_fitted() else None}
                         for n, s in self.steps]}
        if self.fitted_on is not None:
            man["fitted_on"] = self.fitted_on
        return man

    def save(self, path, *, overwrite: bool = False) -> Path:
        """Write the (fitted) pipeline to one ``.npz`` atomically. A calibration that exists
        only in memory is stored inside the file."""
        from ..calibrate.product import Calibration

        man = self.manifest()
        arrays = {}
        for (name, stage), spec in zip(self.steps, man["steps"]):
            if stage.is_fitted():
                for key, arr in stage.get_state()[1].items():
                    arrays[f"{name}/{key}"] = arr
            for key, value in stage.get_params().items():
                if isinstance(value, Calibration) and value.path is None:
                    spec["params"][key]["embedded"] = value.manifest()
                    for k, arr in value.arrays.items():
                        arrays[f"{name}/{key}/{k}"] = arr
        return write_product(path, format=FORMAT, format_version=FORMAT_VERSION, manifest=man,
                             arrays=arrays, overwrite=overwrite)

    @classmethod
    def load(cls, path, *, calibration: Calibration | None = None) -> "Pipeline":
        """Read a pipeline file; stages are resolved by their registered names only.

        Parameters
        ----------
        path : path-like
        calibration : Calibration, optional
            Used for every step whose recorded calibration has the same identity (no file is
            read), and for a version-1 file whose calibration path is not found.

        Raises
        ------
        DataFormatError
            Unreadable or malformed file, unknown stage, calibration not found or changed.
        ParameterError
            A stored parameter breaks the stage's declaration.
        """
        man, arrays = read_product(path, format=FORMAT, format_version=FORMAT_VERSION,
                                   remedy=REMEDY, state_schema=_state_schema)
        try:
            specs = man["steps"]
            if not isinstance(specs, list) or not specs:
                raise TypeError("'steps' must be a non-empty list")
            steps = [_load_step(spec, arrays, Path(path), calibration) for spec in specs]
            pipe = cls(steps)
            record = man.get("fitted_on")
            if record is not None and not isinstance(record, dict):
                raise TypeError("'fitted_on' must be a table")
            pipe.fitted_on = record
            return pipe
        except ParameterError as exc:
            raise ParameterError(f"{path}: {exc}") from exc
        except HsiffcError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise DataFormatError(f"malformed pipeline manifest ({type(exc).__name__}: {exc}); "
                                  f"{REMEDY}", path=path) from exc

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
        from ..files.atomic import require_regular_input
        from ..files.parsers import load_toml

        path = Path(path)
        require_regular_input(path, what="pipeline description")  # never a FIFO: it may block
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise DataFormatError(f"not valid TOML: {exc}", path=path) from exc
        doc = load_toml(text, path=path, what="pipeline description")
        for key in doc:  # [[stepp]] beside [[step]] would be a shorter pipeline, silently
            if key != "step":
                raise DataFormatError(
                    f"unknown table or key {key!r}: {did_you_mean(key, ['step'])}a pipeline "
                    "description holds only [[step]] tables (name = ..., stage = ..., and the "
                    "stage's parameters)", path=path)
        specs = doc.get("step")
        if not specs or not isinstance(specs, list):
            raise DataFormatError("no [[step]] tables: describe each stage as [[step]] with "
                                  "name = ... and stage = ...", path=path)
        steps = []
        for i, spec in enumerate(specs):
            if not isinstance(spec, dict):
                raise DataFormatError(
                    f"step {i + 1} is {spec!r}, not a table; write each step as a [[step]] "
                    "table with name = \"...\" and stage = \"...\" (not step = [...])",
                    path=path)
            spec = dict(spec)
            stage_name = spec.pop("stage", None)
            if not isinstance(stage_name, str):
                raise DataFormatError(f"step {i + 1} has no stage = \"...\"", path=path)
            name = spec.pop("name", None) or stage_name
            try:  # a stage or a parameter name misspelt: named, with the closest valid one
                stage_cls = registry.get(stage_name)
            except KeyError as exc:
                raise DataFormatError(f"step {name!r}: {exc}", path=path) from None
            try:
                registry.check_param_names(stage_name, stage_cls, spec)
            except ParameterError as exc:
                raise ParameterError(f"{path}: step {name!r}: {exc}") from None
            try:
                for key, value in spec.items():  # relative file names: beside the TOML
                    if _is_file(stage_cls, key) and isinstance(value, str):
                        spec[key] = str((path.parent / value).resolve())
                steps.append((name, stage_cls(**spec)))
            except KeyError as exc:
                raise DataFormatError(f"step {name!r}: {exc.args[0]}", path=path) from exc
            except TypeError as exc:
                raise DataFormatError(f"step {name!r}: {exc}", path=path) from exc
        try:
            return cls(steps)
        except ParameterError as exc:
            raise ParameterError(f"{path}: {exc}") from exc


def _load_step(spec: dict, arrays: dict, path: Path, given: Calibration | None):
    name, stage_name = spec["name"], spec["stage"]
    params = dict(spec["params"])
    try:
        stage_cls = registry.get(stage_name)
    except KeyError as exc:
        raise DataFormatError(f"step {name!r}: {exc.args[0]}", path=path) from exc
    for key, value in params.items():
        if _is_calibration(stage_cls, key) and value is not None:
            params[key] = _resolve_calibration(value, f"{name}/{key}/", arrays, path, given)
    stage = stage_cls(**params)
    if spec.get("state") is not None:
        prefix = f"{name}/"
        state = {k[len(prefix):]: v for k, v in arrays.items()
                 if k.startswith(prefix) and "/" not in k[len(prefix):]}
        stage.set_state(dict(spec["state"]), state)
    return name, stage


def _resolve_calibration(ref, prefix: str, arrays: dict, path: Path,
                         given: Calibration | None) -> Calibration:
    """The Calibration a manifest names: ``given`` if it has the recorded identity, the
    embedded copy, or the file (found as recorded or beside the pipeline file)."""
    from ..calibrate.product import Calibration

    if isinstance(ref, str):  # format version 1: a path only
        ref = {"identity": None, "path": ref}
    identity, where = ref.get("identity"), ref.get("path")
    if given is not None and identity == given.identity:
        return given
    if ref.get("embedded") is not None:
        emb = ref["embedded"]
        cal = Calibration(arrays={k[len(prefix):]: v for k, v in arrays.items()
                                  if k.startswith(prefix)},
                          domain=emb["domain"], method=emb["method"],
                          fitted_on=emb.get("fitted_on", {}), created=emb.get("created", ""),
                          hsiffc_version=emb.get("hsiffc_version", "?"))
    else:
        found = [c for c in (Path(where), path.parent / where, path.parent / Path(where).name)
                 if c.is_file()] if where else []
        if not found:
            if given is not None and identity is None:
                return given
            raise DataFormatError(f"its calibration {where} (identity {identity}) is not found; "
                                  "put it back or pass the calibration it was fitted with",
                                  path=path)
        cal = Calibration.load(found[0])
    if identity is not None and cal.identity != identity:
        raise DataFormatError(f"calibration {cal.path or 'embedded'} has identity "
                              f"{cal.identity}, but the pipeline was fitted with {identity}; "
                              "fit the pipeline again or use its calibration", path=path)
    return cal
