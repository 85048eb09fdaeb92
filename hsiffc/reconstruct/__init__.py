"""Spectral-cube reconstruction from a raw snapshot-mosaic frame (array functions, no I/O).

A snapshot-mosaic sensor samples one band per pixel; the bands repeat in tiles of
``mosaic.tile_shape`` pixels starting at ``mosaic.offset``. This package turns a raw frame
``(H, W)`` into a cube:

* :func:`demosaic` - every band at every pixel, ``(H, W, B)``, by one of
  :data:`DEMOSAIC_METHODS` (``"nearest"``, ``"bilinear"``, ``"ppid"``, ``"ppid_paper"``,
  ``"ppid_edge"``, ``"itsd"``);
* :func:`tile_cube` - one spectrum per complete tile, ``(H', W', B)`` (reduced resolution);
* :func:`apply_correction` - a spectral correction matrix applied per pixel
  (``virtual = C @ b``), e.g. the IMEC vendor matrix;
* :func:`reconstruction_error` - per-band RMS relative error against a true cube.

Band order
----------
The cube's last axis is the mosaic's band index (``mosaic.band_map`` values). For IMEC sensors
(:meth:`hsiffc.spectral.ImecSensorCalibration.mosaic`) band ``i`` sits at tile position ``i``
(row-major), so the band order is the *pattern-position* order, which is the column order of
the vendor correction matrix - not wavelength order.

Flagged samples and the DQ rule
-------------------------------
A raw sample is *flagged* when its DQ value is non-zero (or its value is NaN/inf, which adds
``NONFINITE | DO_NOT_USE``). Flagged samples are never sources: they get weight 0 in the
normalised convolutions below, so their values never propagate and nothing becomes NaN. For
band ``b`` at pixel ``x`` let ``S1`` be the same-band samples within the bilinear support
(``|dy| < ph`` and ``|dx| < pw``, ``(ph, pw)`` the tile shape) and ``S2`` those within twice
that. Then (the same for every method):

1. value: the method's estimate from the unflagged samples ("nearest": where the tile's own
   sample is flagged or outside the frame, the bilinear estimate from ``S1``); where ``S1``
   holds no unflagged sample, the same interpolation with a kernel twice as wide (``S2``: a
   flagged sample is bridged from its same-band neighbours one tile away); where ``S2`` has
   none either, the median of the band's unflagged samples (0 if there is none);
2. DQ: at the band's own sample sites, the sample's own flags (a raw flag is never lost);
   where ``S1`` holds no unflagged sample, additionally the OR of the flags of the samples in
   ``S1`` (the value stands in for those samples); where the median was used, additionally
   ``DO_NOT_USE``. Everywhere else the band value is GOOD (0).

The DQ plane therefore depends only on which samples are flagged, not on the method.
"""

from __future__ import annotations

from .correction import (apply_correction, correction_support, reconstruction_error,
                         reduce_over_support)
from .demosaic import (DEMOSAIC_METHODS, DemosaicMethod, Demosaiced, demosaic,
                       reconstruct_alpha)
from .prepare import ppi_kernel
from .tiles import tile_cube, tile_origin

__all__ = ["DEMOSAIC_METHODS", "DemosaicMethod", "Demosaiced", "apply_correction",
           "correction_support", "demosaic", "ppi_kernel", "reconstruct_alpha",
           "reconstruction_error", "reduce_over_support", "tile_cube", "tile_origin"]
