"""Short reprs: a REPL echo of a calibration, a pipeline or a frame shows key figures (shape,
dtype, bit depth, exposure, mosaic, what was done) in a few lines, never an array."""

from __future__ import annotations

import numpy as np

from hsiffc.data.frame import Frame
from hsiffc.stages import Pipeline, create


def test_calibration_repr_is_one_line_of_key_figures(demo_result):
    cal = demo_result.calibration
    text = repr(cal)
    h, w = cal.frame_shape
    assert "\n" not in text and len(text) < 250
    for part in (f"{h} x {w} px", f"{cal.bit_depth}-bit", cal.mosaic.describe(), "8 bands",
                 cal.identity, "ms"):
        assert part in text, part
    assert "array(" not in text


def test_pipeline_repr_is_a_line_per_step(demo_result):
    pipe = demo_result.pipeline
    text = repr(pipe)
    lines = text.splitlines()
    assert len(lines) == len(pipe.steps) + 1 and "# fitted" in lines[0]
    # what runs: the fused front end by name, then the other steps (Pipeline.plan)
    assert lines[0].endswith("# fitted; runs as FusedFrontEnd(dark + mask + ffc), cube")
    assert all(len(line) < 200 for line in lines) and "array(" not in text.replace(
        "array((", "")  # arrays only ever as array((shape) dtype)
    assert demo_result.calibration.identity in text
    unfitted = Pipeline([("dark", create("dark"))])
    assert "# not fitted" in repr(unfitted)


def test_frame_repr_names_shape_dtype_exposure_and_what_was_done(sample_cubes, demo_result):
    from hsiffc.io import read_sweep

    frame = Frame.list_from_sweep(read_sweep(sample_cubes / "test_2200K.tif"))[0]
    text = repr(frame)
    assert text.startswith("<Frame frame 96 x 128 float32, 16.125 ms, 10-bit, light, mosaic 4x2")
    out = demo_result.pipeline.transform(frame)
    text = repr(out)
    assert "\n" not in text and len(text) < 300
    assert "dark removed" in text and "alpha" in text and "after " in text
    bare = Frame.from_raw(np.zeros((4, 8)), exposure_ms=1.0, bit_depth=12)
    assert repr(bare) == "<Frame frame 4 x 8 float32, 1 ms, 12-bit, light, 0.00 % flagged>"


def test_sweep_repr_is_one_line_of_key_figures_and_never_the_array(sample_cubes):
    from hsiffc.io import read_sweep

    sweep = read_sweep(sample_cubes / "sweep_2900K.tif")
    text = repr(sweep)
    assert "\n" not in text and len(text) < 250 and "array" not in text and "[" not in text
    light, dark = int(sweep.is_light.sum()), int(sweep.is_dark.sum())
    t = sweep.exposure_ms
    for part in ("<Sweep 80 frames of 96 x 128 px uint16", "10-bit",
                 f"{len(sweep.steps())} steps", f"exposure {t.min():.4g}-{t.max():.4g} ms",
                 f"{light} light + {dark} dark", sweep.mosaic.describe(), "sweep_2900K.tif"):
        assert part in text, part
    empty = sweep.select(np.zeros(sweep.n_frames, bool))
    assert repr(empty).startswith("<Sweep 0 frames of 96 x 128 px uint16, 10-bit, 0 steps, "
                                  "0 light + 0 dark")
