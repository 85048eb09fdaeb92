"""Names and numbers of the corrected-cube layout (``"format": "hsiffc-corrected"``).

The layout itself (three pages per frame, the provenance JSON) is described in
:mod:`hsiffc.io.corrected`; :mod:`hsiffc.io.corrected_writer` writes it and
:mod:`hsiffc.io.corrected` reads it, both from these constants.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FORMAT", "FORMAT_VERSION", "PLANES", "PLANE_DTYPES", "SUFFIX"]

FORMAT = "hsiffc-corrected"
#: 1: mosaic frames (H, W), three pages per frame. 2: also cubes (H, W, B) (one page per plane
#: and frame, the bands as samples), files without alpha pages and compressed pages.
FORMAT_VERSION = 2
PLANES = ("data", "dq", "alpha")
PLANE_DTYPES = {"data": np.float32, "dq": np.uint32, "alpha": np.float32}
#: name of an output: ``<input stem>.corrected.tif``
SUFFIX = ".corrected.tif"
