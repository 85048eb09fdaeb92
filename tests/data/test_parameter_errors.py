"""Every mistake named: a misspelt stage or parameter (Python, TOML, the command line), and a
frame that does not fit its calibration. One test per message."""

from __future__ import annotations

import re

import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.errors import HsiffcError, ParameterError, UnknownStageError
from hsiffc.data.params import did_you_mean, validate_method
from hsiffc.stages import Pipeline, create


def test_misspelt_stage_name_is_a_parameter_error_with_a_suggestion():
    with pytest.raises(ParameterError) as info:
        create("two_point_fcc")
    exc = info.value
    assert isinstance(exc, ValueError) and isinstance(exc, UnknownStageError)
    text = str(exc)
    assert text.startswith("no stage named 'two_point_fcc'; did you mean 'two_point_ffc'?")
    assert "alpha_mask" in text and "reconstruct" in text  # every installed stage listed
    assert not text.startswith(("'", '"'))  # the message itself, not a KeyError's repr


def test_misspelt_parameter_in_python_names_stage_parameter_and_valid_ones():
    with pytest.raises(ParameterError, match=r"^stage 'alpha_mask' has no parameter "
                                             r"'threshold_percnt'; did you mean "
                                             r"'threshold_percent'\? valid: .*calibration"):
        create("alpha_mask", threshold_percnt=12)


def test_parameter_far_from_any_gets_the_list_without_a_guess():
    with pytest.raises(ParameterError) as info:
        create("dark", colour="blue")
    assert "did you mean" not in str(info.value)
    assert "stage 'dark' has no parameter 'colour'; valid: " in str(info.value)


def test_set_params_names_stage_and_suggests():
    pipe = Pipeline([("dark", create("dark"))])
    with pytest.raises(ParameterError, match="stage 'dark' has no parameter 'mtch'; "
                                             "did you mean 'match'"):
        pipe.set_params(dark__mtch="scale")
    with pytest.raises(ParameterError, match="'drak__match': use step__param with a step of "
                                             r"\['dark'\]; did you mean 'dark'\?"):
        pipe.set_params(drak__match="scale")


def _toml(tmp_path, stage: str, param: str):
    path = tmp_path / "p.toml"
    path.write_text(f'[[step]]\nname = "mask"\nstage = "{stage}"\n{param} = 12\n')
    return path


def test_misspelt_parameter_in_toml_names_file_step_stage_and_suggests(tmp_path):
    path = _toml(tmp_path, "alpha_mask", "threshold_percnt")
    with pytest.raises(ParameterError) as info:
        Pipeline.from_toml(path)
    assert str(info.value) == (
        f"{path}: step 'mask': stage 'alpha_mask' has no parameter 'threshold_percnt'; did "
        f"you mean 'threshold_percent'? valid: {', '.join(create('alpha_mask')._param_names())}")


def test_misspelt_stage_in_toml_through_the_command_line(tmp_path, sample_cubes, capsys):
    path = _toml(tmp_path, "alpha_msk", "threshold_percent")
    code = main(["fit", str(path), str(sample_cubes / "darks.tif"), "-o",
                 str(tmp_path / "p.npz")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"hsiffc fit: error: {path}: step 'mask': no stage named "
                          "'alpha_msk'; did you mean 'alpha_mask'?")
    assert err.count("\n") == 1 and not (tmp_path / "p.npz").exists()


def test_method_names_get_a_suggestion_too():
    with pytest.raises(ParameterError, match="unknown demosaicking method 'ppdi'; did you mean "
                                             "'ppid'\\? valid: nearest, ppid"):
        validate_method("ppdi", {"nearest": 1, "ppid": 2}, "demosaicking method")
    assert did_you_mean(12, ["a"]) == ""


def test_frame_of_another_mosaic_shape_or_depth_is_refused_with_both_values(demo_result):
    from hsiffc.data.frame import Frame
    from hsiffc.data.mosaic import Mosaic

    cal = demo_result.calibration
    stage = create("alpha_mask", calibration=cal)
    h, w = cal.frame_shape
    other = Mosaic.square(4)
    cases = [(Frame.from_raw(cal.dark[:, : w - 8], exposure_ms=10.0, bit_depth=cal.bit_depth),
              f"frame shape {(h, w - 8)} but the calibration is for {(h, w)}"),
             (Frame.from_raw(cal.dark, exposure_ms=10.0, bit_depth=12),
              f"bit depth 12 but the calibration is for {cal.bit_depth}")]
    cases.append((Frame.from_raw(cal.dark, exposure_ms=10.0, bit_depth=cal.bit_depth,
                                 mosaic=other),
                  f"mosaic {other.describe()} differs from the calibration's "
                  f"{cal.mosaic.describe()}"))
    for frame, message in cases:
        with pytest.raises(HsiffcError, match="does not fit calibration") as info:
            stage.transform(frame)
        assert message in str(info.value)


@pytest.mark.parametrize("stages", [("alpha_mask",), ("linearise",)])
def test_frame_without_a_mosaic_on_a_mosaic_calibration_is_warned_in_python(demo_result, stages):
    # the batch said so for a file; a frame built in Python went through silently
    from hsiffc.data.frame import Frame
    from hsiffc.errors import MissingMosaicWarning

    cal = demo_result.calibration
    pipe = Pipeline([(name, create(name, calibration=cal)) for name in stages])
    raw = cal.dark + 50.0
    said = re.escape(f"is for {cal.mosaic.describe()}, {cal.mosaic.n_bands} bands")
    with pytest.warns(MissingMosaicWarning,
                      match=f"gives no mosaic layout but calibration .* {said}"):
        pipe.transform(Frame.from_raw(raw, exposure_ms=10.0, bit_depth=cal.bit_depth))
    # with its layout, nothing to say (the suite turns hsiffc warnings into errors)
    pipe.transform(Frame.from_raw(raw, exposure_ms=10.0, bit_depth=cal.bit_depth,
                                  mosaic=cal.mosaic))


def test_file_without_a_mosaic_corrected_with_a_mosaic_calibration_is_warned(
        demo_result, sample_cubes, tmp_path):
    from hsiffc.batch import correct_batch
    from hsiffc.io import read_sweep

    cal_path = demo_result.calibration.save(tmp_path / "cal.npz")
    test = read_sweep(sample_cubes / "test_2200K.tif")
    plain = tmp_path / "raw" / "plain.tif"
    plain.parent.mkdir()
    tifffile.imwrite(plain, test.data[:2], photometric="minisblack", metadata=None)
    summary = correct_batch([plain.parent], tmp_path / "out", cal_path,
                            overrides={"exposure_ms": 16.125, "bit_depth": 10})
    (res,) = summary.results
    assert res["status"] == "done", res
    note = [w["message"] for w in res["warnings"] if "no mosaic layout" in w["message"]]
    assert note and f"calibration is for {demo_result.calibration.mosaic.describe()}, 8 bands" \
        in note[0] and "--mosaic" in note[0]


def test_command_line_choices_and_options_get_a_suggestion(capsys):
    assert main(["correct", "x.tif", "--ffc", "modle", "-o", "o"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'modle'" in err and "did you mean 'model'?" in err
    assert main(["corect"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'corect'" in err and "did you mean 'correct'?" in err
    assert main(["correct", "x.tif", "--calibraton", "c.npz", "-o", "o"]) == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: --calibraton" in err
    assert "did you mean '--calibration'?" in err and err.count("\n") == 1
