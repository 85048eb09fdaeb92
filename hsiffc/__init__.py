"""hsiffc: leakage-aware calibration and flat-field correction for low-light CMOS
hyperspectral snapshot-mosaic sensors."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("hsiffc")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from .data.dq import DQ
from .data.mosaic import Mosaic
from .data.sweep import Sweep

from ._moved import install

install()  # old module paths (hsiffc.frame, ...) keep working
del install

__all__ = ["DQ", "Mosaic", "Sweep", "__version__"]
