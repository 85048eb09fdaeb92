"""hsiffc: leakage-aware calibration and flat-field correction for low-light CMOS
hyperspectral snapshot-mosaic sensors.

What a newcomer needs first is here, each name imported from its module the first time it is
used (``import hsiffc`` itself imports no numerical code and compiles nothing):

* reading: :func:`read_sweep`, :func:`open_source` (any supported format), :func:`read_cube`
  (a cube file hsiffc wrote, back with its wavelengths and DQ);
* calibrating: ``calibrate(sweep)`` (a :class:`Sweep` -> a per-pixel calibration);
* correcting: :class:`Pipeline` of stages made by :func:`create`, applied to a :class:`Frame`;
* the data model: :class:`Frame`, :class:`Sweep`, :class:`Mosaic`, and :class:`DQ` (the flags
  of every sample).

``hsiffc.calibrate`` is the package of that name, callable as its function
(``hsiffc.calibrate(sweep)`` is ``hsiffc.calibrate.calibrate(sweep)``), so that its modules are
imported by their path as before (``from hsiffc.calibrate import Calibration``).

>>> import hsiffc
>>> callable(hsiffc.calibrate), hsiffc.Frame.__module__
(True, 'hsiffc.data.frame')
>>> hsiffc.calibrate.Calibration.__module__
'hsiffc.calibrate.product'
"""

import importlib as _importlib
import sys as _sys
import types as _types

from ._moved import install

install()  # old module paths (hsiffc.frame, ...) keep working
del install

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


class _CallablePackage(_types.ModuleType):
    """The module type of the package :mod:`hsiffc.calibrate` once the face has handed it out:
    the package, callable as its function ``calibrate`` (everything else unchanged)."""

    def __call__(self, *args, **kwargs):
        return self.calibrate(*args, **kwargs)

    @property
    def __signature__(self):
        import inspect

        return inspect.signature(self.calibrate)


class _Face(_types.ModuleType):
    """The package's module type. ``hsiffc.calibrate`` is both a package and, on the face, the
    function that calibrates; importing the package sets the attribute to it whatever the face
    held. So the attribute is the package itself, made callable as its function: ``import
    hsiffc.calibrate.joint as j``, ``mock.patch("hsiffc.calibrate....")`` and
    ``hsiffc.calibrate(sweep)`` all work, whichever came first. Any other value set (a test's
    stand-in) is kept until the package or nothing is set again."""

    @property
    def calibrate(self):
        """The package :mod:`hsiffc.calibrate`, callable as
        :func:`hsiffc.calibrate.calibrate` (or what was set in its place)."""
        stand_in = self.__dict__.get("_calibrate")
        if stand_in is not None:
            return stand_in
        package = _importlib.import_module("hsiffc.calibrate")
        if not isinstance(package, _CallablePackage):
            package.__class__ = _CallablePackage
        return package

    @calibrate.setter
    def calibrate(self, value):
        if isinstance(value, _types.ModuleType):  # the package (the import system, an undo)
            self.__dict__.pop("_calibrate", None)
        else:
            self.__dict__["_calibrate"] = value

    @calibrate.deleter
    def calibrate(self):
        self.__dict__.pop("_calibrate", None)


_sys.modules[__name__].__class__ = _Face
