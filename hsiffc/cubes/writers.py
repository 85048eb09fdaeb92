"""Writing a :class:`~hsiffc.cubes.Cube` in the formats users' tools open: :func:`write_cube`.

=========  ===========================  ===================================================
format     files                        what carries the bands and the DQ bit table
=========  ===========================  ===================================================
tiff       ``NAME.tif`` (hsiffc TIFF)   provenance JSON of page 0 (``"cube"``, ``"dq_bits"``)
envi       ``NAME.hdr/.img``,           header ``wavelength``, ``fwhm``, ``band names``,
           ``NAME.dq.hdr/.img``,        ``default bands``, ``hsiffc ...`` (below); the DQ
           ``NAME.alpha.hdr/.img``      header ``dq bit names``, ``dq bit values``,
                                        ``dq bit meanings``
ome        ``NAME.ome.tif``             OME-XML: channels named by wavelength, with
                                        ``EmissionWavelength`` (nm); series 0 data, 1 DQ,
                                        2 alpha; Description: JSON with the bit table
netcdf     ``NAME.nc``                  coordinates ``band`` (index), ``wavelength``; ``dq``
                                        CF ``flag_masks`` / ``flag_meanings``; attributes
                                        (needs xarray)
=========  ===========================  ===================================================

Each format keeps what :func:`~hsiffc.cubes.read_cube` needs to give the cube back as written
(band index and mosaic position, unit, history, attributes): the hsiffc TIFF and the OME-TIFF
in their JSON, netCDF in coordinates and attributes, ENVI in ``hsiffc version``,
``hsiffc band index``, ``hsiffc band positions``, ``hsiffc history`` and ``hsiffc attrs``
(JSON lists). A reflectance cube (unit ``reflectance factor``) gets ENVI's
``reflectance scale factor = 1.0``.

ENVI headers are written and parsed by :mod:`hsiffc.io.envi`, not SPy: SPy is an optional
dependency, and the reader must apply hsiffc's size limits and refuse a damaged header before
any data is read (SPy's ``envi.read_envi_header`` reads a header of any size whole). SPy opens
every file written here (``tests/io/test_io_end_to_end.py`` compares its arrays with
:func:`~hsiffc.cubes.read_cube`'s). The DQ and alpha companions are ENVI pairs of their own,
``NAME.dq.hdr`` + ``NAME.dq.img``: each header is its data file's name with ``.hdr`` in place
of ``.img``, the pairing ENVI, SPy (``spectral.open_image``) and GDAL's ENVI driver look for, so
each opens alone; ENVI has no standard key that links a quality file to its cube, so the data
header names it in ``dq file`` (and ``alpha file``).

The DQ plane of the ENVI, OME-TIFF and netCDF files is stored in the smallest unsigned type that
holds the DQ bits in use (:func:`dq_storage`: uint16 today), with the bit table beside it; the
hsiffc TIFF keeps its uint32 DQ pages. The ENVI data header also gives ``data ignore value``
(NaN: hsiffc stores none, the DQ file says what to leave out) and ``bbl`` (0 for a band with no
usable value).

Every file written here holds the bands by wavelength, ascending (the hsiffc TIFF that
``hsiffc correct`` streams keeps the pipeline's band order and records it in its provenance's
``"cube"``). Each file is written atomically.
"""

from __future__ import annotations

import errno
import json
import os
import re
from pathlib import Path

import numpy as np
import tifffile

from ..files.atomic import atomic_path
from ..data.dq import TABLE_VERSION, table
from ..errors import DataFormatError, HsiffcError
from ..files.jsonsafe import json_safe

__all__ = ["FORMATS", "COMPRESSIONS", "format_for", "cube_files", "dq_storage", "write_cube"]

#: format -> the suffix of its main file
FORMATS = {"tiff": ".tif", "envi": ".hdr", "ome": ".ome.tif", "netcdf": ".nc"}
#: compressions the TIFF formats take (imagecodecs), and netCDF (zlib only)
COMPRESSIONS = ("zlib", "zstd", "lzma")
_BIGTIFF_ABOVE = 2 ** 32 - 2 ** 26


def format_for(path) -> str:
    """The format a file name asks for: ``.ome.tif``/``.ome.tiff`` ome, ``.tif``/``.tiff``
    tiff, ``.hdr``/``.img`` envi, ``.nc`` netcdf.

    >>> format_for("a.ome.tif"), format_for("b.hdr"), format_for("c.nc")
    ('ome', 'envi', 'netcdf')
    """
    name = Path(path).name.lower()
    if name.endswith((".ome.tif", ".ome.tiff")):
        return "ome"
    for suffix, fmt in ((".tif", "tiff"), (".tiff", "tiff"), (".hdr", "envi"), (".img", "envi"),
                        (".nc", "netcdf")):
        if name.endswith(suffix):
            return fmt
    raise DataFormatError(f"cannot tell the cube format from the name {Path(path).name!r}; "
                          f"end it in .tif, .ome.tif, .hdr or .nc, or give format= "
                          f"({', '.join(FORMATS)})")


def _stem(path: Path) -> Path:
    name = path.name
    for suffix in (".ome.tiff", ".ome.tif", ".tiff", ".tif", ".hdr", ".img", ".nc"):
        if name.lower().endswith(suffix):
            return path.with_name(name[:-len(suffix)])
    return path


def cube_files(path, fmt: str, *, alpha: bool = True) -> list[Path]:
    """Every file :func:`write_cube` writes for ``path`` in format ``fmt``.

    >>> [p.name for p in cube_files("a.hdr", "envi", alpha=False)]
    ['a.hdr', 'a.img', 'a.dq.hdr', 'a.dq.img']
    """
    base = _stem(Path(path))
    if fmt == "envi":
        parts = ["", ".dq"] + ([".alpha"] if alpha else [])
        return [base.with_name(base.name + p + s) for p in parts for s in (".hdr", ".img")]
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return [base.with_name(base.name + FORMATS[fmt])]


def dq_storage(dq) -> np.ndarray:
    """``dq`` in the smallest unsigned integer type that holds the DQ bits in use: every bit of
    the DQ table (:func:`hsiffc.data.dq.table`) and any other bit set in ``dq``. The table's
    highest bit is below 16 today, so a DQ plane is stored as uint16, half the bytes of the
    in-memory uint32 (:data:`hsiffc.data.dq.DQ_DTYPE`); readers give it back as that type.

    Parameters
    ----------
    dq : ndarray of unsigned integers
        A DQ plane.

    Returns
    -------
    ndarray
        The same values as uint8, uint16 or uint32 (``dq`` itself when its type is already the
        smallest).

    Examples
    --------
    >>> dq_storage(np.array([0, 2, 2048], np.uint32)).dtype
    dtype('uint16')
    >>> dq_storage(np.array([0, 1 << 20], np.uint32)).dtype
    dtype('uint32')
    """
    dq = np.asarray(dq)
    used = max(r["value"] for r in table())
    if dq.size:
        used |= int(np.bitwise_or.reduce(dq, axis=None))
    for kind in (np.uint8, np.uint16, np.uint32):
        if used <= np.iinfo(kind).max:
            return dq if dq.dtype == kind else dq.astype(kind)
    return dq.astype(np.uint64)


def _document(cube) -> dict:
    from .. import __version__

    return json_safe({"format": "hsiffc-cube", "hsiffc_version": __version__,
                      "cube": cube.describe(),
                      "dq_bits": table(), "dq_table_version": TABLE_VERSION,
                      "history": list(cube.history), "attrs": cube.attrs})


def write_cube(cube, path, *, format: str | None = None, compression: str | None = None,
               overwrite: bool | None = None, description: str = "",
               extra: dict | None = None, fileset=None) -> list[Path]:
    """Write a cube (with its DQ and alpha) as ``format``.

    Parameters
    ----------
    cube : Cube or Frame
        A :class:`~hsiffc.cubes.Cube` or a reconstructed :class:`~hsiffc.data.frame.Frame`.
    path : str or Path
        The main file (its suffix chooses the format when ``format`` is None).
    format : {"tiff", "envi", "ome", "netcdf"}, optional
    compression : {"zlib", "zstd", "lzma"} or dict, optional
        For the TIFF formats (imagecodecs), and netCDF (zlib). ENVI is never compressed. A
        dict names it per plane (``{"dq": "zstd"}``: the DQ plane only, which compresses
        tenfold or more at little cost, where float data gain ~20 %).
    overwrite : bool, optional
        Replace existing files (default: the current write policy, which refuses).
    description : str
        A line saying what the cube is (ENVI ``description``, TIFF provenance).
    extra : dict, optional
        More ENVI header entries.
    fileset : hsiffc.files.atomic.FileSet, optional
        Leave every file in this set (renamed with the rest of it by its ``commit``) instead
        of renaming each when it is written.

    Returns
    -------
    list of Path
        The files written.
    """
    from .product import Cube

    if not isinstance(cube, Cube):
        cube = Cube.from_frame(cube)
    path = Path(path)
    fmt = format or format_for(path)
    if fmt not in FORMATS:
        raise DataFormatError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}",
                              path=path)
    codecs = compression.values() if isinstance(compression, dict) else [compression]
    if any(c is not None and c not in COMPRESSIONS for c in codecs):
        raise DataFormatError(f"compression must be one of {', '.join(COMPRESSIONS)} (or a "
                              f"dict of them per plane: data, dq, alpha), got {compression!r}",
                              path=path)
    if fmt == "envi" and compression is not None:
        raise DataFormatError("ENVI files are not compressed; drop the compression or choose "
                              "tiff, ome or netcdf", path=path)
    files = cube_files(path, fmt, alpha=cube.alpha is not None)
    put = {"overwrite": overwrite, "fileset": fileset}  # how each file is put in place
    if fmt == "envi":
        _write_envi(cube.sorted(), files[0], description, extra, put)
    elif fmt == "ome":
        _write_ome(cube.sorted(), files[0], compression, description, put)
    elif fmt == "netcdf":
        _write_netcdf(cube, files[0], compression, description, put)
    else:
        _write_tiff(cube.sorted(), files[0], compression, description, put)
    return files


def _write_tiff(cube, path, compression, description, put) -> None:
    from ..io.corrected import CorrectedWriter

    doc = {**_document(cube), "format_note": description or "written by hsiffc.io.write_cube",
           "alpha_computed": cube.alpha is not None}
    doc.pop("format")
    with atomic_path(path, **put) as tmp:
        writer = CorrectedWriter(tmp, doc, n_frames=1, frame_shape=cube.data.shape,
                                 alpha=cube.alpha is not None, compression=compression)
        with writer:
            writer.write(cube.data, cube.dq, cube.alpha)
            writer.finish()


def _envi_dq_entries() -> dict:
    rows = table()
    return {"dq bit names": [r["name"] for r in rows],
            "dq bit values": [r["value"] for r in rows],
            "dq bit meanings": [r["meaning"] for r in rows],
            "dq table version": TABLE_VERSION}


def _bad_band_list(dq) -> list[int]:
    """ENVI's ``bbl``: 1 for a band with a usable value, 0 for one whose every value is
    flagged DO_NOT_USE (ENVI tools and SPy leave such bands out of plots and statistics)."""
    from ..data.dq import DQ

    flag = dq.dtype.type(DQ.DO_NOT_USE)
    return [0 if np.all(dq[:, :, b] & flag) else 1 for b in range(dq.shape[2])]


def _envi_provenance(cube) -> dict:
    """The ENVI header entries that give a cube back as written (:func:`read_cube`): the
    hsiffc version, each band's index in the pipeline's cube and its mosaic position
    (``r0c1``, ``none`` for a virtual band), and the history and attributes as JSON text.
    An ENVI value may not begin with a brace (a reader takes it for a list), so both JSON
    values are lists: ``hsiffc history`` one entry per stage, ``hsiffc attrs`` one
    ``[name, value]`` pair per attribute."""
    from .. import __version__

    positions = cube.positions or [None] * cube.n_bands
    return {"hsiffc version": __version__,
            "hsiffc band index": list(cube.band_index),
            "hsiffc band positions": ["none" if p is None else f"r{p[0]}c{p[1]}"
                                      for p in positions],
            "hsiffc history": json.dumps(json_safe(list(cube.history)), allow_nan=False),
            "hsiffc attrs": json.dumps(json_safe([[k, v] for k, v in cube.attrs.items()]),
                                       allow_nan=False)}


def _write_envi(cube, header: Path, description, extra, put) -> None:
    from ..io.envi import check_header_values, write_envi

    base = header.with_suffix("")
    bands = {"band names": cube.band_names()}
    if cube.fwhm_nm is not None:
        bands["fwhm"] = list(cube.fwhm_nm)
    if cube.n_bands >= 3:
        bands["default bands"] = [b + 1 for b in cube.default_bands()]  # ENVI counts from 1
    common = {**(extra or {})}
    if "exposure_ms" in cube.attrs:
        common.setdefault("exposure time", cube.attrs["exposure_ms"])
        common.setdefault("exposure time units", "ms")
    wl = cube.wavelengths_nm
    text = description or "hsiffc spectral cube"
    names = {k: v for k, v in bands.items() if k != "band names"}
    files = {"dq": base.with_name(base.name + ".dq"),
             "alpha": base.with_name(base.name + ".alpha")}
    data_extra = {**common, **names, "data units": cube.unit,
                  "data ignore value": "NaN", "bbl": _bad_band_list(cube.dq),
                  "dq file": files["dq"].name + ".img", **_envi_provenance(cube)}
    if cube.unit == "reflectance factor":  # ENVI: the value that scales the data to 0-1
        data_extra["reflectance scale factor"] = 1.0
    if cube.alpha is not None:
        data_extra["alpha file"] = files["alpha"].name + ".img"
    # every header's text checked before the first file is written: a name that cannot be
    # written (a line break, not UTF-8) must not leave a .dq.img without its data pair
    check_header_values(text, cube.unit, *[v for v in data_extra.values()
                                           if not isinstance(v, (int, float, list))])
    dq = dq_storage(cube.dq)
    write_envi(files["dq"], dq, wavelengths_nm=wl, band_names=cube.band_names(),
               description=f"{text}: DQ bits ({dq.dtype}; names and values in dq bit names / "
                           "dq bit values)", interleave="bsq",
               extra={**common, **names, **_envi_dq_entries()}, **put)
    if cube.alpha is not None:
        write_envi(files["alpha"], cube.alpha, wavelengths_nm=wl, band_names=cube.band_names(),
                   description=f"{text}: leakage percentage alpha (percent)",
                   extra={**common, **names, "data units": "percent"}, **put)
    write_envi(base, cube.data, wavelengths_nm=wl, band_names=cube.band_names(),
               description=f"{text} ({cube.unit})", interleave="bsq", extra=data_extra,
               **put)


def _write_ome(cube, path: Path, compression, description, put) -> None:
    names = cube.band_names()
    doc = json.dumps({**_document(cube), "note": description}, allow_nan=False)
    planes = [("data", cube.data, names),
              ("dq", dq_storage(cube.dq), [f"DQ {n}" for n in names])]
    if cube.alpha is not None:
        planes.append(("alpha", cube.alpha, [f"alpha {n}" for n in names]))
    volume = sum(a.nbytes for _, a, _ in planes)
    wl = cube.wavelengths_nm
    # OME's EmissionWavelength is a positive float: given only where every band has one
    emission = ({"EmissionWavelength": [float(w) for w in wl],
                 "EmissionWavelengthUnit": ["nm"] * cube.n_bands}
                if wl is not None and all(np.isfinite(w) and w > 0 for w in wl) else {})
    with atomic_path(path, **put) as tmp:
        with tifffile.TiffWriter(tmp, ome=True, bigtiff=volume > _BIGTIFF_ABOVE) as tw:
            for name, arr, channels in planes:
                meta = {"axes": "CYX", "Name": name, "Channel": {"Name": channels, **emission}}
                if name == "data":
                    meta["Description"] = doc
                codec = compression.get(name) if isinstance(compression, dict) else compression
                tw.write(np.ascontiguousarray(np.moveaxis(arr, 2, 0)), photometric="minisblack",
                         compression=codec, metadata=meta)


def _write_netcdf(cube, path: Path, compression, description, put) -> None:
    from .xr import require_xarray, to_xarray

    require_xarray()
    try:
        import h5netcdf  # noqa: F401
        engine = "h5netcdf"
    except ImportError:
        try:
            import netCDF4  # noqa: F401
            engine = "netcdf4"
        except ImportError:
            raise HsiffcError("writing netCDF needs h5netcdf or netCDF4: pip install "
                              "'hsiffc[xarray]'") from None
    ds = to_xarray(cube)
    dq = dq_storage(ds["dq"].values)  # CF: the flag masks have the variable's type
    ds["dq"] = ds["dq"].copy(data=dq)
    ds["dq"].attrs["flag_masks"] = ds["dq"].attrs["flag_masks"].astype(dq.dtype)
    if description:
        ds.attrs["description"] = description
    codecs = {v: compression.get(v) if isinstance(compression, dict) else compression
              for v in ds.data_vars}
    if any(c not in (None, "zlib") for c in codecs.values()):
        raise DataFormatError(f"netCDF compression is zlib only, got {compression!r}",
                              path=path)
    encoding = {v: {"zlib": True, "complevel": 4} for v, c in codecs.items() if c}
    with atomic_path(path, **put) as tmp:
        try:
            ds.to_netcdf(tmp, engine=engine, encoding=encoding)
        except OSError as exc:  # HDF5's are several lines naming the temporary file
            raise _one_line_os_error(exc, path) from None


def _one_line_os_error(exc: OSError, path: Path) -> OSError:
    """``exc`` as one line naming ``path`` (not the temporary file): HDF5 reports a full disk
    as ``Can't write data (file write failed: ..., errno = 28, error message = 'No space left
    on device', ...)`` over several lines."""
    text = str(exc)
    found = re.search(r"errno = (\d+)", text)
    code = exc.errno or (int(found.group(1)) if found else None)
    if code:
        return OSError(code, os.strerror(code), str(path))
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return OSError(errno.EIO, f"the netCDF library failed: {first[:200]}", str(path))
