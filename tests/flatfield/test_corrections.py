"""One implementation per correction: every stage gives exactly what its array function gives;
a frame knows the dark it lost; calibrations are objects; parameters and stage order are
checked when a pipeline is built, fitted or loaded."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hsiffc.spectral.bandstats import band_reduce
from hsiffc.calibrate import Calibration, calibrate
from hsiffc.data.dq import DQ
from hsiffc.errors import DataFormatError, ParameterError
from hsiffc.flatfield.two_point import two_point_correct
from hsiffc.data.frame import Frame, stack_mean
from hsiffc.io import read_sweep
from hsiffc.leakage.linearise import linearise
from hsiffc.data.params import validate_method
from hsiffc.flatfield.polynomial import polynomial_apply, polynomial_fit
from hsiffc.stages import Pipeline, check_stage, create, registry
from hsiffc.leakage.validity import alpha_table_of, validity_flags

T_MS = 32.25  # a training flat, a dark stack and a test frame share this exposure


@pytest.fixture(scope="module")
def frames(sample_cubes):
    train = (Frame.list_from_sweep(read_sweep(sample_cubes / "training_2900K.tif"))
             + Frame.list_from_sweep(read_sweep(sample_cubes / "darks.tif")))
    test = [f for f in Frame.list_from_sweep(read_sweep(sample_cubes / "test_2200K.tif"))
            if f.exposure_ms == T_MS]
    return train, test[0]


@pytest.fixture(scope="module")
def cal(sample_cubes):
    return calibrate(read_sweep(sample_cubes / "sweep_2900K.tif"))  # in memory, never saved


def _stack(train, kind, t=T_MS):
    return [f for f in train if f.kind == kind and f.exposure_ms == t]


@pytest.mark.filterwarnings(  # the fixture's flats saturate 4 % of band 3: the check says so
    "ignore::hsiffc.stages.refchecks.FlatSaturatedWarning")
@pytest.mark.parametrize("normalisation", ["paper", "mean_gain"])
def test_two_point_stage_after_dark_equals_the_array_function(frames, normalisation):
    train, test = frames
    pipe = Pipeline([("dark", create("dark")),
                     ("ffc", create("two_point_ffc", exposure_ms=T_MS,
                                    normalisation=normalisation))]).fit(train)
    out = pipe.transform(test)
    dark = stack_mean(_stack(train, "dark"))[0]
    flat, flat_dq = stack_mean(_stack(train, "light"))
    ref, ref_dq = two_point_correct(test.data, dark, flat, normalisation=normalisation,
                                    band_map=test.band_map(), dq=test.dq, flat_dq=flat_dq)
    assert np.array_equal(out.data, ref) and np.array_equal(out.dq, ref_dq)
    assert out.corrected_by == "two_point_ffc" and np.array_equal(out.dark_removed, dark)


@pytest.mark.parametrize("after_dark", [False, True])
def test_alpha_mask_equals_validity_flags(frames, cal, after_dark):
    train, test = frames
    steps = [("dark", create("dark"))] if after_dark else []
    pipe = Pipeline(steps + [("mask", create("alpha_mask", calibration=cal))]).fit(train)
    out = pipe.transform(test)
    dark = stack_mean(_stack(train, "dark"))[0] if after_dark else None
    alpha, dq = validity_flags(test.data, T_MS, cal, threshold_percent=12.0, dark=dark)
    assert np.array_equal(out.alpha, alpha) and np.array_equal(out.dq, test.dq | dq)
    assert np.isinf(alpha).sum() == ((dq & DQ.LEAKAGE) != 0)[np.isinf(alpha)].sum()


def test_polynomial_stage_equals_the_array_functions(frames):
    train, test = frames
    pipe = Pipeline([("dark", create("dark")), ("ffc", create("polynomial_ffc", order=2))])
    out = pipe.fit(train).transform(test)
    levels, dqs = [], []
    for t in (6.45, 12.9, 19.35, 25.8, 32.25):
        dark = stack_mean(_stack(train, "dark", t))[0]
        m, dq = stack_mean([f.replace(data=f.data - dark) for f in _stack(train, "light", t)])
        levels.append(m)
        dqs.append(dq | stack_mean(_stack(train, "dark", t))[1])
    fit = polynomial_fit(np.stack(levels), order=2, band_map=test.band_map(),
                         level_dq=np.stack(dqs))
    ref, ref_dq = polynomial_apply(test.data - stack_mean(_stack(train, "dark"))[0], fit)
    assert np.array_equal(out.data, ref) and np.array_equal(out.dq, test.dq | ref_dq)


def test_polynomial_ffc_pixel_dark_in_every_flat_gets_a_neutral_flagged_correction():
    gain = np.random.default_rng(0).uniform(0.9, 1.1, (8, 8))
    levels = np.stack([lv * gain for lv in (100.0, 200.0, 400.0)])
    levels[:, 3, 4] = 0.0  # a pixel that is 0 in every flat
    fit = polynomial_fit(levels, order=2)
    test = 250.0 * gain
    test[3, 4] = 250.0
    out, dq = polynomial_apply(test, fit)
    assert np.all(np.isfinite(out)) and out[3, 4] == 250.0
    assert dq[3, 4] & DQ.NO_FLAT and not dq[3, 4] & DQ.OUT_OF_DOMAIN
    assert np.count_nonzero(dq & DQ.NO_FLAT) == 1
    assert np.abs(out[dq == 0] / out[dq == 0].mean() - 1).max() < 0.01


def test_frame_knows_the_dark_it_lost_and_linearise_uses_it(frames, cal):
    train, test = frames
    dark = create("dark").fit(train)
    sub = dark.transform(test)
    assert sub.state() >= {"dark_subtracted", "response"} and "raw" not in sub.state()
    assert np.array_equal(sub.raw, test.data)  # what was removed is added back, exactly
    with pytest.raises(ValueError, match="no dark has been removed"):
        _ = test.signal
    lin = create("linearise", calibration=cal).fit([])
    k_raw = lin.light_rate(test)[0]
    k_sub = lin.light_rate(sub)[0]
    assert np.array_equal(k_raw, k_sub)  # the leakage acts on the raw response in both cases
    ref = linearise(test.data, T_MS, cal.a, cal.b, cal.dark, cal.dark_current,
                    full_scale_dn=1023)
    assert np.array_equal(k_raw, ref.light_rate)
    out = lin.transform(sub)
    with pytest.raises(ValueError, match="linearise"):
        _ = out.raw


def test_notebook_style_in_memory_calibration_round_trip(frames, cal, tmp_path, monkeypatch):
    train, test = frames
    assert cal.path is None
    pipe = Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=cal)),
                     ("ffc", create("two_point_ffc", calibration=cal))]).fit(train)
    first = pipe.transform(test)
    assert first.history[1]["params"]["calibration"] == {"identity": cal.identity, "path": None}
    pipe.save(tmp_path / "pipe.npz")
    calls = []
    monkeypatch.setattr(Calibration, "load", lambda *a, **k: calls.append(a))
    loaded = Pipeline.load(tmp_path / "pipe.npz")  # the calibration travels inside the file
    again = [loaded.transform(test) for _ in range(3)][-1]
    assert calls == []
    for field in ("data", "dq", "alpha", "dark_removed"):
        assert np.array_equal(getattr(again, field), getattr(first, field)), field
    assert loaded.named_steps["ffc"].calibration_product().identity == cal.identity


def test_calibration_file_is_read_once_and_identity_hashed_once(frames, cal, tmp_path,
                                                                 monkeypatch):
    train, test = frames
    path = cal.save(tmp_path / "cal.npz")
    pipe = Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=str(path)))]).fit(train)
    reads, hashes = [], []
    monkeypatch.setattr(Calibration, "load", lambda *a, **k: reads.append(a))
    for _ in range(3):
        out = pipe.transform(test)
    assert reads == [] and out.history[1]["params"]["calibration"]["path"] == str(path.resolve())
    assert pipe.named_steps["mask"].calibration.path == str(path.resolve())
    real = hashlib.sha256
    monkeypatch.setattr(hashlib, "sha256", lambda *a: hashes.append(1) or real(*a))
    fresh = Calibration(dict(cal.arrays), dict(cal.domain), cal.method)  # hashed when made
    assert fresh.identity == fresh.identity == cal.identity and len(hashes) == 1


def test_pipeline_order_is_checked_when_built_naming_both_steps(cal):
    cases = [
        ([("ffc", create("two_point_ffc")), ("dark", create("dark"))], "'dark' before 'ffc'"),
        ([("dark", create("dark")), ("again", create("dark"))], "'dark' before it takes"),
        ([("dark", create("dark")), ("ffc", create("two_point_ffc")),
          ("mask", create("alpha_mask", calibration=cal))], "put 'mask' before 'ffc'"),
        ([("cube", create("reconstruct")), ("mask", create("alpha_mask", calibration=cal))],
         "put 'mask' before 'cube'"),
        ([("poly", create("polynomial_ffc"))], "put a 'dark' step before it"),
    ]
    for steps, message in cases:
        with pytest.raises(ParameterError, match=message):
            Pipeline(steps)
    Pipeline([("dark", create("dark")), ("mask", create("alpha_mask", calibration=cal)),
              ("ffc", create("two_point_ffc", normalisation="mean_gain")),
              ("cube", create("reconstruct"))])


@pytest.mark.parametrize("value", ["twelve", -5, float("nan"), True])
def test_bad_parameter_fails_at_build_fit_and_load(frames, cal, value, tmp_path):
    train, _ = frames
    with pytest.raises(ParameterError, match=r"threshold_percent=.* is not valid; expected a "
                                             r"number > 0"):
        create("alpha_mask", calibration=cal, threshold_percent=value).fit(train)
    with pytest.raises(ParameterError, match="threshold_percent"):
        Pipeline([("mask", create("alpha_mask", calibration=cal, threshold_percent=value))])
    toml = tmp_path / "p.toml"
    text = json.dumps(value) if not isinstance(value, float) else "nan"
    toml.write_text(f'[[step]]\nstage = "dark"\n[[step]]\nstage = "alpha_mask"\n'
                    f'calibration = "cal.npz"\nthreshold_percent = {text}\n')
    cal.save(tmp_path / "cal.npz", overwrite=True)
    with pytest.raises(ParameterError, match=r"p\.toml.*threshold_percent"):
        Pipeline.from_toml(toml)


def test_pipeline_load_refuses_malformed_manifests(frames, tmp_path):
    train, _ = frames
    path = Pipeline([("dark", create("dark"))]).fit(train).save(tmp_path / "p.npz")
    with np.load(path) as npz:
        contents = {k: npz[k] for k in npz.files}
    good = json.loads(contents["manifest.json"].tobytes())
    bad_param = json.loads(json.dumps(good))
    bad_param["steps"][0]["params"]["average"] = "mode"
    for i, man in enumerate([{**good, "steps": "dark"}, {**good, "steps": [{"name": "x"}]},
                             {**good, "steps": [{**good["steps"][0], "params": [1]}]}, bad_param]):
        contents["manifest.json"] = np.frombuffer(json.dumps(man).encode(), np.uint8)
        np.savez(tmp_path / f"bad{i}.npz", **contents)
        with pytest.raises((DataFormatError, ParameterError), match=f"bad{i}.npz") as info:
            Pipeline.load(tmp_path / f"bad{i}.npz")
        assert "\n" not in str(info.value)
        expected = ParameterError if man is bad_param else DataFormatError
        assert isinstance(info.value, expected), info.value


def test_validate_method_and_band_reduce_conventions(cal):
    with pytest.raises(ParameterError, match="unknown alpha method 'exact'; valid: paper, model"):
        validate_method("exact", ("paper", "model"), "alpha method")
    bm = np.array([[0, 1], [0, 1]])
    stats = band_reduce(np.array([[1.0, 5.0], [3.0, 7.0]]), bm, np.array([[1, 0], [1, 0]], bool),
                        n_bands=3)
    assert stats[0] == 2.0 and np.isnan(stats[1]) and np.isnan(stats[2])
    # alpha tables turn "no statistic" into inf ("no alpha"), never NaN
    dark = np.full((1,) + cal.frame_shape, 0.0)
    table = alpha_table_of(dark, [10.0], cal)
    assert np.all(np.isinf(table.alpha)) and table.select(12.0).selected_ms.tolist() == [None] \
        or np.isnan(table.select(12.0).selected_ms).all()


@pytest.mark.filterwarnings(  # the fixture's flats saturate 4 % of band 3: the check says so
    "ignore::hsiffc.stages.refchecks.FlatSaturatedWarning")
def test_check_stage_prepares_dark_subtracted_frames_for_stages_that_need_them(frames):
    train, test = frames
    check_stage(create("two_point_ffc", exposure_ms=T_MS), train, test)


def test_pipeline_files_of_format_1_still_load(frames, cal, tmp_path):
    """Format 1 named calibrations by path only and kept the two-point flat mean per pixel."""
    train, test = frames
    cal_path = cal.save(tmp_path / "cal1.npz")
    pipe = Pipeline([("dark", create("dark")),
                     ("ffc", create("two_point_ffc", calibration=str(cal_path)))]).fit(train)
    expected = pipe.transform(test)
    path = pipe.save(tmp_path / "p.npz")
    with np.load(path) as npz:
        contents = {k: npz[k] for k in npz.files}
    man = json.loads(contents["manifest.json"].tobytes())
    man["format_version"] = 1
    man["steps"][1]["params"]["calibration"] = "cal1.npz"  # relative: found beside the file
    contents["ffc/flat_mean_"] = contents["ffc/flat_mean_"][test.band_map()]
    contents["manifest.json"] = np.frombuffer(json.dumps(man).encode(), np.uint8)
    np.savez(tmp_path / "v1.npz", **contents)
    again = Pipeline.load(tmp_path / "v1.npz").transform(test)
    assert np.array_equal(again.data, expected.data) and np.array_equal(again.dq, expected.dq)


DECLARED = [(registry.get(name), key) for name in registry.BUILTIN
            for key in registry.get(name).param_spec]


@settings(max_examples=60, deadline=None)
@given(value=st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                       st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                       st.lists(st.integers(), max_size=2)),
       pick=st.integers(0, 10**6))
def test_any_parameter_value_is_accepted_or_refused_in_one_line(value, pick):
    """Fuzz: every declared parameter of every built-in stage either accepts a value or raises
    ParameterError naming it - never another exception."""
    cls, key = DECLARED[pick % len(DECLARED)]
    stage = cls(**{key: value})
    try:
        stage.validate_params()
    except ParameterError as exc:
        assert f"{key}=" in str(exc) and "\n" not in str(exc)
    else:
        param = type(stage).param_spec[key]
        assert param.accepts(value)
        if param.kind in ("number", "integer") and value is not None:
            assert np.isfinite(value) and (param.low is None or value >= param.low)


def test_the_training_exposure_guide_shows_what_select_prints(cal, sample_cubes):
    """docs/guide/training-exposure.md quotes `hsiffc select` on the sample cubes: its rows are
    the table this calibration gives today (it went stale once, by 0.04 points)."""
    from pathlib import Path

    from hsiffc.leakage.validity import alpha_table

    guide = (Path(__file__).resolve().parents[2] / "docs" / "guide"
             / "training-exposure.md").read_text()
    block = guide.split("leakage percentage alpha (%)", 1)[1].split("```", 1)[0]
    quoted = [ln for ln in block.splitlines()[2:] if ln.strip() and ln.strip() != "..."]
    text = alpha_table(read_sweep(sample_cubes / "training_2900K.tif"), cal).select(12).to_text()
    assert len(quoted) >= 3 and all(ln in text.splitlines() for ln in quoted), (quoted, text)
