"""A :class:`~hsiffc.cubes.Cube` as an ``xarray.Dataset`` (optional: ``pip install hsiffc[xarray]``).

Layout: dims ``(y, x, band)``; coordinates ``band`` (0, 1, ... in the Dataset's band order:
an index), ``wavelength`` (nm, ascending; an index too, ``ds.sel(wavelength=650.0,
method="nearest")``), ``fwhm`` (nm), ``band_index`` (the band's index in the pipeline's cube),
``pattern_row`` / ``pattern_col`` (its position in the mosaic tile; -1 for virtual bands) and
``band_name``; variables ``data`` (float32, in the cube's unit), ``dq`` (uint32, CF
``flag_masks`` / ``flag_meanings`` attributes: the bit table) and ``alpha`` (float32 percent,
when computed). Dataset attributes: ``history`` and ``dq_bits`` (JSON text: netCDF attributes
are flat), the cube's unit and whatever the cube's ``attrs`` hold: strings and numbers as they
are, anything else as JSON text, named in ``json_attrs`` (so that
:func:`~hsiffc.cubes.read_cube` gives them back). A netCDF file keeps no index on
``wavelength`` (not a dimension): after ``xarray.open_dataset``, ``ds.set_xindex("wavelength")``
adds it.
"""

from __future__ import annotations

import json

import numpy as np

from ..data.dq import TABLE_VERSION, table
from ..data.mosaic import band_numbers
from ..errors import HsiffcError
from ..files.jsonsafe import json_safe

__all__ = ["require_xarray", "to_xarray"]


#: global attributes that describe the file, not the cube's ``attrs``
OWN_ATTRS = ("title", "unit", "history", "dq_bits", "band_order", "description", "json_attrs")


def require_xarray():
    """The xarray module, or an error that says how to install it."""
    try:
        import xarray
    except ImportError:
        raise HsiffcError("this needs xarray, an optional dependency: pip install "
                          "'hsiffc[xarray]' (xarray with h5netcdf for netCDF)") from None
    return xarray


def dq_attrs() -> dict:
    """CF-convention attributes of a DQ variable: ``flag_masks`` (uint32 values),
    ``flag_meanings`` (names, space-separated) and the full table as JSON text."""
    rows = table()
    return {"flag_masks": np.array([r["value"] for r in rows], np.uint32),
            "flag_meanings": " ".join(r["name"] for r in rows),
            "dq_bits": json.dumps(rows), "dq_table_version": TABLE_VERSION,
            "long_name": "data-quality bits (hsiffc.data.dq.DQ)"}


def _text(value) -> str:
    return json.dumps(json_safe(value), allow_nan=False)


def to_xarray(cube, *, sort: bool = True):
    """The cube as an ``xarray.Dataset`` (layout in this module's docstring).

    Parameters
    ----------
    cube : Cube or Frame
        A :class:`~hsiffc.cubes.Cube`, or a reconstructed :class:`~hsiffc.data.frame.Frame`.
    sort : bool
        Order the bands by wavelength, ascending (default).

    Returns
    -------
    xarray.Dataset
    """
    from .product import Cube

    xr = require_xarray()
    if not isinstance(cube, Cube):
        cube = Cube.from_frame(cube)
    if sort:
        cube = cube.sorted()
    n = cube.n_bands
    nan = [float("nan")] * n
    rows = [-1 if p is None else p[0] for p in (cube.positions or [None] * n)]
    cols = [-1 if p is None else p[1] for p in (cube.positions or [None] * n)]
    coords = {"wavelength": ("band", np.asarray(cube.wavelengths_nm or nan, np.float64),
                             {"units": "nm", "long_name": "band centre wavelength"}),
              "fwhm": ("band", np.asarray(cube.fwhm_nm or nan, np.float64),
                       {"units": "nm", "long_name": "band full width at half maximum"}),
              "band": ("band", np.asarray(band_numbers(n, cube.wavelengths_nm), np.int32),
                       {"long_name": "band number, counted from 1 by wavelength as hsiffc "
                                     "numbers bands in every table, warning and band name"}),
              "band_index": ("band", np.asarray(cube.band_index, np.int32),
                             {"long_name": "the band's index in the pipeline's cube (the "
                                           "mosaic's band order)"}),
              "pattern_row": ("band", np.asarray(rows, np.int32)),
              "pattern_col": ("band", np.asarray(cols, np.int32)),
              "band_name": ("band", np.asarray(cube.band_names(), dtype=str))}
    variables = {"data": (("y", "x", "band"), cube.data, {"units": cube.unit}),
                 "dq": (("y", "x", "band"), cube.dq, dq_attrs())}
    if cube.alpha is not None:
        variables["alpha"] = (("y", "x", "band"), np.ascontiguousarray(cube.alpha),
                              {"units": "percent", "long_name": "leakage percentage alpha"})
    attrs = {"title": "hsiffc spectral cube", "unit": cube.unit,
             "history": _text(list(cube.history)), "dq_bits": json.dumps(table()),
             "band_order": "wavelength ascending" if cube.is_sorted else "band index"}
    as_json = []
    for key, value in cube.attrs.items():
        if key in OWN_ATTRS or value is None:
            continue
        if isinstance(value, np.generic):
            value = value.item()  # numbers stay numbers (np.float32 is no float)
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            attrs[key] = value
        else:
            attrs[key] = _text(value)
            as_json.append(key)
    attrs["json_attrs"] = " ".join(as_json)
    ds = xr.Dataset(variables, coords=coords, attrs=attrs)
    return ds.set_xindex("wavelength")  # ds.sel(wavelength=650.0, method="nearest")
