"""The demo as a library: compute a result, render it, plot it; nothing printed, no backend
switched; the shipped pipeline makes the sample test frames more uniform where temporal noise
does not count."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest

from hsiffc.reports.demo import compute_demo, demo_figure, fit_curve, render_text


@pytest.fixture(scope="module")
def demo(demo_result):
    return demo_result


def test_compute_is_silent_and_leaves_matplotlib_alone(sample_cubes, capsys):
    backend = matplotlib.get_backend()
    res = compute_demo(sample_cubes)
    fig = demo_figure(res)
    assert capsys.readouterr().out == ""
    assert matplotlib.get_backend() == backend
    assert len(fig.axes[0].lines) >= 3 * res.band_mean_dn.shape[1]


def test_flat_field_removes_fixed_pattern_in_every_band(demo):
    steps = demo.correction["fixed_pattern"]
    assert [s["n_frames"] for s in steps] == [4, 2]
    for s in steps:
        before = np.asarray(s["before"]["fpn_percent"])
        after = np.asarray(s["after"]["fpn_percent"])
        assert np.all(after < 0.75 * before), (before, after)
        assert s["improvement_percent_points"] > 0.3


def test_model_ffc_from_the_calibration_removes_fixed_pattern_too(demo):
    """The default of ``hsiffc correct`` (model_ffc from the calibration alone), measured on
    the same pixels: more than halves the pattern in every band (measured 0.40 / 0.43 % pooled
    against raw 1.04 / 0.98 % and two-point 0.51 / 0.47 %)."""
    for s in demo.correction["fixed_pattern"]:
        before = np.asarray(s["before"]["fpn_percent"])
        model = np.asarray(s["model_ffc"]["fpn_percent"])
        assert np.all(model < 0.6 * before), (before, model)
        assert s["model_improvement_percent_points"] > 0.4
    assert "model_ffc" in render_text(demo)


def test_render_text_names_both_measures(demo):
    text = render_text(demo)
    assert "level off below full scale" in text
    assert "fixed-pattern non-uniformity (EMVA 1288" in text and "eq. 6" in text


def test_fit_curve_recovers_known_parameters():
    from hsiffc.leakage import model

    t = np.linspace(1, 300, 30)
    y = model.response(t, 6.0, 0.02, 0.01, 32.0)
    f = fit_curve(t, y, 32.0)
    assert f["k"] == pytest.approx(6.0, rel=1e-4)
    assert f["saturation_dn"] == pytest.approx(float(model.dynamic_saturation_level(6.0, 0.02,
                                                                                    0.01)), abs=0.1)
    assert f["rms_dn"] < 1e-3 < f["rms_linear_dn"]
