"""hsiffc: leakage-aware calibration and flat-field correction for low-light CMOS
hyperspectral snapshot-mosaic sensors."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("hsiffc")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from .dq import DQ
from .mosaic import Mosaic
from .sweep import Sweep

__all__ = ["DQ", "Mosaic", "Sweep", "__version__"]
