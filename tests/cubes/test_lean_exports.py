"""Cube exports in the smallest form that holds them (issue 54): the DQ plane in the smallest
unsigned type that holds the bits in use, with the bit table beside it, read back as the
package's DQ type; the ENVI header with what users' tools look for (``data ignore value``,
``bbl``, ``wavelength units``) and the DQ companion file still linked."""

from __future__ import annotations

import numpy as np
import pytest

from hsiffc.cubes import Cube, read_cube
from hsiffc.cubes.writers import dq_storage
from hsiffc.data.dq import DQ, DQ_DTYPE, table
from hsiffc.io import write_cube
from hsiffc.io.envi import parse_envi_header, read_envi


def _cube() -> Cube:
    rng = np.random.default_rng(5)
    data = rng.normal(100, 10, (5, 7, 4)).astype(np.float32)
    dq = np.zeros(data.shape, np.uint32)
    dq[:, :, 2] = DQ.DO_NOT_USE            # a band with no usable value (band index 2)
    dq[1, 2, 0] = DQ.SATURATED | DQ.LEAKAGE
    dq[3, 3, 1] = DQ.OUT_OF_DOMAIN         # the highest bit of the table
    return Cube(data, dq, None, [700.0, 500.0, 600.0, 650.0])


def test_dq_storage_is_the_smallest_type_that_holds_the_bits_in_use():
    top = max(r["value"] for r in table())
    assert top < 1 << 16  # uint16 today; a table that outgrows it is stored wider
    assert dq_storage(np.zeros((2, 2), np.uint32)).dtype == np.uint16
    assert dq_storage(np.array([top], np.uint32)).dtype == np.uint16
    wide = dq_storage(np.array([0, 1 << 17], np.uint32))  # a bit beyond the table is kept
    assert wide.dtype == np.uint32 and wide[1] == 1 << 17
    np.testing.assert_array_equal(dq_storage(_cube().dq), _cube().dq)


@pytest.mark.parametrize("name", ["c.hdr", "c.ome.tif", "c.nc"])
def test_exports_store_dq_as_uint16_and_read_it_back_as_the_dq_type(tmp_path, name):
    if name.endswith(".nc"):
        pytest.importorskip("xarray")
    cube = _cube()
    write_cube(cube, tmp_path / name)
    if name.endswith(".hdr"):
        stored = read_envi(tmp_path / "c.dq.hdr")[0]
    elif name.endswith(".nc"):
        import xarray as xr

        with xr.open_dataset(tmp_path / name) as ds:
            stored = ds["dq"].values
            masks = ds["dq"].attrs["flag_masks"]
            assert masks.dtype == np.uint16  # CF: the flag masks have the variable's type
            assert masks.tolist() == [r["value"] for r in table()]
    else:
        import tifffile

        with tifffile.TiffFile(tmp_path / name) as tf:
            stored = tf.series[1].asarray()
    assert stored.dtype == np.uint16
    back = read_cube(tmp_path / name)
    assert back.dq.dtype == DQ_DTYPE
    np.testing.assert_array_equal(back.dq, cube.sorted().dq)
    np.testing.assert_array_equal(back.data, cube.sorted().data)


def test_envi_header_has_ignore_value_bad_bands_units_and_the_dq_file(tmp_path):
    cube = _cube()
    files = write_cube(cube, tmp_path / "c.hdr")
    head = parse_envi_header(tmp_path / "c.hdr")
    assert head["data ignore value"] == "NaN"
    assert head["wavelength units"] == "Nanometers"
    # bands by wavelength: 500 (index 1), 600 (index 2: all DO_NOT_USE), 650, 700
    assert head["bbl"] == ["1", "0", "1", "1"]
    assert head["dq file"] == "c.dq.img" and (tmp_path / "c.dq.img") in files
    dq_head = parse_envi_header(tmp_path / "c.dq.hdr")
    assert dq_head["data type"] == "12"  # uint16
    assert dq_head["dq bit names"] == [r["name"] for r in table()]
    assert [int(v) for v in dq_head["dq bit values"]] == [r["value"] for r in table()]
    assert "DQ bits (uint16;" in str(dq_head["description"])
    # the DQ plane takes half the bytes of the float32 cube
    assert (tmp_path / "c.dq.img").stat().st_size * 2 == (tmp_path / "c.img").stat().st_size


def test_spy_reads_the_bad_band_list_and_the_ignore_value(tmp_path):
    spectral = pytest.importorskip("spectral")
    write_cube(_cube(), tmp_path / "c.hdr")
    img = spectral.open_image(str(tmp_path / "c.hdr"))
    assert img.metadata["bbl"] == [1, 0, 1, 1]
    assert img.metadata["data ignore value"] == "NaN"
    assert img.bands.band_unit == "Nanometers"
    assert img.bands.centers == [500.0, 600.0, 650.0, 700.0]
