"""Hostile and unusual inputs, round three (issue 52): one test per cause.

Each test names the cause it covers; each failed before its fix.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.io.corrected import read_provenance
from test_hostile_inputs import sweep  # noqa: F401  (the module's simulated sweep + calibration)
from checks import one_line as _one_line  # the one checker of one-line errors
from testfiles import capped_cli, synthetic_imec_xml


# -- cause: the resume identity left out the metadata sources' content ---------------------------
def test_resume_redoes_an_output_whose_sidecar_changed(sweep, tmp_path, capsys):
    """A sidecar's exposure changed from 12 to 24 ms: the rerun redoes the file (it used to
    say "0 done, 1 skipped" and keep the old exposure); an unchanged rerun still skips, and a
    sidecar added next to the input later redoes it too."""
    from hsiffc.io import read_sweep

    data = read_sweep(sweep / "s.tif").data
    raw = tmp_path / "in"
    raw.mkdir()
    tifffile.imwrite(raw / "plain.tif", data, photometric="minisblack")
    side = raw / "hsiffc.toml"
    side.write_text("[defaults]\nexposure_ms = 12\nbit_depth = 10\n")
    out = tmp_path / "out"
    argv = ["correct", str(raw / "plain.tif"), "--calibration", str(sweep / "cal.npz"),
            "-o", str(out)]
    assert main(argv) == 0
    made = out / "plain.corrected.tif"
    assert read_provenance(made)["exposure"][0] == 12.0
    capsys.readouterr()
    assert main(argv) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out
    side.write_text("[defaults]\nexposure_ms = 24\nbit_depth = 10\n")
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "1 done, 0 skipped" in text
    assert read_provenance(made)["exposure"][0] == 24.0
    sources = read_provenance(made)["input"]["metadata_sources"]
    assert [src["path"] for src in sources] == [str(side)]
    # a sidecar that is gone: redone (here it fails, as the exposure is nowhere now)
    side.unlink()
    assert main(argv) == 1


def test_resume_redoes_an_envi_input_whose_data_file_changed(sweep, tmp_path, capsys):
    """An ENVI input named by its header: a new data file redoes it (the check compared the
    header's size and time only); its bytes are not hashed at each resume check."""
    from hsiffc.io import read_sweep

    data = read_sweep(sweep / "s.tif").data
    raw = tmp_path / "in"
    raw.mkdir()
    data.astype("<u2").tofile(raw / "c.img")
    n, h, w = data.shape
    (raw / "c.hdr").write_text(f"ENVI\nsamples = {w}\nlines = {h}\nbands = {n}\n"
                               "header offset = 0\ndata type = 12\ninterleave = bsq\n"
                               "byte order = 0\nbit depth = 10\nexposure time = 12\n"
                               "exposure time units = ms\n")
    argv = ["correct", str(raw / "c.hdr"), "--calibration", str(sweep / "cal.npz"),
            "-o", str(tmp_path / "out")]
    assert main(argv) == 0
    files = read_provenance(tmp_path / "out" / "c.corrected.tif")["input"]["data_files"]
    assert [f["path"] for f in files] == [str(raw / "c.img")]
    capsys.readouterr()
    assert main(argv) == 0 and "0 done, 1 skipped" in capsys.readouterr().out
    (data // 2).astype("<u2").tofile(raw / "c.img")
    os.utime(raw / "c.img", ns=(1, 1))
    assert main(argv) == 0 and "1 done, 0 skipped" in capsys.readouterr().out


# -- cause: hsiffc.dq.mask took bytes as integers, "" as no flag, and overflowed ------------------
from hypothesis import given, settings, strategies as st  # noqa: E402

from hsiffc.data.dq import DQ, DQ_DTYPE, bits, mask  # noqa: E402

_NAMES = [f.name for f in DQ if f]
_TOP = int(np.iinfo(DQ_DTYPE).max)
_DQ = np.arange(0, 1 << 12, dtype=DQ_DTYPE) * np.uint32(1048573)  # many bit patterns


def test_dq_mask_refuses_bytes_empty_expressions_and_values_past_32_bits():
    with pytest.raises(TypeError, match="decode"):
        mask(_DQ, b"DEAD")
    for empty in ("", " ", "|", " , + "):
        with pytest.raises(ValueError, match="name no flag"):
            mask(_DQ, empty, good=True)  # used to select every value
    for big in ("4294967296", 4294967296, "9" * 5000, -1):
        with pytest.raises(ValueError, match="32-bit"):
            mask(_DQ, big)  # an OverflowError before
    assert mask(_DQ, "4294967295").all() == (_DQ != 0).all()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(_NAMES), min_size=1, max_size=5),
       st.lists(st.sampled_from(["|", "+", ",", " | ", "||"]), min_size=5, max_size=5),
       st.booleans())
def test_dq_mask_of_names_is_the_or_of_their_bits(names, seps, lower):
    text = names[0] + "".join(sep + (n.lower() if lower else n)
                              for sep, n in zip(seps, names[1:]))
    want = 0
    for n in names:
        want |= int(DQ[n])
    assert bits(text) == want
    assert np.array_equal(mask(_DQ, text), (_DQ & np.uint32(want)) != 0)
    assert np.array_equal(mask(_DQ, text, good=True), (_DQ & np.uint32(want)) == 0)


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=-(1 << 70), max_value=1 << 70))
def test_dq_mask_of_integers_is_the_value_or_one_valueerror(value):
    for given_as in (value, str(value)):
        if 0 <= value <= _TOP:
            assert bits(given_as) == value
            assert np.array_equal(mask(_DQ, given_as), (_DQ & np.uint32(value)) != 0)
        else:
            with pytest.raises(ValueError) as err:  # never OverflowError
                mask(_DQ, given_as)
            assert "\n" not in str(err.value)


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=40), st.binary(max_size=10),
                 st.lists(st.one_of(st.sampled_from(_NAMES), st.integers(0, _TOP)), max_size=4)))
def test_dq_mask_of_any_expression_is_bits_in_range_or_one_line(flags):
    try:
        value = bits(flags)
    except (TypeError, ValueError) as exc:
        assert not isinstance(exc, OverflowError) and "\n" not in str(exc)
        assert not isinstance(flags, str) or not flags.strip(" |+,") or "DQ flag" in str(exc)
        return
    assert not isinstance(flags, bytes)
    assert 0 <= value <= _TOP
    mask(_DQ, flags)


# -- cause: plugin loading caught Exception only; a SystemExit ended the command with its code ----
def test_plugin_calling_sys_exit_on_import_fails_fit_in_one_line(
        sweep, tmp_path, monkeypatch, capsys):
    import importlib.metadata

    from hsiffc.stages import registry

    (tmp_path / "hsiffc_exits_on_import.py").write_text("import sys\nsys.exit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    info = tmp_path / "metadata" / "hsiffc_exits-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hsiffc-exits\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{registry.GROUP}]\nexits = hsiffc_exits_on_import:Stage\n")
    extra = list(importlib.metadata.PathDistribution(info).entry_points.select(
        group=registry.GROUP))
    real = registry.entry_points
    monkeypatch.setattr(registry, "entry_points", lambda **kw: list(real(**kw)) + extra)
    desc = tmp_path / "pipe.toml"
    desc.write_text('[[step]]\nname = "x"\nstage = "exits"\n')
    capsys.readouterr()
    rc = main(["fit", str(desc), str(sweep / "s.tif"), "-o", str(tmp_path / "p.npz")])
    err = capsys.readouterr().err
    assert rc != 0  # was 0: nothing written, no summary
    assert "sys.exit(0)" in err and "hsiffc-exits 1.0" in err
    assert not (tmp_path / "p.npz").exists()


def test_a_system_exit_inside_any_command_is_one_line_and_not_zero(monkeypatch, capsys):
    """The command's exception boundary: a SystemExit that is not hsiffc's own status."""
    import hsiffc.cli as cli

    parser = cli.build_parser()
    args = parser.parse_args(["info", "x.tif"])

    def exits(_args):
        raise SystemExit(0)

    monkeypatch.setattr(cli, "build_parser", lambda: _Fixed(parser, args, exits))
    assert main(["info", "x.tif"]) == 3
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "sys.exit(0)" in err


class _Fixed:
    """A parser that returns ``args`` with its command replaced by ``func``."""

    def __init__(self, parser, args, func):
        self.parser, self.args = parser, args
        self.args.func = func

    def parse_args(self, argv):
        return self.args


# -- cause: the ENVI header parser was quadratic and read any size --------------------------------
def test_envi_header_size_is_bounded_and_a_large_legal_header_parses(tmp_path, monkeypatch,
                                                                     capsys):
    """A 2 MB header (thousands of wavelengths, one long line without '=' handled in linear
    time) parses; over ``HSIFFC_MAX_HEADER_BYTES`` it is one line before it is read."""
    from hsiffc.io.envi import parse_envi_header

    np.zeros((2, 4, 5), np.uint16).tofile(tmp_path / "c.img")
    head = ("ENVI\nsamples = 5\nlines = 4\nbands = 2\nheader offset = 0\ndata type = 12\n"
            "interleave = bsq\nbyte order = 0\nbit depth = 12\nband names = {a, b}\n")
    notes = "notes = {" + ",\n".join(f"{i}.5" for i in range(250_000)) + "}\n"
    (tmp_path / "c.hdr").write_text(head + notes)
    assert (tmp_path / "c.hdr").stat().st_size > 2_000_000
    parsed = parse_envi_header(tmp_path / "c.hdr")
    assert len(parsed["notes"]) == 250_000 and parsed["band names"] == ["a", "b"]
    with open_source_ok(tmp_path / "c.hdr") as src:
        assert src.n_frames == 2
    monkeypatch.setenv("HSIFFC_MAX_HEADER_BYTES", "1000000")
    capsys.readouterr()
    assert main(["info", str(tmp_path / "c.hdr"), "--exposure-ms", "1"]) == 2
    line = _one_line(capsys, "c.hdr", "HSIFFC_MAX_HEADER_BYTES")
    assert "more than the limit of 1,000,000" in line


def open_source_ok(path):
    from hsiffc.io import open_source

    return open_source(path, exposure_ms=1.0)


# -- cause: a cube's size was not checked against HSIFFC_MAX_BYTES before it was allocated --------
def test_a_cube_over_the_byte_limit_is_refused_before_it_is_allocated(monkeypatch):
    from hsiffc.data.mosaic import Mosaic
    from hsiffc.errors import DataFormatError
    from hsiffc.reconstruct.demosaic import demosaic

    monkeypatch.setenv("HSIFFC_MAX_BYTES", "100000")  # the 64 x 64 x 64-band cube: 2 MiB
    with pytest.raises(DataFormatError, match="HSIFFC_MAX_BYTES") as err:
        demosaic(np.zeros((64, 64), np.float32), Mosaic.square(8))
    assert "64 bands" in str(err.value) and "\n" not in str(err.value)
    monkeypatch.delenv("HSIFFC_MAX_BYTES")
    assert demosaic(np.zeros((64, 64), np.float32), Mosaic.square(8)).cube.shape == (64, 64, 64)


# -- cause: only --mosaic WxH was checked against the frame; an IMEC pattern or a file's own ------
def test_a_tile_larger_than_the_frame_from_an_imec_pattern_or_the_file_is_one_line(tmp_path,
                                                                                     capsys):

    from hsiffc import Sweep
    from hsiffc.data.mosaic import Mosaic
    from hsiffc.io import write_sweep

    xml = synthetic_imec_xml(order=tuple(range(900)))
    xml = xml.replace("<pattern_width>2</pattern_width><pattern_height>2</pattern_height>",
                      "<pattern_width>30</pattern_width><pattern_height>30</pattern_height>")
    xml = xml.replace('nr_elements="4"><data>' + ", ".join(["0.01"] * 4),
                      'nr_elements="900"><data>' + ", ".join(["0.01"] * 900))
    (tmp_path / "big.xml").write_text(xml)
    tifffile.imwrite(tmp_path / "raw.tif", np.zeros((2, 32, 64), np.uint16),
                     photometric="minisblack")
    own = Sweep(np.zeros((2, 8, 8), np.uint16), exposure_ms=[1.0, 1.0], kind=["light"] * 2,
                bit_depth=10, mosaic=Mosaic.rectangular(16, 16))
    write_sweep(tmp_path / "own.tif", own)
    capsys.readouterr()
    assert main(["info", str(tmp_path / "raw.tif"), "--exposure-ms", "1", "--bit-depth", "10",
                 "--mosaic", str(tmp_path / "big.xml")]) == 2
    _one_line(capsys, "big.xml", "30 x 30", "larger than its filter area (60 x 28")
    assert main(["info", str(tmp_path / "own.tif")]) == 2
    _one_line(capsys, "own.tif", "16 x 16", "larger than the frames (8 x 8")


# -- cause: quicklook --frame past the file's frames was an internal error -----------------------
def test_a_frame_out_of_range_is_one_line(tmp_path, capsys):
    from hsiffc.errors import ParameterError
    from hsiffc.io.corrected import CorrectedWriter, read_corrected

    path = tmp_path / "f.corrected.tif"
    writer = CorrectedWriter(path, {"source": "example"}, n_frames=2, frame_shape=(4, 6))
    for _ in range(2):
        writer.write(np.zeros((4, 6), np.float32), np.zeros((4, 6), np.uint32))
    writer.finish()
    with pytest.raises(ParameterError, match=r"holds 2 frames \(0..1\)"):
        read_corrected(path, frames=[99])
    capsys.readouterr()
    assert main(["quicklook", str(path), "-o", str(tmp_path / "q.png"), "--frame", "99"]) == 2
    _one_line(capsys, "out of range", "2 frames")


# -- cause: EMVA 1288 on degenerate sets divided by zero or reduced empty arrays ------------------
def _emva_set(case):
    from hsiffc.data.sweep import Sweep

    rng = np.random.default_rng(0)
    data, photons = [], []
    for i in range(6):
        if case == "saturated":
            pair = np.full((2, 16, 16), 4095, np.uint16)
        elif case == "identical":
            pair = np.repeat(rng.poisson(100 + 200 * i, (1, 16, 16)), 2, axis=0)
        else:
            pair = rng.poisson(100 + 200 * i, (2, 16, 16))
        data.append(pair)
        photons += [0.0 if case == "photons 0" else 1000.0 * (i + 1)] * 2
    data.append(rng.poisson(100, (2, 16, 16)))
    kind = ["light"] * 12 + ["dark"] * 2
    return Sweep(np.concatenate(data).astype(np.uint16), 10.0, np.array(kind), 12,
                 step=np.repeat(np.arange(7), 2), photons=np.array(photons + [np.nan] * 2),
                 source="set")


@pytest.mark.parametrize("case, needle", [("saturated", "clipped"), ("identical", "identical"),
                                          ("photons 0", "photon counts")])
def test_emva1288_on_a_degenerate_set_is_one_line(case, needle):
    from hsiffc.emva1288 import characterise
    from hsiffc.errors import DataFormatError

    with pytest.raises(DataFormatError, match=needle) as err:
        characterise(_emva_set(case))
    assert "\n" not in str(err.value) and str(err.value).startswith("set: ")


# -- cause: quicklook's readers and the panel file skipped the file-kind check and the limits ----
def test_quicklook_readers_and_the_panel_file_refuse_fifos_and_apply_the_limits(tmp_path,
                                                                               capsys,
                                                                               monkeypatch):
    """A FIFO named as an OME, netCDF, corrected-TIFF or ENVI cube, or as the panel's spectrum:
    one line each, never opened (they hung before); HSIFFC_MAX_FRAME_PIXELS bounds a cube's
    planes before they are decoded."""
    import subprocess
    import sys

    from hsiffc.cubes import Cube, write_cube

    names = ["c.ome.tif", "c.nc", "c.corrected.tif", "c.hdr"]
    for name in names + ["panel.csv"]:
        os.mkfifo(tmp_path / name)
    runs = [["quicklook", str(tmp_path / n), "-o", str(tmp_path / f"{n}.png")] for n in names]
    code = "".join(f"sys.stderr.write('===\\n'); sys.stderr.flush(); codes.append(main({r!r})); "
                   for r in runs)
    code += ("from hsiffc.reflectance._panel import read_panel_spectrum\n"
             "sys.stderr.write('===\\n')\n"
             "try:\n"
             f"    read_panel_spectrum({str(tmp_path / 'panel.csv')!r})\n"
             "except Exception as exc:\n"
             "    sys.stderr.write(str(exc) + '\\n')\n")
    done = subprocess.run([sys.executable, "-c", "import sys; from hsiffc.cli import main; "
                           f"codes = []\n{code}sys.exit(10 * max(codes) + min(codes))"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 22, done.stderr
    parts = [[ln for ln in p.splitlines() if ln.strip()] for p in done.stderr.split("===")[1:]]
    assert [len(p) for p in parts] == [1] * 5, done.stderr
    assert all("named pipe (FIFO)" in p[0] for p in parts), parts

    rng = np.random.default_rng(1)
    cube = Cube(rng.random((8, 8, 4), np.float32), np.zeros((8, 8, 4), np.uint32),
                wavelengths_nm=(500, 600, 700, 800))
    for name in ("big.ome.tif", "big.nc"):
        write_cube(cube, tmp_path / name)
    monkeypatch.setenv("HSIFFC_MAX_FRAME_PIXELS", "100")
    capsys.readouterr()
    for name in ("big.ome.tif", "big.nc"):
        assert main(["quicklook", str(tmp_path / name), "-o", str(tmp_path / f"{name}.png")]) == 2
        _one_line(capsys, name, "HSIFFC_MAX_FRAME_PIXELS")


# -- cause: an ENVI cube's header was trusted for its DQ file's name and shape and its fwhm -------
@pytest.mark.parametrize("old, new, needle", [
    ("dq file = c.dq.img", "dq file = ../elsewhere/c.dq.img", "not a file name beside"),
    ("dq file = c.dq.img", "dq file = d.dq.img", "damaged or mixed up"),
    ("fwhm = {", "fwhm = {wide, ", "'fwhm' holds values that are not numbers")],
    ids=["dq-outside", "dq-shape", "fwhm-words"])
def test_an_altered_envi_cube_header_is_one_line(tmp_path, capsys, old, new, needle):
    from hsiffc.cubes import Cube, write_cube

    cube = Cube(np.ones((6, 5, 2), np.float32), np.zeros((6, 5, 2), np.uint32),
                wavelengths_nm=(500, 600), fwhm_nm=(10, 10))
    write_cube(cube, tmp_path / "c.hdr")
    write_cube(Cube(np.ones((3, 5, 2), np.float32), np.zeros((3, 5, 2), np.uint32)),
               tmp_path / "d.hdr")
    head = (tmp_path / "c.hdr").read_text()
    assert old in head
    (tmp_path / "c.hdr").write_text(head.replace(old, new))
    capsys.readouterr()
    assert main(["quicklook", str(tmp_path / "c.hdr"), "-o", str(tmp_path / "q.png")]) == 2
    _one_line(capsys, "c.hdr", needle)


# -- cause: ENVI header text refused braces anywhere and was checked after the data were written --
def test_envi_cube_names_with_braces_are_written_and_unwritable_names_leave_no_file(tmp_path):
    from hsiffc.cubes import Cube, read_cube, write_cube
    from hsiffc.errors import DataFormatError

    cube = Cube(np.ones((4, 3, 2), np.float32), np.zeros((4, 3, 2), np.uint32),
                wavelengths_nm=(500, 600))
    write_cube(cube, tmp_path / "scan{1}.hdr")  # no header before: braces were refused
    assert read_cube(tmp_path / "scan{1}.hdr").data.shape == (4, 3, 2)
    for bad in ("two\nlines", os.fsdecode(b"caf\xe9")):
        folder = tmp_path / f"bad{len(bad)}"
        folder.mkdir()
        with pytest.raises(DataFormatError, match="rename the file") as err:
            write_cube(cube, folder / f"{bad}.hdr")
        assert "\n" not in str(err.value).replace("\\n", "")
        assert list(folder.iterdir()) == []  # no .dq.img left to block a rerun


# -- cause: the outputs of a file of more than 10,000 frames (_f10000) were read back as inputs --
def test_exports_past_ten_thousand_frames_are_known_as_outputs():
    from hsiffc.batch.plan import is_batch_output

    for name in ("a.corrected_f10000.hdr", "a.corrected_f123456.dq.img",
                 "a.corrected_f10000.ome.tif", "a.corrected_f10000.nc"):
        assert is_batch_output(name), name
    assert not is_batch_output("a_f10000.hdr")


# -- cause: an ENVI export was several atomic writes, each put in place on its own ----------------
def _envi_set(out):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".hdr", ".img")}


def test_envi_product_is_put_in_place_as_one_set_and_a_broken_commit_resumes(
        sweep, tmp_path, monkeypatch, capsys):
    """The .hdr/.img/DQ files of every frame appear together, after the last frame: a failure
    (a kill, a full disk) before that leaves no file under a final name; one during the
    renames leaves a set whose files do not agree (new headers beside the older data files),
    which the rerun of the same command, without --overwrite, redoes instead of reporting it
    up to date."""
    import errno

    import hsiffc.files.atomic as atomic

    out = tmp_path / "out"
    argv = ["correct", str(sweep / "s.tif"), "--calibration", str(sweep / "cal.npz"), "-o",
            str(out), "--format", "envi", "-q"]
    real = atomic._commit
    calls = []

    def stop_after(n):
        def commit(*args, **kwargs):
            calls.append(args[1])
            if len(calls) > n:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*args, **kwargs)
        return commit

    monkeypatch.setattr(atomic, "_commit", stop_after(0))  # the first rename fails
    assert main(argv) == 1
    assert not [p for p in out.iterdir() if not p.name.startswith(".")]  # nothing, no .part
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]
    monkeypatch.setattr(atomic, "_commit", real)
    assert main(argv) == 0
    clean = _envi_set(out)
    headers = [n for n in clean if n.endswith(".hdr")]
    assert len(clean) == 2 * len(headers) and not any(n.endswith(".tif") for n in clean)

    # redo it (--overwrite) and break the renames after the headers: new headers, old data
    calls.clear()
    monkeypatch.setattr(atomic, "_commit", stop_after(len(headers) + 1))
    assert main(argv + ["--overwrite"]) == 1
    monkeypatch.setattr(atomic, "_commit", real)
    capsys.readouterr()
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert "1 done" in said and "is not the data file its header" in said  # redone, and why
    assert main(argv) == 0 and "0 done, 1 skipped" in capsys.readouterr().out
    again = _envi_set(out)
    assert again.keys() == clean.keys()
    assert all(again[n] == clean[n] for n in clean if n.endswith(".img"))


# -- cause: a netCDF cube's variables could point to another file's bytes (HDF5 external) --------
def test_a_netcdf_cube_with_external_storage_is_refused(tmp_path, capsys):
    import h5py

    from hsiffc.cubes import Cube, write_cube

    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"S" * 400)
    cube = Cube(np.ones((4, 3, 2), np.float32), np.zeros((4, 3, 2), np.uint32),
                wavelengths_nm=(500, 600))
    write_cube(cube, tmp_path / "c.nc")
    with h5py.File(tmp_path / "c.nc", "r+") as h5:
        h5.create_dataset("leak", shape=(10, 10), dtype="f4",
                          external=[(str(secret), 0, 400)])
    capsys.readouterr()
    assert main(["quicklook", str(tmp_path / "c.nc"), "-o", str(tmp_path / "q.png")]) == 2
    _one_line(capsys, "c.nc", "'leak'", "another file")
    assert not (tmp_path / "q.png").exists()


# -- cause: a full disk during a netCDF export was HDF5's several lines naming the temporary file --
def test_a_full_disk_during_a_netcdf_export_is_one_line_naming_the_cube(sweep, tmp_path,
                                                                       monkeypatch, capsys):
    import xarray

    out = tmp_path / "out"
    argv = ["correct", str(sweep / "s.tif"), "--calibration", str(sweep / "cal.npz"), "-o",
            str(out), "-q"]

    def full(self, path, *args, **kwargs):
        raise OSError(f"Can't write data (file write failed: time = Fri Nov 27, filename = "
                      f"'{path}', file descriptor = 7, errno = 28, error message = 'No space "
                      "left on device', buf = 0x1, total write size = 1024)\n  HDF5-DIAG: "
                      "error detected in libhdf5")

    monkeypatch.setattr(xarray.Dataset, "to_netcdf", full)
    capsys.readouterr()
    assert main(argv + ["--format", "netcdf"]) != 0
    said = capsys.readouterr().out
    lines = [ln for ln in said.splitlines() if "No space left on device" in ln]
    assert len(lines) == 1, said
    assert ".part" not in lines[0] and "HDF5" not in lines[0] and "s.corrected" in lines[0]
    assert not [p for p in out.iterdir() if p.suffix == ".nc" or p.name.endswith(".part")]


# -- cause: exports ran after the batch returned, outside the folder's lock -----------------------
def test_exports_run_inside_the_folder_lock_and_clear_an_interrupted_exports_part_file(
        sweep, tmp_path, monkeypatch):
    """A second run while the first writes its netCDF cubes is refused (the exports ran
    after the lock was let go), and the temporary file a killed netCDF write left is removed
    by the rerun that holds the lock (it survived)."""
    import hsiffc.cubes.stream as stream
    from hsiffc.files.folderlock import FolderLockedError, folder_lock

    out = tmp_path / "out"
    out.mkdir()
    argv = ["correct", str(sweep / "s.tif"), "--calibration", str(sweep / "cal.npz"), "-o",
            str(out), "-q"]
    stale = out / ".s.corrected_f0000.nc.4242-deadbeef.part"
    stale.write_bytes(b"half a cube")
    real, seen = stream.write_cube, []

    def during(*args, **kwargs):
        try:
            with folder_lock(out, what="a second hsiffc correct"):
                seen.append("second run got the lock")
        except FolderLockedError:
            seen.append("refused")
        return real(*args, **kwargs)

    monkeypatch.setattr(stream, "write_cube", during)
    assert main(argv + ["--format", "netcdf"]) == 0
    assert seen and set(seen) == {"refused"}
    assert not stale.exists()
    assert (out / "s.corrected_f0000.nc").is_file()


# -- cause: an IMEC XML's peak wavelength, FWHM and QE were not checked for sign ------------------
@pytest.mark.parametrize("old, new, needle", [
    ("<wavelength_nm>402</wavelength_nm>", "<wavelength_nm>-500</wavelength_nm>", "> 0"),
    ("<fwhm_nm>2.4</fwhm_nm>", "<fwhm_nm>-2.4</fwhm_nm>", ">= 0"),
    ("<QE>100</QE>", "<QE>-100</QE>", ">= 0")], ids=["peak", "fwhm", "qe"])
def test_imec_peaks_with_impossible_values_are_refused(tmp_path, old, new, needle):

    from hsiffc.errors import DataFormatError
    from hsiffc.spectral.imec import read_imec_xml

    text = synthetic_imec_xml().replace(old, new, 1)
    assert text != synthetic_imec_xml()
    (tmp_path / "a.xml").write_text(text)
    with pytest.raises(DataFormatError, match=needle) as err:
        read_imec_xml(tmp_path / "a.xml")
    assert "peak" in str(err.value) and "\n" not in str(err.value)


# -- cause: reflectance check --roi took ROW0 as a count (>= 1) though rows count from 0 ---------
def test_reflectance_check_roi_counts_from_zero(capsys):
    from hsiffc.cli import build_parser

    args = build_parser().parse_args(["reflectance", "check", "t.tif", "--pipeline", "p.npz",
                                      "--roi", "0", "4", "0", "4"])
    assert args.roi == [0, 4, 0, 4]
    assert main(["reflectance", "check", "t.tif", "--pipeline", "p.npz", "--roi", "-1", "4",
                 "0", "4"]) == 2
    _one_line(capsys, "--roi", "count from 0")


# -- cause: a one-band cube could not be written (tifffile refuses an (H, W, 1) page) -------------
@pytest.mark.parametrize("name", ["one.tif", "one.ome.tif", "one.hdr", "one.nc"])
def test_a_one_band_cube_is_written_and_read_back_as_one_band(tmp_path, name):
    from hsiffc.cubes import Cube, read_cube, write_cube

    rng = np.random.default_rng(2)
    cube = Cube(rng.random((6, 5, 1), np.float32), np.ones((6, 5, 1), np.uint32),
                alpha=np.full((6, 5, 1), 2.0, np.float32), wavelengths_nm=(550,))
    write_cube(cube, tmp_path / name)
    back = read_cube(tmp_path / name)
    assert back.data.shape == back.dq.shape == back.alpha.shape == (6, 5, 1)
    np.testing.assert_array_equal(back.data, cube.data)
    np.testing.assert_array_equal(back.dq, cube.dq)
    assert back.wavelengths_nm == (550.0,)


def test_a_pixel_with_b_not_positive_is_flagged_not_fatal(sweep, tmp_path, capsys):
    """One pixel of a calibration with leakage b <= 0 used to fail every frame of a batch
    ("b (1/DN) must be > 0") without naming the calibration; a NaN was just flagged. Now the
    calibration names itself in a warning, that pixel is flagged DO_NOT_USE (b NaN) and the
    rest of the frame is corrected."""
    from dataclasses import replace

    from hsiffc.calibrate import Calibration
    from hsiffc.errors import CalibrationDomainWarning
    from hsiffc.io.corrected import read_corrected

    good = Calibration.load(sweep / "cal.npz")
    arrays = dict(good.arrays)
    b = arrays["b_per_dn"].copy()
    b[2, 3] = -0.01
    arrays["b_per_dn"] = b
    a = arrays["a_dn_per_ms"].copy()
    a[2, 3] = max(float(a[2, 3]), 1e-3)  # a leaking pixel: its b is used
    arrays["a_dn_per_ms"] = a
    with pytest.warns(CalibrationDomainWarning, match="1 pixel"):
        bad = replace(good, arrays=arrays, path=None)
    assert np.isnan(bad.b[2, 3]) and bad.flags[2, 3] & DQ.DO_NOT_USE
    # a file holding such a pixel, as another tool or an older fit may have written it
    with np.load(sweep / "cal.npz") as z:
        members = {k: z[k] for k in z.files}
    members["b_per_dn"] = b
    members["a_dn_per_ms"] = a
    np.savez(tmp_path / "bad.npz", **members)
    out = tmp_path / "out"
    capsys.readouterr()
    rc = main(["correct", str(sweep / "s.tif"), "--calibration", str(tmp_path / "bad.npz"),
               "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "bad.npz" in err and "b <= 0" in err, err
    c = read_corrected(out / "s.corrected.tif")
    assert (c.dq[:, 2, 3] & DQ.DO_NOT_USE).all()
    others = np.ones(c.dq.shape[1:], bool)
    others[2, 3] = False
    assert np.isfinite(c.data[:, others]).all()


# -- cause: readers allocated what a file's header declared (a 2 MB OME took 3.3 GB; a sparse
# -- 3 GB ENVI header was read whole) -------------------------------------------------------------
def test_a_small_ome_declaring_a_huge_cube_is_refused_within_a_memory_bound(tmp_path,
                                                                             monkeypatch):
    """An OME-TIFF of a few hundred kB whose zstd tiles decode to 315 MB (the issue's 2 MB file
    declared 3.3 GB; the same attack at a tenth of the scale) is refused from its declared size
    in one line naming HSIFFC_MAX_BYTES, in a process whose address space is capped at 150 MB
    above its imports: nothing of the declared size is ever allocated."""

    c, h, w = 3, 5120, 5120                       # 3 x 5120 x 5120 x 2 bytes per series
    tile = np.zeros((256, 256), np.uint16)
    path = tmp_path / "bomb.ome.tif"
    with tifffile.TiffWriter(path, ome=True, bigtiff=True) as tw:
        for name in ("data", "dq"):
            tiles = (tile for _ in range(c * (h // 256) * (w // 256)))
            tw.write(tiles, shape=(c, h, w), dtype=np.uint16, tile=(256, 256),
                     compression="zstd", photometric="minisblack",
                     metadata={"axes": "CYX", "Name": name})
    assert path.stat().st_size < 2_000_000        # a small file ...
    assert 2 * c * h * w * 2 > 300_000_000        # ... declaring 315 MB of planes
    monkeypatch.setenv("HSIFFC_MAX_BYTES", "100000000")
    for argv in (["quicklook", path, "-o", tmp_path / "q.png"],):
        rc, err = capped_cli(argv, extra_mb=150)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert rc == 2 and len(lines) == 1, err
        assert "HSIFFC_MAX_BYTES" in lines[0] and "bomb.ome.tif" in lines[0]
        assert "MemoryError" not in err and "Traceback" not in err


def test_a_sparse_3_gb_envi_header_is_refused_from_its_size_within_a_memory_bound(tmp_path):
    """A sparse 3 GB .hdr (it took 3 GB of memory: the parser read it whole) is refused from
    its stat, before it is read, in a process capped at 100 MB above its imports."""

    np.zeros((2, 4, 5), np.uint16).tofile(tmp_path / "c.img")
    header = tmp_path / "c.hdr"
    header.write_text("ENVI\nsamples = 5\nlines = 4\nbands = 2\ndata type = 12\n"
                      "interleave = bsq\nbyte order = 0\nnotes = {")
    os.truncate(header, 3 * 2 ** 30)                  # 3 GiB of holes: no disk used
    assert header.stat().st_size == 3 * 2 ** 30
    for argv in (["info", header, "--exposure-ms", "1"], ["quicklook", header, "-o",
                                                            tmp_path / "q.png"]):
        rc, err = capped_cli(argv, extra_mb=100)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert rc == 2 and len(lines) == 1, err
        assert "HSIFFC_MAX_HEADER_BYTES" in lines[0] and "c.hdr" in lines[0]
