"""A campaign through ``hsiffc correct`` (issue 51): every warning reaches the file it is
about (printed with its name, in --json, in the provenance, counted in the summary), and a
folder's outputs are replaced only by the same job or with --overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.data.mosaic import Mosaic
from hsiffc.io.corrected import read_provenance
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.spectral import imec_4x4_visible

LIGHT = PAPER_LIGHT_W_M2["training"]
SIDE = '[defaults]\nbit_depth = 10\nmosaic = "4x4"\nexposure_ms = 12.0\n'
BRIGHT = "SceneBrighterThanReferenceWarning"


def _capture(sensor, rho, n, seed, dark=False):
    n_l = len(sensor.bands.wavelengths_nm)
    return sensor.capture(12.0, None if dark else "lamp A", irradiance_w_m2=LIGHT, n_frames=n,
                          reflectance=np.full(n_l, rho), seed=seed).frames


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Plain camera TIFFs with a sidecar: a dark, a white panel recorded in shade (reflectance
    0.1, said to be 0.99), two scenes of reflectance 0.6 (each some 6x brighter than the
    panel), a reflectance pipeline and a two-point pipeline fitted on them."""
    root = tmp_path_factory.mktemp("campaign")
    bands = imec_4x4_visible()
    sensor = MosaicSensor((32, 48), bands=bands,
                          mosaic=Mosaic.square(4, wavelengths_nm=bands.centres_nm), seed=6)
    refs, scenes = root / "refs", root / "scenes"
    refs.mkdir()
    scenes.mkdir()
    for i, f in enumerate(_capture(sensor, 0, 8, 1, dark=True)):
        tifffile.imwrite(refs / f"dark_{i:02d}.tif", f)
    for i, f in enumerate(_capture(sensor, 0.1, 8, 2)):
        tifffile.imwrite(refs / f"white_{i:02d}.tif", f)
    for i in range(2):
        tifffile.imwrite(scenes / f"scene_{i}.tif", _capture(sensor, 0.6, 1, 3 + i)[0])
    (refs / "hsiffc.toml").write_text(SIDE)
    (scenes / "hsiffc.toml").write_text(SIDE)
    darks = [str(p) for p in sorted(refs.glob("dark_*"))]
    whites = [str(p) for p in sorted(refs.glob("white_*"))]
    assert main(["reflectance", "fit", "--dark", *darks, "--white", *whites, "--panel",
                 "0.99", "-o", str(root / "refl.npz")]) == 0
    (root / "two.toml").write_text('[[step]]\nname = "dark"\nstage = "dark"\n\n[[step]]\n'
                                   'name = "ffc"\nstage = "two_point_ffc"\nexposure_ms = 12.0\n')
    assert main(["fit", str(root / "two.toml"), "--dark", *darks, "--flat", *whites, "-o",
                 str(root / "two.npz")]) == 0
    return {"root": root, "scenes": scenes, "refl": root / "refl.npz",
            "two": root / "two.npz"}


def _correct(campaign, out, *extra, pipeline="refl"):
    return main(["correct", "--pipeline", str(campaign[pipeline]), str(campaign["scenes"]),
                 "-o", str(out), *map(str, extra)])


def test_every_scene_warning_reaches_its_file(campaign, tmp_path, capsys):
    """Two scenes brighter than the panel: a line for each, naming it, even with -q; both
    in the summary (a count per class and the files), in --json and in each provenance."""
    capsys.readouterr()
    out = tmp_path / "out"
    assert _correct(campaign, out, "-q", "--json", tmp_path / "s.json") == 0
    cap = capsys.readouterr()
    lines = [x for x in cap.err.splitlines() if "brighter than the white reference" in x]
    assert len(lines) == 2, cap.err
    assert "scene_0.tif" in lines[0] and "scene_1.tif" in lines[1]
    assert f"{BRIGHT}: 2 files (scene_0.tif, scene_1.tif)" in cap.out
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["warnings"][BRIGHT] == {"count": 2, "files": ["scene_0.tif", "scene_1.tif"]}
    for r in doc["results"]:
        (w,) = [w for w in r["warnings"] if w["class"] == BRIGHT]
        assert "brighter" in w["message"] and w["figures"]["fraction_above_max"] > 0.5
        assert w["figures"]["median"] > 1.5 and w["count"] == 1  # one frame: one warning
        prov = read_provenance(out / r["rel"].replace(".tif", ".reflectance.tif"))
        assert [p["class"] for p in prov["warnings"]] == [w["class"] for w in r["warnings"]]


def test_a_resumed_campaign_still_lists_its_warnings(campaign, tmp_path, capsys):
    """Outputs skipped as up to date keep the warnings recorded when they were made (summary
    and --json); --fail-on-warning fails them too, the outputs kept."""
    out = tmp_path / "out"
    assert _correct(campaign, out, "-q") == 0
    capsys.readouterr()
    assert _correct(campaign, out, "-q", "--json", tmp_path / "s.json") == 0
    text = capsys.readouterr().out
    assert "2 skipped" in text and f"{BRIGHT}: 2 files (scene_0.tif, scene_1.tif)" in text
    doc = json.loads((tmp_path / "s.json").read_text())
    assert all(r["warnings"][0]["run"] == "earlier" for r in doc["results"])
    before = {p.name: p.read_bytes() for p in out.glob("*.reflectance.tif")}
    assert _correct(campaign, out, "-q", "--fail-on-warning", "all") == 1
    text = capsys.readouterr().out
    assert "recorded when the output was made" in text and "the output is kept" in text
    assert {p.name: p.read_bytes() for p in out.glob("*.reflectance.tif")} == before


def test_a_warning_class_can_fail_the_file(campaign, tmp_path, capsys):
    out = tmp_path / "out"
    assert _correct(campaign, out, "-q", "--fail-on-warning", "ReflectanceWarning") == 1
    text = capsys.readouterr().out
    assert "failed:" in text and f"{BRIGHT} (--fail-on-warning)" in text
    assert not list(out.glob("*.reflectance.tif"))  # no output written for a failed file
    assert _correct(campaign, out, "--fail-on-warning", "SceneBrighterThanReferenceWarnin") == 2
    err = capsys.readouterr().err
    assert f"did you mean '{BRIGHT}'" in err and len(err.strip().splitlines()) == 1


def _state(folder):
    """Every file but the folder's lock (which each run takes): inode, time, bytes."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(folder.iterdir()) if p.is_file() and p.name != ".hsiffc.lock"}


def test_another_jobs_outputs_are_not_replaced_unasked(campaign, tmp_path, capsys):
    """Reflectance outputs, then the same pipeline with other input options (another job:
    its fingerprint covers them) into the same folder: refused in one line naming the
    existing job (rc 2), the folder unchanged; the same job resumes; --overwrite replaces
    them. A two-point pipeline's outputs are named .corrected.tif: written beside the
    reflectance products, which stay as they were."""
    out = tmp_path / "out"
    assert _correct(campaign, out, "-q") == 0
    before = _state(out)
    capsys.readouterr()
    assert _correct(campaign, out, "-q", "--bit-depth", "10") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "already written by another job" in err
    assert "pipeline refl.npz (dark, reflectance" in err and "--overwrite" in err
    assert _state(out) == before
    assert _correct(campaign, out, "-q") == 0  # the same job: a resume (skipped)
    assert "2 skipped" in capsys.readouterr().out and _state(out) == before
    assert _correct(campaign, out, "-q", pipeline="two") == 0
    assert read_provenance(out / "scene_0.corrected.tif")["pipeline"]["path"].endswith(
        "two.npz")
    assert {k: v for k, v in _state(out).items() if k in before} == before
    assert _correct(campaign, out, "-q", "--overwrite", "--bit-depth", "10") == 0
    prov = read_provenance(out / "scene_0.reflectance.tif")
    assert prov["pipeline"]["input_overrides"] == {"bit_depth": "10"}


def test_input_hygiene_in_a_scene_folder(campaign, tmp_path, capsys):
    """A dark frame (its metadata says dark), a .txt and a .jpg among the scenes: the dark is
    left out, and all three are listed in the summary and --json."""
    import shutil

    from hsiffc.data.sweep import Sweep
    from hsiffc.io import read_sweep, write_sweep

    scenes = tmp_path / "scenes"
    shutil.copytree(campaign["scenes"], scenes)
    dark = read_sweep(campaign["root"] / "refs" / "dark_00.tif")  # metadata from the sidecar
    write_sweep(scenes / "dark_cap.tif", Sweep(dark.data, [12.0], ["dark"], 10,
                                               mosaic=dark.mosaic, source="dark"))
    (scenes / "notes.txt").write_text("lens cap on for dark_cap")
    (scenes / "preview.jpg").write_bytes(b"\xff\xd8\xff\xe0")
    capsys.readouterr()
    assert main(["correct", "--pipeline", str(campaign["refl"]), str(scenes), "-o",
                 str(tmp_path / "out"), "-q", "--json", str(tmp_path / "s.json")]) == 0
    text = capsys.readouterr().out
    assert "left out 1 files of dark frames" in text and "dark_cap.tif" in text
    assert "not read: 2 files" in text and "notes.txt" in text and "preview.jpg" in text
    assert not (tmp_path / "out" / "dark_cap.reflectance.tif").exists()
    assert (tmp_path / "out" / "scene_1.reflectance.tif").exists()
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["left_out"] == ["dark_cap.tif"]
    assert sorted(p.rsplit("/", 1)[-1] for p in doc["unread"]) == ["notes.txt", "preview.jpg"]


def test_a_misspelt_table_in_a_pipeline_file_is_refused(campaign, tmp_path, capsys):
    toml = tmp_path / "p.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n\n[[stepp]]\nname = "ffc"\n'
                    'stage = "two_point_ffc"\n')
    refs = campaign["root"] / "refs"
    assert main(["fit", str(toml), "--dark", str(refs / "dark_00.tif"), "-o",
                 str(tmp_path / "p.npz")]) == 2
    err = capsys.readouterr().err
    assert "unknown table or key 'stepp'" in err and "did you mean 'step'" in err
    assert not (tmp_path / "p.npz").exists()


def test_an_exposure_in_seconds_gets_a_unit_hint_and_cli_options(campaign, tmp_path, capsys):
    """A dark pipeline fitted at 12 ms, a scene said to be at 0.012 ms: the file fails with
    the unit's hint, and the fix it suggests is the command line's --calibration FILE."""
    (tmp_path / "d.toml").write_text('[[step]]\nname = "dark"\nstage = "dark"\n')
    refs = campaign["root"] / "refs"
    assert main(["fit", str(tmp_path / "d.toml"), "--dark", str(refs / "dark_00.tif"), "-o",
                 str(tmp_path / "d.npz")]) == 0
    scene = tmp_path / "scene.tif"  # no sidecar: its metadata from the command line
    scene.write_bytes((campaign["scenes"] / "scene_0.tif").read_bytes())
    assert main(["correct", "--pipeline", str(tmp_path / "d.npz"), str(scene), "-o",
                 str(tmp_path / "out"), "-q", "--exposure-ms", "0.012", "--bit-depth", "10",
                 "--mosaic", "4x4"]) == 1
    text = capsys.readouterr().out
    assert "no master dark at 0.012 ms (only at 12 ms)" in text
    assert "was the exposure given in seconds?" in text
    assert "--calibration FILE" in text and "calibration=\"" not in text


# -- the fit's frame contract --------------------------------------------------------------------

def test_a_fitted_pipeline_records_and_checks_its_frames(campaign, tmp_path, capsys):
    """The manifest records what the pipeline was fitted on; frames given another mosaic or
    bit depth fail per file with one line naming the option to fix."""
    from hsiffc.stages import Pipeline

    pipe = Pipeline.load(campaign["two"])
    rec = pipe.fitted_on
    assert rec["shape"] == [32, 48] and rec["bit_depth"] == 10 and rec["dtype"] == "uint16"
    assert rec["mosaic_option"] == "4x4" and rec["exposure_ms"] == [12.0, 12.0]
    scene = tmp_path / "scene.tif"  # no sidecar: metadata from the command line
    scene.write_bytes((campaign["scenes"] / "scene_0.tif").read_bytes())
    base = ["correct", "--pipeline", str(campaign["two"]), str(scene), "-q",
            "--exposure-ms", "12"]
    assert main([*base, "-o", str(tmp_path / "a"), "--bit-depth", "10", "--mosaic", "2x2"]) == 1
    text = capsys.readouterr().out
    assert "scene.tif: mosaic 2x2 (W x H), but the pipeline was fitted on frames of mosaic " \
           "4x4 (W x H): give --mosaic 4x4" in text
    assert main([*base, "-o", str(tmp_path / "b"), "--bit-depth", "12", "--mosaic", "4x4"]) == 1
    text = capsys.readouterr().out
    assert "bit depth 12, but the pipeline was fitted on 10-bit frames" in text
    assert "give --bit-depth 10" in text
    assert main([*base, "-o", str(tmp_path / "c"), "--bit-depth", "10", "--mosaic", "4x4"]) == 0
    # the same check in Python, on the frame
    from hsiffc.data.frame import Frame

    frame = Frame.from_raw(np.zeros((32, 48), np.uint16), exposure_ms=12, bit_depth=12)
    with pytest.raises(ValueError, match="give --mosaic 4x4"):
        pipe.transform(frame)


def test_fit_refuses_a_reconstruct_step_without_a_mosaic(campaign, tmp_path, capsys):
    toml = tmp_path / "cube.toml"
    toml.write_text('[[step]]\nname = "dark"\nstage = "dark"\n\n[[step]]\nname = "cube"\n'
                    'stage = "reconstruct"\n')
    dark = tmp_path / "dark.tif"  # no sidecar: no mosaic
    dark.write_bytes((campaign["root"] / "refs" / "dark_00.tif").read_bytes())
    capsys.readouterr()
    assert main(["fit", str(toml), "--dark", str(dark), "--bit-depth", "10", "--exposure-ms",
                 "12", "-o", str(tmp_path / "cube.npz")]) == 2
    err = capsys.readouterr().err
    assert "step 'cube' (reconstruct) needs a mosaic layout" in err and "--mosaic" in err
    assert not (tmp_path / "cube.npz").exists()


# -- reference checks of the dark and two-point stages -------------------------------------------

def test_two_point_fit_checks_its_references(campaign, tmp_path, capsys):
    """Dark and flat swapped: "were the dark and flat swapped?"; one dim flat frame: too
    dark, with its numbers, and one frame; the fit still writes the pipeline."""
    refs = campaign["root"] / "refs"
    toml = campaign["root"] / "two.toml"
    darks = [str(p) for p in sorted(refs.glob("dark_*"))]
    whites = [str(p) for p in sorted(refs.glob("white_*"))]
    capsys.readouterr()
    assert main(["fit", str(toml), "--dark", *whites, "--flat", *darks, "-o",
                 str(tmp_path / "swapped.npz")]) == 0
    err = capsys.readouterr().err
    line = [x for x in err.splitlines() if "dark is above the flat" in x]
    assert line and "were the dark and flat swapped?" in line[0] and "16 of 16 bands" in line[0]
    assert main(["fit", str(toml), "--dark", *darks, "--flat", whites[0], "-o",
                 str(tmp_path / "dim.npz")]) == 0
    err = capsys.readouterr().err
    dim = [x for x in err.splitlines() if "too dark" in x]
    assert dim and "flat (12 ms) too dark in 16 of 16 bands" in dim[0] and "% of the range" \
        in dim[0]
    assert "one flat frame (12 ms): its noise cannot be measured" in err


def test_reference_warnings_carry_their_figures():
    import warnings

    from hsiffc.data.frame import Frame
    from hsiffc.data.mosaic import Mosaic
    from hsiffc.stages import create
    from hsiffc.stages.refchecks import DarkAboveFlatWarning, SingleReferenceFrameWarning

    mosaic = Mosaic.square(2)
    dark = Frame.from_raw(np.full((8, 8), 100, np.uint16), exposure_ms=5, bit_depth=10,
                          mosaic=mosaic, kind="dark")
    flat = Frame.from_raw(np.full((8, 8), 40, np.uint16), exposure_ms=5, bit_depth=10,
                          mosaic=mosaic)
    step = create("dark")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        step.fit([dark])
        create("two_point_ffc", exposure_ms=5).fit([step.transform(flat)])
    kinds = {type(w.message): w.message for w in caught}
    assert kinds[DarkAboveFlatWarning].figures["level_dn"] == [-60.0] * 4
    assert kinds[SingleReferenceFrameWarning].figures["n_frames"] == 1
