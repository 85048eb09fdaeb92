"""Reading a cube file written by :func:`~hsiffc.cubes.write_cube` or ``hsiffc correct`` back
as a :class:`~hsiffc.cubes.Cube` (for quicklooks and round trips): :func:`read_cube`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from .product import Cube
from .writers import format_for

__all__ = ["read_cube"]


def _floats(values):
    return None if values is None else [float(v) for v in values]


def _envi(path: Path) -> Cube:
    from ..io.envi import parse_envi_header, read_envi

    header = path.with_suffix(".hdr")
    data, head = read_envi(header)
    raw = parse_envi_header(header)
    planes = {}
    for key in ("dq", "alpha"):
        name = raw.get(f"{key} file")
        if isinstance(name, str) and name:
            planes[key] = read_envi(header.with_name(name).with_suffix(".hdr"))[0]
    dq = planes.get("dq")  # stored in the smallest type (uint16); Cube gives it as DQ_DTYPE
    if dq is None:
        dq = np.zeros(data.shape, np.uint32)
    fwhm = raw.get("fwhm")
    return Cube(data.astype(np.float32), dq, planes.get("alpha"),
                head.get("wavelengths_nm"), _floats(fwhm) if isinstance(fwhm, list) else None,
                unit=str(raw.get("data units", "DN")), attrs={"source": path.name})


def _hsiffc_tiff(path: Path, frame: int) -> Cube:
    from ..io.corrected import read_corrected
    from .export import cube_from_corrected

    got = read_corrected(path, frames=[frame])
    return cube_from_corrected(got.provenance, frame, got.data[0], got.dq[0], got.alpha[0],
                               source=path.name)


def _ome(path: Path) -> Cube:
    import tifffile

    with tifffile.TiffFile(path) as tf:
        series = tf.series
        if not tf.is_ome or len(series) < 2:
            raise DataFormatError("not an OME-TIFF cube written by hsiffc (data and DQ "
                                  "series)", path=path)
        data = np.moveaxis(series[0].asarray(), 0, 2)
        dq = np.moveaxis(series[1].asarray(), 0, 2)
        alpha = np.moveaxis(series[2].asarray(), 0, 2) if len(series) > 2 else None
        doc = {}
        import xml.etree.ElementTree as ET

        root = ET.fromstring(tf.ome_metadata)
        for el in root.iter():
            if el.tag.endswith("Description") and (el.text or "").startswith("{"):
                doc = json.loads(el.text)
                break
    info = doc.get("cube") or {}
    return Cube(data, dq, alpha, info.get("wavelengths_nm"), info.get("fwhm_nm"),
                info.get("band_positions"), info.get("band_index"),
                unit=info.get("unit", "DN"), attrs={"source": path.name})


def _netcdf(path: Path) -> Cube:
    from .xr import require_xarray

    xr = require_xarray()
    with xr.open_dataset(path) as ds:
        alpha = ds["alpha"].values if "alpha" in ds else None
        rows, cols = ds["pattern_row"].values, ds["pattern_col"].values
        positions = [None if r < 0 else (int(r), int(c)) for r, c in zip(rows, cols)]
        wl = ds["wavelength"].values
        fwhm = ds["fwhm"].values
        return Cube(ds["data"].values, ds["dq"].values, alpha,
                    None if np.isnan(wl).all() else wl, None if np.isnan(fwhm).all() else fwhm,
                    positions, ds["band_index"].values, unit=str(ds.attrs.get("unit", "DN")),
                    attrs={"source": path.name})


def read_cube(path, *, frame: int = 0) -> Cube:
    """A cube file as a :class:`Cube`.

    Parameters
    ----------
    path : str or Path
        An hsiffc TIFF (``hsiffc correct`` output: a mosaic frame becomes one spectrum per
        tile), an ENVI header or data file, an OME-TIFF or a netCDF file written by hsiffc.
    frame : int
        Which frame of an hsiffc TIFF that holds several.

    Returns
    -------
    Cube

    Examples
    --------
    >>> import tempfile
    >>> from hsiffc.io import write_cube
    >>> tmp = tempfile.TemporaryDirectory()
    >>> cube = Cube(np.ones((4, 6, 3), np.float32), np.zeros((4, 6, 3), np.uint32),
    ...             wavelengths_nm=(500.0, 600.0, 700.0))
    >>> paths = write_cube(cube, Path(tmp.name) / "cube.hdr")
    >>> back = read_cube(paths[0])
    >>> back.data.shape, [float(w) for w in back.wavelengths_nm]
    ((4, 6, 3), [500.0, 600.0, 700.0])
    >>> tmp.cleanup()
    """
    path = Path(path)
    if not path.exists():
        raise DataFormatError("cube file not found", path=path)
    fmt = format_for(path)
    if fmt == "envi":
        return _envi(path)
    if fmt == "ome":
        return _ome(path)
    if fmt == "netcdf":
        return _netcdf(path)
    return _hsiffc_tiff(path, int(frame))
