"""What every task of a batch shares: its settings, the calibration and the pipeline.

:class:`Settings` are plain values sent to the workers; :func:`context_for` turns them into the
loaded calibration and pipeline once per process (a worker handles many files).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from ..calibrate.product import Calibration
from ..data.params import LiveChoices
from ..flatfield.methods import FROM_CALIBRATION
from ..reconstruct import DEMOSAIC_METHODS
from ..stages import Pipeline, create
from ..stages import defaults
from .plan import BatchError

__all__ = ["CUBE_METHODS", "FFC_CHOICES", "Context", "Settings", "check_ffc", "context_for",
           "forget_contexts",
           "default_pipeline", "load_pipeline", "sha256_file", "with_cube_step"]

NAN_POLICIES = ("flag", "fail")


#: ``--ffc`` choices: the flat-field methods learnt from a calibration alone
#: (:data:`hsiffc.flatfield.FROM_CALIBRATION`, read from the registry when looked at) and
#: "none"
FFC_CHOICES = LiveChoices(lambda: (*FROM_CALIBRATION, "none"))


def default_pipeline(calibration, *, threshold_percent: float = 12.0,
                     linearise: bool = False, ffc: str = "model") -> Pipeline:
    """The pipeline ``hsiffc correct`` applies without ``--pipeline``
    (:func:`hsiffc.stages.defaults.default_pipeline`), after :func:`check_ffc` (BatchError for
    an unknown ``ffc`` or ``linearise`` with a flat-field method)."""
    check_ffc(ffc, linearise)
    return defaults.default_pipeline(calibration, threshold_percent=threshold_percent,
                                     linearise=linearise, ffc=ffc)


#: ``--cube`` choices: the demosaicking methods (:data:`hsiffc.reconstruct.DEMOSAIC_METHODS`)
#: and "tile" (one spectrum per mosaic tile)
CUBE_METHODS = (*DEMOSAIC_METHODS, "tile")


def with_cube_step(pipe: Pipeline, method: str, correction=None, imec_xml=None) -> Pipeline:
    """``pipe`` with a fitted ``reconstruct`` step appended (``hsiffc correct --cube``):
    ``method`` one of :data:`CUBE_METHODS` ("tile": one spectrum per mosaic tile), with the
    IMEC correction matrix to virtual bands when ``correction`` is "imec" or "derived"."""
    if method not in CUBE_METHODS:
        raise BatchError(f"--cube must be one of {', '.join(CUBE_METHODS)}, got {method!r}")
    if any(stage.name == "reconstruct" for _, stage in pipe.steps):
        raise BatchError("--cube adds a reconstruct step, but the pipeline already has one: "
                         "drop --cube (the pipeline's own step writes the cubes)")
    if correction is not None and imec_xml is None:
        raise BatchError(f"--cube-correction {correction} needs --imec-xml (the sensor's IMEC "
                         "calibration XML, which holds the correction matrix)")
    params = {"method": "bilinear" if method == "tile" else method,
              "resolution": "tile" if method == "tile" else "full",
              "correction": correction, "imec_xml": imec_xml}
    step = create("reconstruct", **params).fit([])
    out = Pipeline(list(pipe.steps) + [("cube", step)])
    out.fitted_on = pipe.fitted_on  # the frames it takes are the same
    return out


def check_ffc(ffc: str, linearise: bool) -> None:
    """BatchError unless ``ffc`` is one of :data:`FFC_CHOICES` and not a method (other than
    "none") together with ``linearise``."""
    if ffc not in FFC_CHOICES:
        raise BatchError(f"--ffc must be one of {', '.join(FFC_CHOICES)}, got {ffc!r}")
    if linearise and ffc != "none":
        raise BatchError("--linearise needs --ffc none: the default --ffc model already inverts "
                         "the leakage (drop --linearise, or add --ffc none for linearisation "
                         "without flat field)")


def load_pipeline(path, calibration: Calibration | None, notes: list | None = None) -> Pipeline:
    """A fitted pipeline file whose stages use ``calibration``.

    A stage's own calibration must have the same identity (else BatchError).
    :meth:`~hsiffc.stages.Pipeline.load` resolves the calibrations: a step recorded with
    ``calibration``'s identity gets it without reading a file; a format-1 file whose calibration
    path is not found gets it too.
    """
    path = Path(path)
    notes = [] if notes is None else notes
    if path.suffix != ".npz":
        raise BatchError(f"{path}: --pipeline takes a fitted pipeline (.npz from 'hsiffc fit'); "
                         "fit a TOML description first")
    pipe = Pipeline.load(path, calibration=calibration)  # same identity: no file read
    for name, stage in pipe.steps:
        if not stage.is_fitted():
            raise BatchError(f"{path}: step {name!r} is not fitted; fit it with 'hsiffc fit'")
        other = stage.get_params().get("calibration")
        if other is None:
            continue
        if calibration is None:
            raise BatchError(f"{path}: step {name!r} uses a calibration; pass it with "
                             "--calibration")
        if other.identity != calibration.identity:
            raise BatchError(f"{path}: step {name!r} uses calibration {other.identity} "
                             f"({other.path or 'embedded'}) but --calibration is "
                             f"{calibration.identity}: pass the calibration the pipeline was "
                             "fitted with, or fit the pipeline again")
        stage.set_params(calibration=calibration)  # loaded once, not per frame
    return pipe


@dataclass(frozen=True)
class Settings:
    """Everything a task needs besides its Job (plain values, sent to the workers)."""

    calibration: str | None  # None: a fitted pipeline that needs no calibration
    calibration_identity: str | None
    pipeline: str | None = None
    threshold_percent: float = 12.0
    linearise: bool = False
    ffc: str = "model"
    overwrite: bool = False
    nan: str = "flag"
    hash_inputs: bool = True
    #: metadata for inputs that do not carry it (fields of :class:`hsiffc.io.Overrides`)
    overrides: tuple = ()
    #: a reconstruct step appended to the pipeline (``--cube``): method ("nearest",
    #: "bilinear", "ppid" or "tile"), correction (None, "imec", "derived") and its IMEC XML
    cube: str | None = None
    cube_correction: str | None = None
    imec_xml: str | None = None
    #: compression of the outputs: "auto" (each format's default:
    #: :data:`hsiffc.cubes.stream.DEFAULT_COMPRESSION`), None, "zlib", "zstd" or "lzma"
    compression: str | None = "auto"
    #: where the pipeline runs: "cpu", or "cuda" (:mod:`hsiffc.gpu`; the same frames within
    #: its stated float32 tolerance, so not part of the outputs' fingerprint)
    device: str = "cpu"
    #: warning classes (or "all") that fail a file (``--fail-on-warning``; not part of the
    #: outputs' fingerprint: an output is written only without such a warning)
    fail_on_warning: tuple = ()
    #: the product files (``--format``: :data:`hsiffc.cubes.stream.PRODUCT_FORMATS`); not part
    #: of the fingerprint (each format holds the same corrected frames)
    formats: tuple = ("tiff",)
    #: write the alpha planes in the cube formats too (the hsiffc TIFF always holds them)
    cube_alpha: bool = False


@dataclass
class Context:
    """A batch's loaded calibration and pipeline, and what the provenance says of them."""

    calibration: Calibration | None
    identity: str | None  # the calibration's (a content hash: computed once)
    pipeline: Pipeline
    info: dict


_CONTEXTS: dict = {}  # per process: a worker builds its context once


def forget_contexts() -> None:
    """Drop the contexts this process has built (:func:`context_for` builds the next one
    afresh), e.g. after replacing a function it builds them with."""
    _CONTEXTS.clear()


def context_for(settings: Settings, calibration: Calibration | None = None) -> Context:
    """The calibration and pipeline of these settings, built once per process (from
    ``calibration`` when it is already loaded)."""
    key = (settings.calibration, settings.calibration_identity, settings.pipeline,
           settings.threshold_percent, settings.linearise, settings.ffc, settings.overrides,
           settings.cube, settings.cube_correction, settings.imec_xml, settings.device)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        cal = calibration
        if cal is None and settings.calibration is not None:
            cal = Calibration.load(settings.calibration)
        if calibration is None and cal is not None and cal.identity != settings.calibration_identity:
            raise BatchError(f"{settings.calibration}: the calibration changed since the batch "
                             f"started (identity {cal.identity}, expected "
                             f"{settings.calibration_identity})")
        if settings.pipeline:
            notes: list = []
            pipe = load_pipeline(settings.pipeline, cal, notes)
            info = {"kind": "file", "path": settings.pipeline,
                    "sha256": sha256_file(settings.pipeline), "notes": notes}
        else:
            pipe = default_pipeline(cal, threshold_percent=settings.threshold_percent,
                                    linearise=settings.linearise, ffc=settings.ffc)
            info = {"kind": "default", "path": None, "sha256": None, "notes": []}
        info["fitted_on"] = pipe.fitted_on  # what frames must be (None: not recorded)
        if settings.cube:
            pipe = with_cube_step(pipe, settings.cube, settings.cube_correction,
                                  settings.imec_xml)
        steps = [{"name": s["name"], "stage": s["stage"], "params": s["params"]}
                 for s in pipe.manifest()["steps"]]
        identity = settings.calibration_identity
        norm = [{**s, "params": {k: (f"identity:{identity}" if k == "calibration" and v
                                     else v) for k, v in s["params"].items()}} for s in steps]
        info["steps"] = steps
        info["input_overrides"] = {k: str(v) for k, v in settings.overrides}
        basis = {"steps": norm, "file": info["sha256"]}
        if info["input_overrides"]:
            basis["overrides"] = info["input_overrides"]
        info["fingerprint"] = hashlib.sha256(json.dumps(
            basis, sort_keys=True).encode()).hexdigest()[:16]
        info["alpha_computed"] = any(s["stage"] == "alpha_mask" for s in steps)
        info["cube"] = bool(steps) and steps[-1]["stage"] == "reconstruct"
        info["device"] = settings.device
        if settings.device != "cpu":  # refuses, in one line, a step the device cannot run
            from ..gpu import to_device

            pipe = to_device(pipe, settings.device)
        ctx = Context(cal, identity, pipe, info)
        if len(_CONTEXTS) > 4:
            _CONTEXTS.clear()
        _CONTEXTS[key] = ctx
    return ctx


def sha256_file(path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


