"""Spectral cubes leaving hsiffc: labelled bands, files users' tools open, a picture of the result.

* :class:`Cube` - an ``(H, W, B)`` cube with its DQ and alpha, the bands' wavelengths, widths
  and mosaic positions, and its history; :meth:`Cube.from_frame` takes a reconstructed
  :class:`~hsiffc.data.frame.Frame`, :meth:`Cube.sorted` orders the bands by wavelength.
* :func:`write_cube` - one function for every format (:data:`FORMATS`): the hsiffc TIFF,
  ENVI (bands by wavelength, DQ as its own file), OME-TIFF (channels named by wavelength),
  netCDF and zarr (through xarray, optional). Every file carries the DQ bit table.
* :func:`read_cube` - a cube file written here back as a :class:`Cube`.
* :func:`to_xarray` - an ``xarray.Dataset`` (dims y, x, band; coordinate wavelength).
* :func:`quicklook` - one PNG: pseudo-colour, a grid of bands, the DQ map, a spectrum.

The formats, side by side, are described in ``docs/formats-and-metadata.md``.
"""

from __future__ import annotations

from .product import Cube, default_bands
from .readers import read_cube
from .writers import FORMATS, format_for, write_cube
from .xr import to_xarray

__all__ = ["Cube", "FORMATS", "default_bands", "format_for", "quicklook", "read_cube",
           "to_xarray", "write_cube"]


def quicklook(*args, **kwargs):
    """See :func:`hsiffc.cubes.look.quicklook` (imports matplotlib on first use)."""
    from . import look

    return look.quicklook(*args, **kwargs)
