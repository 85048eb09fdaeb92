"""Third-party stages: discovery through the entry point, broken plugins, and the example
plugin ``plugins/hsiffc-hotpixel`` (hot/dead pixel repair from same-band neighbours).

Measured on the 128 x 128 simulated sensor below (seed 11, 1 % hot, 1 % dead, darks of 5
frames at 200 ms and 10 ms, flats of 5 frames at 10 ms under lamp A): 193 of 193 hot pixels
and 159 of 159 dead pixels found, no false detection (recall and precision 1.0); the robust
sigma of the dark residual is 2.2 DN against a hot excess of about 400 DN. The repaired flat's
mean per-band non-uniformity (std/mean) is 1.82 % against 1.83 % over unaffected pixels only
(9.1 % before repair). On a lamp B scene (band levels 139-435 DN) the same-band repair is within
7.6 DN of the band level at every defect (median 1.6 DN, pixel noise 3.6 DN), whereas a 3x3
median is off by 133 DN (median, up to 207 DN) because it mixes bands.
"""

from __future__ import annotations

import importlib.metadata
import textwrap

import numpy as np
import pytest
from scipy.ndimage import median_filter

from hsiffc.data.dq import DQ
from hsiffc.data.frame import Frame
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor, SensorParams
from hsiffc.stages import Pipeline, check_stage, create, describe, get, registry
from hsiffc.stages.registry import PluginWarning

PLUGIN_DIST = "hsiffc-hotpixel"
INSTALL = ("python3 -m pip install -e plugins/hsiffc-hotpixel (the README's test command "
           "installs it)")


@pytest.fixture(scope="module")
def plugin_cls():
    try:
        importlib.metadata.version(PLUGIN_DIST)
        return get("hot_pixel_repair")
    except (importlib.metadata.PackageNotFoundError, KeyError) as exc:
        pytest.fail(f"the example plugin is not installed ({exc}); run {INSTALL}")


def _frames(sensor, cap, kind):
    return cap.to_frames(kind)


@pytest.fixture(scope="module")
def defective():
    """A 128 x 128 sensor with 1 % hot and 1 % dead pixels and its training frames."""
    sensor = MosaicSensor((128, 128), seed=11,
                          params=SensorParams(hot_fraction=0.01, dead_fraction=0.01))
    flats = sensor.capture(10.0, "lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2["training"],
                           n_frames=5)
    train = (_frames(sensor, sensor.capture(200.0, None, n_frames=5), "dark")
             + _frames(sensor, flats, "light")
             + _frames(sensor, sensor.capture(10.0, None, n_frames=5), "dark"))
    return sensor, train


# -- discovery -----------------------------------------------------------------------------------
def test_plugin_discovered_through_entry_point(plugin_cls):
    import hsiffc_hotpixel

    assert plugin_cls is hsiffc_hotpixel.HotPixelRepair
    rows = {r["name"]: r for r in describe()}
    row = rows["hot_pixel_repair"]
    version = importlib.metadata.version(PLUGIN_DIST)
    assert version == "0.1.0"
    assert row["source"] == f"{PLUGIN_DIST} {version}"
    assert row["status"] == "ok" and row["target"] == "hsiffc_hotpixel:HotPixelRepair"
    assert row["summary"].startswith("Detect hot and dead pixels")
    assert create("hot_pixel_repair", hot_sigma=8.0).hot_sigma == 8.0


def _fake_distribution(tmp_path, name, version, lines):
    # kept off sys.path: only the patched entry_points below sees it
    info = tmp_path / "metadata" / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text(f"[{registry.GROUP}]\n" + "\n".join(lines) + "\n")
    return importlib.metadata.PathDistribution(info)


def _install_fake(monkeypatch, dist):
    real = registry.entry_points
    extra = list(dist.entry_points.select(group=registry.GROUP))

    def fake(**kwargs):
        return list(real(**kwargs)) + extra

    monkeypatch.setattr(registry, "entry_points", fake)


def test_broken_plugin_warns_and_is_marked(tmp_path, monkeypatch):
    (tmp_path / "hsiffc_raises_on_import.py").write_text(
        "raise ImportError('needs libfoo, which is not installed')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    dist = _fake_distribution(tmp_path, "hsiffc-broken", "0.3.0", [
        "missing_module = hsiffc_no_such_module_9f3:Stage",
        "raises_on_import = hsiffc_raises_on_import:Stage"])
    _install_fake(monkeypatch, dist)
    for name in ("missing_module", "raises_on_import"):
        with pytest.warns(PluginWarning, match=r"hsiffc-broken 0\.3\.0"):
            with pytest.raises(KeyError, match="failed to load"):
                get(name)
    rows = {r["name"]: r for r in describe()}  # no crash, no warning escapes
    assert rows["missing_module"]["source"] == "hsiffc-broken 0.3.0"
    assert rows["missing_module"]["status"].startswith("broken:")
    assert "hsiffc_no_such_module_9f3" in rows["missing_module"]["status"]
    assert "libfoo" in rows["raises_on_import"]["status"]
    assert rows["dark"]["status"] == "ok"  # the others still load


def test_plugin_cannot_shadow_builtin(tmp_path, monkeypatch):
    dist = _fake_distribution(tmp_path, "hsiffc-evil", "1.0", ["dark = os:getcwd"])
    _install_fake(monkeypatch, dist)
    with pytest.warns(PluginWarning, match="hsiffc-evil 1.0"):
        cls = get("dark")
    assert cls.__module__ == "hsiffc.stages.dark"


# -- the example plugin on a simulated sensor -----------------------------------------------------
def test_detection_against_simulator_truth(plugin_cls, defective):
    sensor, train = defective
    stage = plugin_cls().fit(train)
    hot, dead = stage.hot_.astype(bool), stage.dead_.astype(bool)
    # every simulated hot pixel has a large dark excess: 2 DN/ms x 200 ms, >> 6 sigma
    excess = (sensor.dark_current - np.median(sensor.dark_current)) * 200.0
    assert excess[sensor.hot].min() > 20 * stage.sigma_dn_
    figures = {}
    for label, found, truth in (("hot", hot, sensor.hot), ("dead", dead, sensor.dead)):
        tp = int((found & truth).sum())
        figures[label] = (tp / truth.sum(), tp / max(found.sum(), 1))
        assert truth.sum() > 100
    assert figures["hot"][0] >= 0.95 and figures["hot"][1] >= 0.95, figures
    assert figures["dead"][0] >= 0.95 and figures["dead"][1] >= 0.95, figures


def _band_nonuniformity(img, band, mask):
    return np.mean([img[(band == b) & mask].std() / img[(band == b) & mask].mean()
                    for b in range(int(band.max()) + 1)])


def test_repaired_flat_uniformity(plugin_cls, defective):
    sensor, train = defective
    stage = plugin_cls().fit(train)
    cap = sensor.capture(10.0, "lamp A", irradiance_w_m2=PAPER_LIGHT_W_M2["training"], seed=3)
    flat = _frames(sensor, cap, "light")[0]
    band, defects = sensor.band_map, sensor.hot | sensor.dead
    clean = _band_nonuniformity(flat.data, band, ~defects)  # unaffected pixels only
    everything = np.ones_like(defects)
    before = _band_nonuniformity(flat.data, band, everything)
    after = _band_nonuniformity(stage.transform(flat).data, band, everything)
    assert before > 3 * clean  # dead (and hot) pixels dominate the raw flat's spread
    assert after < 1.05 * clean, (clean, before, after)


def test_same_band_repair_beats_3x3_median_on_a_mosaic(plugin_cls, defective):
    sensor, train = defective
    stage = plugin_cls().fit(train)
    # lamp B: the 8 bands differ in level by a factor of ~4
    cap = sensor.capture(16.125, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"], seed=4)
    frame = _frames(sensor, cap, "light")[0]
    band, defects = sensor.band_map, sensor.hot | sensor.dead
    level = np.array([np.median(cap.expected_dn[(band == b) & ~defects])
                      for b in range(8)])[band]
    assert level.max() > 3 * (level.min() - 32)  # a scene where bands really differ
    same = np.abs(stage.transform(frame).data - level)[defects]
    naive = np.abs(median_filter(frame.data, size=3, mode="nearest") - level)[defects]
    noise = np.abs(frame.data - level)[~defects]
    assert np.median(same) < 2 * np.median(noise) and same.max() < 5 * np.median(noise)
    assert np.median(naive) > 10 * np.median(same)


def test_plugin_passes_check_stage_and_pipeline_round_trip(plugin_cls, defective, tmp_path):
    sensor, train = defective
    check_stage(plugin_cls(), train, train[5])
    pipe = Pipeline([("defects", plugin_cls()), ("dark", create("dark"))]).fit(train)
    out = pipe.transform(train[5])
    assert np.all(out.dq[sensor.hot] & DQ.HOT) and np.all(out.dq[sensor.dead] & DQ.DEAD)
    # the dark stage learnt from repaired darks: hot pixels come out at the band's level
    band = sensor.band_map
    good = ~(sensor.hot | sensor.dead)
    level = np.array([np.median(out.data[(band == b) & good]) for b in range(8)])[band]
    assert np.abs(out.data - level)[sensor.hot].max() < 0.1 * level.min()
    path = pipe.save(tmp_path / "pipe.npz")
    again = Pipeline.load(path)  # resolved by the registered name
    assert again.named_steps["defects"].n_hot_ == int(sensor.hot.sum())
    assert np.array_equal(again.transform(train[5]).data, out.data)
    assert [h["stage"] for h in out.history] == ["hot_pixel_repair", "dark"]


def test_write_your_own_stage_example(tmp_path, monkeypatch):
    """The minimal plugin of docs_golden.md: a module plus an entry point."""
    (tmp_path / "my_scale_plugin.py").write_text(textwrap.dedent('''
        from hsiffc.stages import Stage

        class Scale(Stage):
            """Multiply every pixel by a constant."""
            name = "scale"
            stateless = True

            def __init__(self, *, factor=1.0):
                self.factor = factor

            def transform(self, frame):
                return frame.replace(data=frame.data * self.factor)
        '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    dist = _fake_distribution(tmp_path, "my-scale-plugin", "0.0.1",
                              ["scale = my_scale_plugin:Scale"])
    _install_fake(monkeypatch, dist)
    frame = Frame.from_raw(np.ones((4, 4)), exposure_ms=1.0, bit_depth=10)
    check_stage(create("scale", factor=2.0), [frame], frame)
    assert {r["name"]: r for r in describe()}["scale"]["source"] == "my-scale-plugin 0.0.1"
