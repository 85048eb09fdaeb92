"""Reading a cube file written by :func:`~hsiffc.cubes.write_cube` or ``hsiffc correct`` back
as a :class:`~hsiffc.cubes.Cube` (for quicklooks and round trips): :func:`read_cube`."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, HsiffcError
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
    if "dq bit names" in raw and "dq file" not in raw:
        raise DataFormatError("this is the DQ file of a cube (its bit table in 'dq bit names'); "
                              "give the cube's own header, the one whose 'dq file' names this "
                              "file", path=header)
    planes = {}
    for key in ("dq", "alpha"):
        name = raw.get(f"{key} file")
        if isinstance(name, str) and name:
            if Path(name).name != name or name in (".", ".."):
                raise DataFormatError(f"'{key} file = {name[:60]}' is not a file name beside "
                                      "the header (hsiffc writes NAME.dq.img there); the header "
                                      "was altered", path=header)
            planes[key] = read_envi(header.with_name(name).with_suffix(".hdr"))[0]
            if planes[key].shape != data.shape:
                raise DataFormatError(f"the {key} file {name} holds {planes[key].shape}, the "
                                      f"data {data.shape}; the pair is damaged or mixed up",
                                      path=header)
    dq = planes.get("dq")  # stored in the smallest type (uint16); Cube gives it as DQ_DTYPE
    if dq is None:
        dq = np.zeros(data.shape, np.uint32)
    fwhm = raw.get("fwhm")
    try:
        fwhm = _floats(fwhm) if isinstance(fwhm, list) else None
    except ValueError:
        raise DataFormatError("'fwhm' holds values that are not numbers (nm); correct or "
                              "remove it", path=header) from None
    bands = _envi_bands(raw, data.shape[2], header)
    return Cube(data.astype(np.float32), dq.astype(np.uint32), planes.get("alpha"),
                head.get("wavelengths_nm"), fwhm, *bands,
                unit=str(raw.get("data units", "DN")), **_envi_history(raw, path, header))


def _envi_bands(raw: dict, n: int, header: Path):
    """Band positions and indices from ``hsiffc band positions`` / ``hsiffc band index``
    (written by :func:`~hsiffc.cubes.write_cube`); (None, None) for another program's file,
    or where their lengths are not the cube's (a tool that kept the keys when it wrote a
    subset of the bands)."""
    index, where = raw.get("hsiffc band index"), raw.get("hsiffc band positions")
    if not isinstance(index, list) or not isinstance(where, list) or not (
            len(index) == len(where) == n):
        return None, None
    positions = []
    for item in where:
        found = re.fullmatch(r"r(\d+)c(\d+)", item)
        if item != "none" and not found:
            raise DataFormatError(f"'hsiffc band positions' holds {item[:20]!r}, not rRcC or "
                                  "none; the header was altered", path=header)
        positions.append((int(found[1]), int(found[2])) if found else None)
    try:
        return positions, [int(i) for i in index]
    except ValueError:
        raise DataFormatError("'hsiffc band index' holds values that are not whole numbers; "
                              "the header was altered", path=header) from None


def _envi_history(raw: dict, path: Path, header: Path) -> dict:
    """The cube's history and attributes as written (``hsiffc history``, ``hsiffc attrs``:
    JSON lists); another program's file gets its own name as ``source``."""
    if "hsiffc attrs" not in raw and "hsiffc history" not in raw:
        return {"attrs": {"source": path.name}}
    try:
        history = json.loads(_text(raw.get("hsiffc history", "[]")))
        pairs = json.loads(_text(raw.get("hsiffc attrs", "[]")))
        attrs = {str(k): v for k, v in pairs}
        if not isinstance(history, list) or not all(isinstance(h, dict) for h in history):
            raise ValueError("not a list of stages")
    except (ValueError, TypeError):
        raise DataFormatError("'hsiffc history' / 'hsiffc attrs' is not the JSON hsiffc "
                              "writes; the header was altered", path=header) from None
    return {"history": history, "attrs": attrs}


def _text(value) -> str:
    """A header value as the text written (a value holding commas is one string here)."""
    return ", ".join(value) if isinstance(value, list) else str(value)


def _hsiffc_tiff(path: Path, frame: int) -> Cube:
    from ..io.corrected import read_corrected
    from .export import cube_from_corrected

    got = read_corrected(path, frames=[frame])
    cube = cube_from_corrected(got.provenance, frame, got.data[0], got.dq[0], got.alpha[0],
                               source=path.name)
    prov = got.provenance
    if isinstance(prov.get("attrs"), dict) and isinstance(prov.get("history"), list):
        # written by write_cube (not hsiffc correct): its history and attributes as written
        cube = replace(cube, history=tuple(prov["history"]), attrs=prov["attrs"])
    return cube


def _ome(path: Path) -> Cube:
    import tifffile

    with tifffile.TiffFile(path) as tf:
        series = tf.series
        if not tf.is_ome or len(series) < 2:
            raise DataFormatError("not an OME-TIFF cube written by hsiffc (data and DQ "
                                  "series)", path=path)
        _check_sizes(path, [(s.shape, s.dtype) for s in series[:3]])
        data, dq = _yxc(series[0]), _yxc(series[1])
        alpha = _yxc(series[2]) if len(series) > 2 else None
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
                unit=info.get("unit", "DN"), history=doc.get("history") or (),
                attrs=doc["attrs"] if isinstance(doc.get("attrs"), dict)
                else {"source": path.name})


def _yxc(series) -> np.ndarray:
    """An OME series (C, Y, X) as (Y, X, C); tifffile gives a one-band cube's series as (Y, X)."""
    arr = series.asarray()
    return arr[:, :, None] if arr.ndim == 2 else np.moveaxis(arr, 0, 2)


def _netcdf(path: Path) -> Cube:
    from .xr import require_xarray

    xr = require_xarray()
    _no_external_storage(path)
    with xr.open_dataset(path) as ds:
        _check_sizes(path, [(ds[k].shape, ds[k].dtype) for k in ("data", "dq", "alpha")
                            if k in ds])
        alpha = ds["alpha"].values if "alpha" in ds else None
        rows, cols = ds["pattern_row"].values, ds["pattern_col"].values
        positions = [None if r < 0 else (int(r), int(c)) for r, c in zip(rows, cols)]
        wl = ds["wavelength"].values
        fwhm = ds["fwhm"].values
        history, attrs = _netcdf_attrs(ds.attrs, path)
        return Cube(ds["data"].values, ds["dq"].values, alpha,
                    None if np.isnan(wl).all() else wl, None if np.isnan(fwhm).all() else fwhm,
                    positions, ds["band_index"].values, unit=str(ds.attrs.get("unit", "DN")),
                    history=history, attrs=attrs)


def _netcdf_attrs(stored: dict, path: Path) -> tuple:
    """The cube's history and attributes from a netCDF file's global attributes: those
    :func:`~hsiffc.cubes.to_xarray` lists in ``json_attrs`` decoded from JSON text, numbers as
    Python numbers; another program's file (no ``json_attrs``) gets its own name as
    ``source``."""
    from .xr import OWN_ATTRS

    if "json_attrs" not in stored:  # another program's, or written before hsiffc 0.2
        try:
            history = json.loads(str(stored.get("history", "[]")))
        except ValueError:
            history = []
        ok = isinstance(history, list) and all(isinstance(h, dict) for h in history)
        return (tuple(history) if ok else ()), {"source": path.name}
    as_json = str(stored["json_attrs"]).split()
    try:
        history = json.loads(str(stored.get("history", "[]")))
        attrs = {k: json.loads(str(v)) if k in as_json else
                 (v.item() if isinstance(v, np.generic) else v)
                 for k, v in stored.items() if k not in OWN_ATTRS}
    except ValueError:
        raise DataFormatError("an attribute listed in 'json_attrs' (or 'history') is not JSON "
                              "text; the file was altered", path=path) from None
    return history, attrs


def _no_external_storage(path: Path) -> None:
    """Refuse a netCDF-4 (HDF5) file whose variables keep their data in other files (HDF5
    external or virtual storage): decoding them would draw another file's bytes, perhaps any
    file on the disk, into a quicklook a user may share."""
    try:
        import h5py
    except ImportError:  # xarray then reads through netCDF4, which has the same HDF5 library
        return
    try:
        h5 = h5py.File(path, "r")
    except OSError:  # not HDF5 (netCDF classic): no external storage
        return
    bad: list = []
    with h5:
        h5.visititems(lambda name, obj: bad.append(name) if isinstance(obj, h5py.Dataset) and (
            obj.external or obj.is_virtual) else None)
    if bad:
        raise DataFormatError(f"variable {bad[0]!r} keeps its data in another file (HDF5 "
                              "external or virtual storage); hsiffc reads only data stored in "
                              "the file it is given", path=path)


def _check_sizes(path, arrays) -> None:
    """The limits in force (``HSIFFC_MAX_FRAME_PIXELS``, ``HSIFFC_MAX_BYTES``) applied to the
    (shape, dtype) each plane's header states, before any is decoded."""
    from ..files.limits import default_limits

    limits = default_limits()
    total = 0
    for shape, dtype in arrays:
        limits.check_frames(path=path, n_frames=1, shape=shape or (1,),
                            itemsize=np.dtype(dtype).itemsize)
        total += int(np.prod(shape, dtype=np.float64)) * np.dtype(dtype).itemsize
    limits.check_bytes(path=path, nbytes=total, what="the cube's planes")


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
        As written: data, DQ (uint32), alpha, wavelengths, widths, band indices and mosaic
        positions, unit, history and attributes (a file another program wrote has its own
        name as ``attrs["source"]``).

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
    from ..files.atomic import require_regular_input

    path = Path(path)
    if not path.exists():
        raise DataFormatError("cube file not found", path=path)
    require_regular_input(path, what="cube file")  # a FIFO or device is never opened
    fmt = format_for(path)
    readers = {"envi": _envi, "ome": _ome, "netcdf": _netcdf,
               "tiff": lambda p: _hsiffc_tiff(p, int(frame))}
    try:
        return readers[fmt](path)
    except (HsiffcError, MemoryError):
        raise
    except Exception as exc:  # tifffile, HDF5 and xarray raise many types on damaged files,
        # and a header's values may not make a Cube (3 bands, 1 wavelength)
        what = {"ome": "OME-TIFF cube", "netcdf": "netCDF cube", "envi": "ENVI cube",
                "tiff": "corrected file"}[fmt]
        text = " ".join(str(exc).split())[:200]
        raise DataFormatError(f"not a readable {what} written by hsiffc ({type(exc).__name__}: "
                              f"{text}); the file is damaged or another program's",
                              path=path) from exc
