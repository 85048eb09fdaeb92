"""Cubes out of hsiffc: ``hsiffc correct`` writing full-resolution cubes, the formats users'
tools open (SPy, xarray, tifffile), the self-describing DQ plane and the quicklook.

The simulated sensor's bands are stored out of wavelength order (band index != wavelength
rank), so a writer that forgets to sort, or sorts the wavelengths without the data, fails."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.cubes import Cube, read_cube, write_cube
from hsiffc.data.dq import DQ, bits, mask, table
from hsiffc.data.frame import Frame
from hsiffc.io import read_corrected, read_sweep, write_sweep
from hsiffc.data.mosaic import Mosaic
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.simulate.params import default_bands
from hsiffc.spectral.bands import BandSet
from hsiffc.stages import Pipeline, create

SHAPE = (48, 64)
PERM = [3, 0, 6, 1, 7, 2, 5, 4]  # band index k holds the default sensor's band PERM[k]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Darks, flats and two scene frames of a 4 x 2 mosaic sensor whose bands are out of
    wavelength order, a fitted dark + flat pipeline with and without a bilinear
    reconstruct step."""
    root = tmp_path_factory.mktemp("cubes")
    b = default_bands()
    bands = BandSet(b.wavelengths_nm, b.responses[PERM], b.centres_nm[PERM], b.fwhm_nm[PERM],
                    name="permuted")
    mosaic = Mosaic(np.arange(8).reshape(2, 4), tuple(bands.centres_nm), name="sim",
                    fwhm_nm=tuple(bands.fwhm_nm))
    sensor = MosaicSensor(SHAPE, mosaic=mosaic, bands=bands, seed=4)
    light = PAPER_LIGHT_W_M2["training"] * 0.8

    def save(path, sweep):  # without the simulator's truth arrays
        write_sweep(path, replace(sweep, meta={}))

    save(root / "dark.tif", sensor.sweep([10.0], None, n_frames=3, seed=1))
    save(root / "flat.tif", sensor.sweep([10.0], "lamp A", irradiance_w_m2=light, n_frames=3,
                                         darks=False, seed=2))
    (root / "scene").mkdir()
    save(root / "scene" / "scene.tif", sensor.sweep([10.0], "lamp A", irradiance_w_m2=light * 0.6,
                                                     n_frames=2, darks=False, seed=3))
    base = ('[[step]]\nname = "dark"\nstage = "dark"\n\n'
            '[[step]]\nname = "ffc"\nstage = "two_point_ffc"\nexposure_ms = 10.0\n')
    (root / "frames.toml").write_text(base)
    (root / "cube.toml").write_text(base + '\n[[step]]\nname = "cube"\nstage = "reconstruct"\n'
                                           'method = "bilinear"\n')
    for name in ("frames", "cube"):
        assert main(["fit", str(root / f"{name}.toml"), "--dark", str(root / "dark.tif"),
                     "--flat", str(root / "flat.tif"), "-o", str(root / f"{name}.npz")]) == 0
    return {"root": root, "mosaic": mosaic, "scene": root / "scene"}


def _reference_cube(world, method="bilinear"):
    """What the CLI should write for the first scene frame: the same pipeline in Python."""
    pipe = Pipeline.load(world["root"] / "frames.npz")
    frame = Frame.list_from_sweep(read_sweep(world["scene"] / "scene.tif"))[0]
    step = create("reconstruct", method=method).fit([])
    return step.transform(pipe.transform(frame))


def _decode_envi_dq(header_path):
    """Decode a DQ file with the file alone: plain text parsing and numpy, no hsiffc."""
    text = header_path.read_text()
    fields = dict(re.findall(r"^([a-z ]+?)\s*=\s*\{?([^}\n]*)\}?$", text, flags=re.M))
    names = [s.strip() for s in fields["dq bit names"].split(",")]
    values = [int(s) for s in fields["dq bit values"].split(",")]
    shape = (int(fields["bands"]), int(fields["lines"]), int(fields["samples"]))
    # the smallest unsigned type that holds the bits in use: uint16 (12) today
    assert fields["data type"].strip() == "12" and fields["interleave"].strip() == "bsq"
    plane = np.fromfile(header_path.with_suffix(".img"), "<u2").reshape(shape)
    return dict(zip(names, values)), np.moveaxis(plane, 0, 2)


def test_fitted_pipeline_with_reconstruct_writes_cubes_and_envi(world, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["correct", "--pipeline", str(world["root"] / "cube.npz"), str(world["scene"]),
                 "-o", str(out), "--format", "envi,tiff", "-q"]) == 0
    got = read_corrected(out / "scene.corrected.tif")
    assert got.data.shape == (2,) + SHAPE + (8,)
    ref = _reference_cube(world)
    np.testing.assert_array_equal(got.data[0], ref.data)
    np.testing.assert_array_equal(got.dq[0], ref.dq)
    prov = got.provenance
    assert prov["cube"]["band_order"] == "band index"
    assert prov["cube"]["wavelengths_nm"] == list(world["mosaic"].wavelengths_nm)
    assert {r["name"]: r["value"] for r in prov["dq_bits"]}["SATURATED"] == int(DQ.SATURATED)

    # SPy opens the ENVI cube: bands by wavelength, each band the data of its wavelength
    import spectral

    hdr = out / "scene.corrected_f0000.hdr"
    img = spectral.open_image(str(hdr))
    centres = np.asarray(img.bands.centers)
    order = np.argsort(world["mosaic"].wavelengths_nm)
    np.testing.assert_allclose(centres, np.sort(world["mosaic"].wavelengths_nm), rtol=1e-5)
    assert np.all(np.diff(centres) > 0)
    np.testing.assert_allclose(img.bands.bandwidths, np.asarray(world["mosaic"].fwhm_nm)[order],
                               rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(img.load()), ref.data[:, :, order])
    meta = img.metadata
    names = meta["band names"]
    r, c = np.argwhere(world["mosaic"].pattern == order[0])[0]
    assert names[0].startswith(f"band 1 (r{r}c{c} ")  # numbered by wavelength, with position
    red, green, blue = (int(v) - 1 for v in meta["default bands"])
    assert centres[red] > centres[green] > centres[blue]

    # the DQ file decoded with its header alone
    table_in_file, dq = _decode_envi_dq(out / "scene.corrected_f0000.dq.hdr")
    assert table_in_file == {row["name"]: row["value"] for row in table()}
    np.testing.assert_array_equal(dq, ref.dq[:, :, order])
    # and rerunning skips both the corrected file and its cubes
    capsys.readouterr()
    assert main(["correct", "--pipeline", str(world["root"] / "cube.npz"), str(world["scene"]),
                 "-o", str(out), "--format", "envi,tiff", "-q"]) == 0
    assert "skipped" in capsys.readouterr().out


def test_cube_shortcut_ppid_to_ome_and_netcdf(world, tmp_path):
    xr = pytest.importorskip("xarray")
    out = tmp_path / "out"
    assert main(["correct", "--pipeline", str(world["root"] / "frames.npz"), "--cube", "ppid",
                 str(world["scene"]), "-o", str(out), "--format", "ome,tiff",
                 "--compression", "zlib", "-q"]) == 0
    ref = _reference_cube(world, "ppid")
    order = np.argsort(world["mosaic"].wavelengths_nm)
    got = read_corrected(out / "scene.corrected.tif")
    assert got.provenance["compression"] == "zlib"
    np.testing.assert_array_equal(got.data[0], ref.data)
    with tifffile.TiffFile(out / "scene.corrected_f0000.ome.tif") as tf:
        assert tf.is_ome
        channels = [c.group("Name") for c in re.finditer(r'<Channel [^>]*Name="(?P<Name>[^"]+)"',
                                                       tf.ome_metadata)]
        data = tf.series[0].asarray()
        dq = tf.series[1].asarray()
    wl = [float(re.search(r"([\d.]+) nm", n)[1]) for n in channels[:8]]
    assert [n.split(" (")[0] for n in channels[:8]] == [f"band {k}" for k in range(1, 9)]
    assert wl == sorted(wl) and len(channels) == 16  # data's 8 channels, then DQ's 8
    np.testing.assert_allclose(wl, np.sort(world["mosaic"].wavelengths_nm), atol=0.05)
    np.testing.assert_array_equal(data, np.moveaxis(ref.data[:, :, order], 2, 0))
    np.testing.assert_array_equal(dq, np.moveaxis(ref.dq[:, :, order], 2, 0))

    assert main(["correct", "--pipeline", str(world["root"] / "frames.npz"), "--cube", "ppid",
                 str(world["scene"]), "-o", str(out), "--format", "netcdf", "-q"]) == 0
    with xr.open_dataset(out / "scene.corrected_f0001.nc") as ds:
        assert ds["data"].dims == ("y", "x", "band") and ds["data"].shape == SHAPE + (8,)
        assert np.all(np.diff(ds["wavelength"].values) > 0)
        flags = dict(zip(ds["dq"].attrs["flag_meanings"].split(),
                         np.asarray(ds["dq"].attrs["flag_masks"]).tolist()))
        assert flags["LEAKAGE"] == int(DQ.LEAKAGE)
        assert [row["name"] for row in json.loads(ds.attrs["dq_bits"])] == list(flags)
        assert "two_point_ffc" in ds.attrs["history"]


def test_quicklook_of_a_corrected_cube(world, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["correct", "--pipeline", str(world["root"] / "cube.npz"), str(world["scene"]),
                 "-o", str(out), "-q"]) == 0
    png = tmp_path / "look.png"
    assert main(["quicklook", str(out / "scene.corrected.tif"), "-o", str(png),
                 "--region", "10", "20", "10", "30", "--rgb", "800", "650", "500"]) == 0
    image = __import__("matplotlib.image", fromlist=["imread"]).imread(png)
    assert image.shape[0] > 500 and image.shape[1] > 700
    assert image[..., :3].std() > 0.05  # not a blank page
    assert main(["quicklook", str(out / "scene.corrected.tif"), "-o", str(png)]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["quicklook", str(out / "scene.corrected.tif"), "-o", str(tmp_path / "b.png"),
                 "--pixel", "999", "0"]) == 2
    assert "pixel" in capsys.readouterr().err


def test_cube_needs_its_correction_xml(world, tmp_path, capsys):
    assert main(["correct", "--pipeline", str(world["root"] / "cube.npz"), "--cube", "ppid",
                 str(world["scene"]), "-o", str(tmp_path / "o"), "-q"]) == 2
    assert "already has one" in capsys.readouterr().err
    assert main(["correct", "--pipeline", str(world["root"] / "frames.npz"),
                 "--cube-correction", "imec", str(world["scene"]), "-o",
                 str(tmp_path / "o")]) == 2
    assert "--cube" in capsys.readouterr().err


def _cube(rng, alpha=True):
    data = rng.random((6, 7, 4)).astype(np.float32)
    dq = np.zeros(data.shape, np.uint32)
    dq[1, 2, 0] = DQ.SATURATED | DQ.LEAKAGE
    dq[3, 3, 2] = DQ.DEAD
    return Cube(data, dq, data * 10 if alpha else None, [700.0, 600.0, 650.0, 500.0],
                [10.0, 11.0, 12.0, 13.0], [(0, 0), (0, 1), (1, 0), (1, 1)],
                attrs={"exposure_ms": 5.0})


@pytest.mark.parametrize("name", ["c.tif", "c.hdr", "c.ome.tif", "c.nc"])
def test_write_cube_round_trip_sorted(tmp_path, name):
    if name.endswith(".nc"):
        pytest.importorskip("xarray")
    cube = _cube(np.random.default_rng(1))
    files = write_cube(cube, tmp_path / name, compression=None)
    assert all(f.exists() for f in files)
    back = read_cube(tmp_path / name)
    assert back.wavelengths_nm == (500.0, 600.0, 650.0, 700.0)
    assert back.fwhm_nm == (13.0, 11.0, 12.0, 10.0)
    np.testing.assert_array_equal(back.data, cube.data[:, :, [3, 1, 2, 0]])
    np.testing.assert_array_equal(back.dq, cube.dq[:, :, [3, 1, 2, 0]])
    np.testing.assert_allclose(back.alpha, cube.alpha[:, :, [3, 1, 2, 0]])
    with pytest.raises(FileExistsError):
        write_cube(cube, tmp_path / name, overwrite=False)


def test_frame_to_xarray_and_dq_names(tmp_path):
    pytest.importorskip("xarray")
    mosaic = Mosaic(np.array([[1, 0], [2, 3]]), (650.0, 500.0, 600.0, 550.0))
    raw = np.random.default_rng(2).integers(0, 1023, (8, 10)).astype(np.uint16)
    frame = Frame.from_raw(raw, exposure_ms=5.0, bit_depth=10, mosaic=mosaic)
    cube = create("reconstruct", method="bilinear").fit([]).transform(frame)
    ds = cube.to_xarray()
    assert ds["data"].dims == ("y", "x", "band")
    assert ds["wavelength"].values.tolist() == [500.0, 550.0, 600.0, 650.0]
    assert ds["band_index"].values.tolist() == [1, 3, 2, 0]
    np.testing.assert_array_equal(ds["data"].values, cube.data[:, :, [1, 3, 2, 0]])
    assert [r["value"] for r in json.loads(ds.attrs["dq_bits"])] == [int(f) for f in DQ if f]
    with pytest.raises(ValueError, match="reconstruct"):
        frame.to_xarray()
    dq = cube.dq.copy()
    dq[0, 0, 0] = DQ.SATURATED
    dq[0, 1, 0] = DQ.HOT
    m = mask(dq, "SATURATED|leakage")
    assert m[0, 0, 0] and not m[0, 1, 0] and m.sum() == np.count_nonzero(dq & 6)
    assert bits(["SATURATED", "HOT"]) == int(DQ.SATURATED | DQ.HOT)
    with pytest.raises(ValueError, match="known flags"):
        mask(dq, "SATURATD")


def test_formats_page_lists_the_dq_table():
    """The DQ bit table on the formats page is the one every file carries."""
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "formats-and-metadata.md").read_text()
    rows = re.findall(r"^\| `([A-Z_]+)` \| (\d+) \| (.+?) \|$", page, flags=re.M)
    assert [(n, int(v), m) for n, v, m in rows] == [(r["name"], r["value"], r["meaning"])
                                                    for r in table()]


@pytest.mark.realdata
def test_imec_virtual_bands_written_with_their_wavelengths(imec_xml, tmp_path):
    """The IMEC correction matrix to virtual bands: the ENVI cube lists the virtual
    wavelengths ascending with the XML's virtual FWHM, and names the bands virtual."""
    import spectral

    from hsiffc.spectral.imec import read_imec_xml

    imec = read_imec_xml(imec_xml)
    mosaic = imec.mosaic()
    raw = np.random.default_rng(3).integers(100, 900, (40, 50)).astype(np.uint16)
    frame = Frame.from_raw(raw, exposure_ms=10.0, bit_depth=10,
                           mosaic=Mosaic(mosaic.pattern, mosaic.wavelengths_nm,
                                         fwhm_nm=mosaic.fwhm_nm))
    step = create("reconstruct", method="ppid", correction="imec", imec_xml=str(imec_xml))
    cube = step.fit([frame]).transform(frame)
    write_cube(cube, tmp_path / "v.hdr")
    img = spectral.open_image(str(tmp_path / "v.hdr"))
    virtual = np.asarray(imec.virtual_wavelengths_nm, float)
    assert img.nbands == len(virtual)
    np.testing.assert_allclose(img.bands.centers, np.sort(virtual), rtol=1e-5)
    if imec.virtual_fwhm_nm is not None:
        np.testing.assert_allclose(img.bands.bandwidths, imec.virtual_fwhm_nm, rtol=1e-5)
    assert [name.split(" (")[0] for name in img.metadata["band names"]] == [
        f"band {k}" for k in range(1, len(virtual) + 1)]
    assert all("(virtual " in name for name in img.metadata["band names"])
    order = np.argsort(virtual, kind="stable")
    np.testing.assert_array_equal(np.asarray(img.load()), cube.data[:, :, order])
