"""The contracts: what a pipeline was fitted on and the check of the frames it is given
against it, and the stage contract tests (:func:`check_stage`).

:meth:`hsiffc.stages.Pipeline.fit` records the training frames' shape, mosaic, bit depth,
dtype (where known) and exposure range (:func:`training_record`); the record is saved in the
pipeline's manifest (``fitted_on``). :func:`check_frames` compares frames with it and raises
one line naming the option that fixes a mismatch (``--mosaic ...``, ``--bit-depth 8``), the
way a calibration checks the frames it corrects. :func:`check_needs` refuses, at fit, steps
whose needs the training frames cannot meet (a ``reconstruct`` step without a mosaic).

>>> import numpy as np
>>> from hsiffc.data.frame import Frame
>>> from hsiffc.data.mosaic import Mosaic
>>> f = Frame.from_raw(np.zeros((8, 8), np.uint8), exposure_ms=5, bit_depth=8,
...                    mosaic=Mosaic.square(4))
>>> rec = training_record([f])
>>> rec["shape"], rec["bit_depth"], rec["exposure_ms"], rec["mosaic_option"]
([8, 8], 8, [5.0, 5.0], '4x4')
>>> check_frames(rec, shape=(8, 8), mosaic=Mosaic.square(4), bit_depth=12)
Traceback (most recent call last):
...
hsiffc.errors.CalibrationMismatchError: the frames: bit depth 12, but the pipeline was fitted on 8-bit frames (saturation is flagged at 255 DN); give --bit-depth 8 if these frames are 8-bit, or fit the pipeline on frames of this bit depth
"""

from __future__ import annotations

import io
import json

import numpy as np

from ..data.frame import Frame
from ..data.mosaic import TILE_NAME, Mosaic
from ..errors import CalibrationMismatchError, ParameterError
from .base import NotFittedError, Stage
from .dark import DarkSubtract

__all__ = ["check_frames", "check_needs", "check_stage", "training_record"]


def _option(mosaic: Mosaic) -> str:
    """What ``--mosaic`` takes for ``mosaic``: its tile size, or the XML it came from."""
    rows, cols = mosaic.tile_shape
    if mosaic.name and not TILE_NAME.fullmatch(mosaic.name):
        return f"<the XML or sidecar used at fit: {mosaic.name}>"
    return f"{cols}x{rows}"


def training_record(frames) -> dict:
    """What a pipeline is fitted on: ``shape``, ``mosaic`` (its dict, or None),
    ``mosaic_text``, ``mosaic_option`` (what ``--mosaic`` takes), ``bit_depth``, ``dtype``
    (the files', where the frames' ``input_dtype`` metadata says it), ``exposure_ms``
    ([min, max]) and ``n_frames``."""
    f0 = frames[0]
    dtype = f0.meta.get("input_dtype")
    mosaic = f0.mosaic
    exposures = [float(f.exposure_ms) for f in frames]
    return {"shape": [int(s) for s in f0.data.shape],
            "mosaic": None if mosaic is None else mosaic.to_dict(),
            "mosaic_text": None if mosaic is None else mosaic.describe(),
            "mosaic_option": None if mosaic is None else _option(mosaic),
            "bit_depth": int(f0.bit_depth), "dtype": dtype,
            "exposure_ms": [min(exposures), max(exposures)], "n_frames": len(frames)}


def _same_layout(a: Mosaic, b: Mosaic) -> bool:
    """The same tile and offset (wavelengths aside: a layout given as ``--mosaic 5x5`` has
    none, the sensor's XML has them; the mosaic decides which pixel is which band)."""
    return np.array_equal(a.pattern, b.pattern) and a.offset == b.offset


def check_frames(record: dict | None, *, shape, mosaic, bit_depth, what: str = "the frames"
                 ) -> None:
    """Raise :class:`~hsiffc.errors.CalibrationMismatchError` (one line: what differs and
    the option that fixes it) when frames of ``shape``, ``mosaic`` and ``bit_depth`` do not
    fit what the pipeline was fitted on (``record``: :func:`training_record`; None: nothing
    to check, e.g. a pipeline saved before the record existed)."""
    if not record:
        return
    fitted = record.get("mosaic")
    if fitted is not None:
        want = Mosaic.from_dict(fitted)
        if mosaic is None or not _same_layout(want, mosaic):
            given = "no mosaic layout" if mosaic is None else f"mosaic {mosaic.describe()}"
            raise CalibrationMismatchError(
                f"{what}: {given}, but the pipeline was fitted on frames of mosaic "
                f"{record.get('mosaic_text') or want.describe()}: give --mosaic "
                f"{record.get('mosaic_option') or _option(want)} (the layout used at fit; or "
                "the same in a sidecar hsiffc.toml), or fit the pipeline on frames of this "
                "sensor")
    want_shape = tuple(record.get("shape") or ())
    if want_shape and tuple(shape) != want_shape[:len(tuple(shape))]:
        raise CalibrationMismatchError(
            f"{what}: frames of {' x '.join(map(str, shape))} px, but the pipeline was fitted "
            f"on {' x '.join(map(str, want_shape))} px frames: correct frames of the size (and "
            "crop) it was fitted on, or fit it on frames of this size")
    want_bits = record.get("bit_depth")
    if want_bits is not None and bit_depth is not None and int(bit_depth) != int(want_bits):
        raise CalibrationMismatchError(
            f"{what}: bit depth {bit_depth}, but the pipeline was fitted on {want_bits}-bit "
            f"frames (saturation is flagged at {2 ** int(want_bits) - 1} DN); give --bit-depth "
            f"{want_bits} if these frames are {want_bits}-bit, or fit the pipeline on frames "
            "of this bit depth")


def check_needs(steps, frames) -> None:
    """ParameterError, before anything is fitted, for a step whose needs the training frames
    cannot meet: a ``reconstruct`` step needs a mosaic layout (its cube's bands are the
    mosaic's)."""
    if any(f.mosaic is not None for f in frames[:1]):
        return
    for name, stage in steps:
        if (stage.name or "") == "reconstruct":
            raise ParameterError(
                f"step {name!r} (reconstruct) needs a mosaic layout, but the training frames "
                "give none: give --mosaic (e.g. --mosaic 5x5, or the sensor's IMEC XML) or a "
                "sidecar hsiffc.toml with mosaic = ..., so that the pipeline is fitted, and "
                "later applied, on frames whose bands are known")


def check_stage(stage: Stage, train_frames, test_frame) -> None:
    """Run the stage contract tests; raises AssertionError with the broken rule.

    Checks: parameters round-trip through get_params/clone; transform before fit raises
    NotFittedError (unless stateless); fit returns self; transform returns a new Frame and does
    not mutate its input; no NaN or inf appears in the output data; the DQ plane is kept or
    extended (no bit of the input is cleared); the output has the states the stage declares it
    produces and none it declares it removes; the fitted state survives a JSON + npz round
    trip and gives the same output.

    Frames are given raw (as read from files); when the stage ``requires`` dark-subtracted
    frames, a default dark stage fitted on ``train_frames`` is run on them first.

    Parameters
    ----------
    stage : Stage
        An unfitted instance with the parameters to test.
    train_frames : list of Frame
        Training frames (darks and flats, as the stage needs).
    test_frame : Frame
        A raw frame to transform.

    Raises
    ------
    AssertionError
        Naming the rule the stage breaks.
    """
    if "dark_subtracted" in stage.requires and "dark_subtracted" not in test_frame.state():
        dark = DarkSubtract().fit(train_frames)
        train_frames = [dark.transform(f) for f in train_frames]
        test_frame = dark.transform(test_frame)
    missing = stage.requires - test_frame.state()
    assert not missing, f"check_stage cannot give {type(stage).__name__} frames with {missing}"
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
    state = out.state()
    assert stage.produces <= state, f"output lacks the declared {set(stage.produces - state)}"
    assert not stage.removes & state, f"output still has the removed {set(stage.removes & state)}"
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
