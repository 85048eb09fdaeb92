"""hsiffc: leakage-aware calibration and flat-field correction for low-light CMOS
hyperspectral snapshot-mosaic sensors.

What a newcomer needs first is here, each name imported from its module the first time it is
used (``import hsiffc`` itself imports no numerical code and compiles nothing):

* reading: :func:`read_sweep`, :func:`open_source` (any supported format), :func:`read_cube`
  (a cube file hsiffc wrote, back with its wavelengths and DQ);
* calibrating: :func:`calibrate` (a :class:`Sweep` -> a per-pixel calibration);
* correcting: :class:`Pipeline` of stages made by :func:`create`, applied to a :class:`Frame`;
* the data model: :class:`Frame`, :class:`Sweep`, :class:`Mosaic`, and :class:`DQ` (the flags
  of every sample).

``hsiffc.calibrate`` is the function even once the package of the same name is imported (its
modules are imported by their path: ``from hsiffc.calibrate import Calibration``).

>>> import hsiffc
>>> callable(hsiffc.calibrate), hsiffc.Frame.__module__
(True, 'hsiffc.data.frame')
"""

import importlib as _importlib
import sys as _sys
import types as _types

from ._moved import install as _install

_install()  # old module paths (hsiffc.frame, ...) keep working

#: public name -> the module it lives in (imported on first use: see ``__getattr__``)
_FACE = {
    "DQ": "hsiffc.data.dq",
    "Frame": "hsiffc.data.frame",
    "Mosaic": "hsiffc.data.mosaic",
    "Sweep": "hsiffc.data.sweep",
    "read_sweep": "hsiffc.io",
    "open_source": "hsiffc.io",
    "read_cube": "hsiffc.cubes",
    "calibrate": "hsiffc.calibrate",
    "Pipeline": "hsiffc.stages",
    "create": "hsiffc.stages",
}

__all__ = ["DQ", "Frame", "Mosaic", "Pipeline", "Sweep", "__version__",
           "calibrate", "create", "open_source", "read_cube", "read_sweep"]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hsiffc")
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "0.0.0+unknown"


__version__ = _version()


def __getattr__(name: str):
    """Import a public name from its module the first time it is asked for (PEP 562)."""
    where = _FACE.get(name)
    if where is None:
        raise AttributeError(f"module 'hsiffc' has no attribute {name!r}")
    value = getattr(_importlib.import_module(where), name)
    globals()[name] = value  # later look-ups find it at once
    return value


def __dir__() -> list[str]:
    """The public face (``__all__``), not the helpers of this module."""
    return sorted(__all__)


class _Face(_types.ModuleType):
    """The package's module type: importing the package ``hsiffc.calibrate`` sets the attribute
    ``calibrate`` of its parent to the package, which would hide the function of the face
    (after any command or module had imported it). Here the attribute stays the function; any
    other value set (a test's stand-in) is kept."""

    @property
    def calibrate(self):
        """:func:`hsiffc.calibrate.calibrate` (or what was set in its place)."""
        fn = self.__dict__.get("_calibrate")
        if fn is None:
            fn = _importlib.import_module("hsiffc.calibrate").calibrate
            self.__dict__["_calibrate"] = fn
        return fn

    @calibrate.setter
    def calibrate(self, value):
        if not isinstance(value, _types.ModuleType):  # the import system's setattr is ignored
            self.__dict__["_calibrate"] = value

    @calibrate.deleter
    def calibrate(self):
        self.__dict__.pop("_calibrate", None)


_sys.modules[__name__].__class__ = _Face
