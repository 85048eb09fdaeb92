"""The ``filter`` stage (issue 51): registered OpenCV and scikit-image filters run band by band
(per mosaic position on a mosaic frame), DQ-aware, stateless, saved by name."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from hsiffc.data.dq import DQ
from hsiffc.data.frame import Frame
from hsiffc.data.mosaic import Mosaic
from hsiffc.data.params import Param
from hsiffc.errors import ParameterError
from hsiffc.io import read_sweep
from hsiffc.stages import Pipeline, check_stage, create
from hsiffc.stages.filter import FILTERS, FilterStage, get_filter, register_filter

OPENCV = ["gaussian", "median", "bilateral"]
SKIMAGE = ["total_variation", "nl_means"]


def _method(name):
    if name in SKIMAGE:
        pytest.importorskip("skimage", reason="scikit-image is not installed: "
                                              "pip install 'hsiffc[skimage]'")
    return name


def _cube(seed=0, shape=(32, 32, 4), level=1000.0, noise=20.0):
    rng = np.random.default_rng(seed)
    data = rng.normal(level, noise, shape).astype(np.float32)
    return Frame(data, np.zeros(shape, np.uint32), {"exposure_ms": 10.0, "bit_depth": 12})


def _mosaic_frame(seed=0, shape=(60, 60), n=3, offset=(0, 0)):
    rng = np.random.default_rng(seed)
    mosaic = Mosaic(np.arange(n * n).reshape(n, n), offset=offset)
    levels = np.arange(n * n, dtype=np.float32) * 300 + 500  # bands far apart in level
    data = (levels[mosaic.band_map(shape)] + rng.normal(0, 20, shape)).astype(np.float32)
    return Frame(data, np.zeros(shape, np.uint32),
                 {"exposure_ms": 10.0, "bit_depth": 12, "mosaic": mosaic})


@pytest.mark.parametrize("method", OPENCV + SKIMAGE)
def test_every_filter_denoises_a_noisy_flat_cube(method):
    f = _cube()
    out = create("filter", method=_method(method)).fit([f]).transform(f)
    assert out.data.dtype == np.float32 and out.data.shape == f.data.shape
    for b in range(f.data.shape[2]):
        assert out.data[:, :, b].std() < 0.8 * f.data[:, :, b].std(), method
    # DN kept: no rescaling of the level
    assert abs(float(out.data.mean()) - float(f.data.mean())) < 5


@pytest.mark.parametrize("method", OPENCV + SKIMAGE)
def test_a_flagged_outlier_does_not_spread_and_flags_are_carried(method):
    f = _cube(shape=(24, 24, 2))
    dq = f.dq.copy()
    dq[12, 12, 0] = DQ.DO_NOT_USE
    dq[3, 5, 1] = DQ.SATURATED
    calm = f.replace(dq=dq)
    data = f.data.copy()
    data[12, 12, 0] = 1e6
    hot = f.replace(data=data, dq=dq)
    stage = create("filter", method=_method(method)).fit([f])
    a, b = stage.transform(calm), stage.transform(hot)
    assert np.array_equal(a.dq, dq) and np.array_equal(b.dq, dq)  # flags carried unchanged
    diff = a.data != b.data
    assert diff.sum() == 1 and diff[12, 12, 0]  # only the flagged sample itself differs
    assert b.data[12, 12, 0] == np.float32(1e6)  # which keeps its input value
    assert b.data[3, 5, 1] == f.data[3, 5, 1]


@pytest.mark.parametrize("method, offset", [(m, (0, 0)) for m in OPENCV]
                         + [("gaussian", (1, 2)), ("median", (2, 1))])
def test_a_mosaic_frame_is_filtered_per_band_without_mixing_bands(method, offset):
    f = _mosaic_frame(offset=offset)
    out = create("filter", method=method).fit([f]).transform(f)
    band = f.band_map()
    for b in range(f.mosaic.n_bands):
        before, after = f.data[band == b], out.data[band == b]
        # each band keeps its own level (a 3x3 filter over the mosaic would mix 300 DN steps)
        assert abs(after.mean() - before.mean()) < 3 and after.std() < 0.8 * before.std()


def test_a_frame_without_a_mosaic_is_one_image():
    f = _mosaic_frame().replace(meta={"mosaic": None})
    out = create("filter", method="gaussian", params={"sigma": 2.0}).transform(f)
    # the bands' 300 DN steps are blurred together: the whole frame is one image
    assert out.data.std() < 0.8 * f.data.std() and out.corrected_by == "filter"


def test_stages_that_need_the_response_go_before_the_filter():
    with pytest.raises(ParameterError, match="needs the uncorrected sensor response"):
        Pipeline([("dark", create("dark")), ("denoise", create("filter")),
                  ("alpha", create("alpha_mask", calibration="cal.npz"))])


def test_params_are_checked_against_the_filters_own_declaration():
    with pytest.raises(ParameterError, match=r"filter 'gaussian' has no parameter 'sigm'; "
                                             r"did you mean 'sigma'\? valid: sigma"):
        create("filter", method="gaussian", params={"sigm": 2}).validate_params()
    with pytest.raises(ParameterError, match=r"filter 'median': size=1 is not valid"):
        Pipeline([("f", create("filter", method="median", params={"size": 1}))])
    with pytest.raises(ParameterError, match="expected a table"):
        create("filter", params=[1, 2]).validate_params()
    stage = create("filter", method="bilateral", params={"diameter": 7})
    assert stage.resolved()[1] == {"diameter": 7, "sigma_color": None, "sigma_space": 2.0}


def test_unknown_method_lists_the_valid_ones():
    with pytest.raises(ParameterError) as info:
        Pipeline([("f", create("filter", method="gausian"))])
    text = str(info.value)
    assert "\n" not in text and "did you mean 'gaussian'?" in text
    assert all(name in text for name in FILTERS)


def test_skimage_filters_name_the_extra_when_it_is_missing(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_skimage(name, *args, **kwargs):
        if name == "skimage" or name.startswith("skimage."):
            raise ImportError("No module named 'skimage'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_skimage)
    monkeypatch.delitem(sys.modules, "skimage", raising=False)
    for method in SKIMAGE:
        with pytest.raises(ParameterError, match=r"needs skimage, which is not installed: "
                                                 r"pip install 'hsiffc\[skimage\]'") as info:
            create("filter", method=method).validate_params()
        assert "\n" not in str(info.value)


@pytest.mark.parametrize("method", OPENCV + SKIMAGE)
def test_a_pipeline_with_the_stage_saves_and_loads_by_name(tmp_path, method):
    f = _cube(shape=(16, 16, 3))
    params = {"gaussian": {"sigma": 1.5}, "median": {"size": 5}}.get(method)
    pipe = Pipeline([("denoise", create("filter", method=_method(method),
                                        params=params))]).fit([f])
    expected = pipe.transform(f)
    path = pipe.save(tmp_path / "p.npz")
    again = Pipeline.load(path)
    step = again.named_steps["denoise"]
    assert isinstance(step, FilterStage) and step.get_params() == {"method": method,
                                                                   "params": params}
    out = again.transform(f)
    assert np.array_equal(out.data, expected.data) and np.array_equal(out.dq, expected.dq)
    entry = out.history[-1]
    assert entry["stage"] == "filter" and entry["params"]["method"] == method


def test_a_toml_step_denoises_before_reflectance(tmp_path):
    """The guide's example: dark, reconstruct, filter, reflectance from a TOML description."""
    (tmp_path / "p.toml").write_text(
        '[[step]]\nstage = "dark"\n\n[[step]]\nstage = "reconstruct"\nmethod = "bilinear"\n\n'
        '[[step]]\nname = "denoise"\nstage = "filter"\nmethod = "gaussian"\n'
        'params = { sigma = 1.0 }\n\n[[step]]\nstage = "reflectance"\nmethod = "ratio"\n'
        'panel = 0.99\n')
    pipe = Pipeline.from_toml(tmp_path / "p.toml")
    assert pipe.named_steps["denoise"].get_params() == {"method": "gaussian",
                                                        "params": {"sigma": 1.0}}
    rng = np.random.default_rng(3)
    mosaic = Mosaic.square(2)
    meta = {"exposure_ms": 10.0, "bit_depth": 12, "mosaic": mosaic}
    ok = np.zeros((32, 32), np.uint32)
    dark = [Frame(rng.normal(64, 2, (32, 32)).astype(np.float32), ok, {**meta, "kind": "dark"})
            for _ in range(4)]
    white = [Frame(rng.normal(2064, 20, (32, 32)).astype(np.float32), ok, meta)
             for _ in range(8)]
    scene = Frame(rng.normal(1064, 30, (32, 32)).astype(np.float32), ok, meta)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reference checks: not what is tested here
        pipe.fit(dark + white)
        out = pipe.transform(scene)
        plain = Pipeline([("dark", create("dark")),
                          ("reconstruct", create("reconstruct", method="bilinear")),
                          ("reflectance", create("reflectance", method="ratio", panel=0.99))]
                         ).fit(dark + white).transform(scene)
    assert out.is_cube and abs(float(np.median(out.data)) - 0.99 * 0.5) < 0.02
    assert out.data.std() < plain.data.std()


def test_plugins_register_filters(tmp_path):
    calls = []

    def box(image, *, k):
        calls.append(image.shape)
        import cv2

        return cv2.blur(image, (int(k), int(k)))

    try:
        register_filter("test_box", box, params={"k": Param("integer", low=1)},
                        defaults={"k": 3}, summary="box blur", source="test")
        f = _cube(shape=(16, 16, 2))
        pipe = Pipeline([("f", create("filter", method="test_box", params={"k": 5}))]).fit([f])
        out = pipe.transform(f)
        assert calls == [(16, 16), (16, 16)] and out.data.std() < f.data.std()
        again = Pipeline.load(pipe.save(tmp_path / "p.npz")).transform(f)
        assert np.array_equal(again.data, out.data)
        with pytest.raises(ParameterError, match="has no parameter 'kk'"):
            create("filter", method="test_box", params={"kk": 5}).validate_params()
        with pytest.raises(ParameterError, match="built-in"):
            register_filter("gaussian", box)
        with pytest.raises(ParameterError, match="no default"):
            register_filter("test_nodefault", box, params={"k": Param("integer")})
        # a filter that writes into its image never changes the frame it was given
        register_filter("test_inplace", lambda im: np.add(im, 1, out=im))
        plain = f.replace(data=np.ascontiguousarray(f.data[:, :, 0]), dq=f.dq[:, :, 0])
        before = plain.data.copy()
        shifted = create("filter", method="test_inplace").transform(plain)
        assert np.array_equal(plain.data, before)
        assert np.array_equal(shifted.data, before + 1)
    finally:
        FILTERS.pop("test_box", None)
        FILTERS.pop("test_inplace", None)
    with pytest.raises(ParameterError, match="not a registered filter"):
        get_filter("test_box")


def test_filters_of_installed_packages_load_from_their_entry_point(monkeypatch):
    """A module declared under the entry-point group hsiffc.filters is imported when a name
    is not found (it registers its filters); a broken one warns and hsiffc goes on."""
    from hsiffc.stages import filter as filter_module
    from hsiffc.stages.registry import PluginWarning

    class EntryPoint:
        def __init__(self, value, load):
            self.value, self.load = value, load

    def good():
        register_filter("test_ep_filter", lambda im: im, summary="identity", source="test")

    def bad():
        raise ImportError("no such module")

    monkeypatch.setattr("importlib.metadata.entry_points",
                        lambda group: [EntryPoint("broken_pkg", bad),
                                       EntryPoint("good_pkg", good)]
                        if group == "hsiffc.filters" else [])
    monkeypatch.setattr(filter_module, "_loaded_plugins", False)
    try:
        with pytest.warns(PluginWarning, match="broken_pkg"):
            assert get_filter("test_ep_filter").source == "test"
    finally:
        FILTERS.pop("test_ep_filter", None)


def test_a_pipeline_file_never_names_an_import_path(tmp_path):
    import json

    f = _cube(shape=(8, 8, 2))
    path = Pipeline([("f", create("filter", method="median"))]).fit([f]).save(tmp_path / "p.npz")
    with np.load(path) as npz:
        man = json.loads(npz["manifest.json"].tobytes())
    assert man["steps"][0]["stage"] == "filter"
    assert man["steps"][0]["params"] == {"method": "median", "params": None}
    assert man["steps"][0]["state"] == {"fitted_": True}


@pytest.mark.parametrize("method", OPENCV + SKIMAGE)
def test_the_contract_helper_passes(sample_cubes, method):
    train = (Frame.list_from_sweep(read_sweep(sample_cubes / "training_2900K.tif"))[:3]
             + Frame.list_from_sweep(read_sweep(sample_cubes / "darks.tif"))[:3])
    test = Frame.list_from_sweep(read_sweep(sample_cubes / "test_2200K.tif"))[0]
    params = {"patch_distance": 2} if method == "nl_means" else None  # quicker on full frames
    check_stage(create("filter", method=_method(method), params=params), train, test)


def test_the_stage_is_listed_by_hsiffc_stages():
    out = subprocess.run([sys.executable, "-m", "hsiffc", "stages"], capture_output=True,
                         text=True, check=True).stdout
    assert "filter" in out and "filters of the 'filter' stage" in out
    assert "  gaussian " in out and "sigma=1.0" in out
