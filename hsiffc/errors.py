"""Exceptions and warnings raised by hsiffc.

Every error names the file or argument at fault, what was expected, what was found and what to do.
"""

from __future__ import annotations

import contextvars
from contextlib import contextmanager


class HsiffcError(Exception):
    """Base class of every error hsiffc raises on purpose."""


class DataFormatError(HsiffcError, ValueError):
    """A file or array does not have the layout or metadata hsiffc needs.

    The message names the file (when there is one) and the problem.
    """

    def __init__(self, message: str, *, path: object | None = None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class ParameterError(HsiffcError, ValueError):
    """A parameter (of a stage, a function or a command) has a wrong type, range or name.

    The message is one line naming the parameter, the value given and what is valid.
    """


class UnknownStageError(ParameterError, KeyError):
    """No stage is registered (or loads) under the name asked for.

    A :class:`ParameterError` (so a ``ValueError``); also a ``KeyError`` for callers that
    looked a stage up as in a mapping. Its text is the message itself, not its repr.
    """

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class CalibrationMismatchError(HsiffcError, ValueError):
    """A calibration product does not fit the data it is applied to."""


class HsiffcWarning(UserWarning):
    """Base class of hsiffc warnings (a library never prints; it warns).

    ``figures``: the numbers behind the message (a dict of JSON values), recorded with the
    warning where a batch keeps it as data (``hsiffc correct``'s results and provenance).
    """

    def __init__(self, *args, figures: dict | None = None):
        super().__init__(*args)
        self.figures = dict(figures or {})


def band_figures(idx, values, fmt: str, limit: int = 6, labels=None) -> str:
    """The bands a warning is about, each with its figure: ``"band 3 12.5, band 7 9.1 (and 4
    more)"`` (``idx`` band indices, 0-based; ``values`` indexed by band index; ``fmt`` a format
    spec; at most ``limit`` named). ``labels``: each band's label by band index
    (:func:`hsiffc.data.mosaic.band_labels`: numbered by wavelength, with the mosaic position);
    without them bands are counted from 1 in band-index order.

    >>> band_figures([2, 6], [0.0, 0.0, 12.5, 0, 0, 0, 9.12], ".1f")
    'band 3 12.5, band 7 9.1'
    >>> band_figures([1], [0.0, 4.0], ".1f", labels=["band 2 (r0c0 700 nm)", "band 1 (600 nm)"])
    'band 1 (600 nm) 4.0'
    """
    name = (lambda i: labels[i]) if labels is not None else (lambda i: f"band {i + 1}")
    shown = ", ".join(f"{name(i)} {format(values[i], fmt)}" for i in idx[:limit])
    return shown + (f" (and {len(idx) - limit} more)" if len(idx) > limit else "")


_SCOPE: contextvars.ContextVar = contextvars.ContextVar("hsiffc_warning_scope", default=None)


@contextmanager
def warning_scope():
    """A new scope for warnings a stage gives once (:class:`WarnedOnce`): a batch opens one
    per file, so each file gets its own warnings (never only the first file of a campaign)."""
    token = _SCOPE.set(object())
    try:
        yield
    finally:
        _SCOPE.reset(token)


class WarnedOnce:
    """The warnings one holder has given in the current :func:`warning_scope`, made with the
    holder (a prepared stage, e.g. the reflectance stage's
    :class:`~hsiffc.stages.reflectance.PreparedReflectance`): a warning is given the first
    time its key is seen in the scope (outside any scope: once)."""

    __slots__ = ("_keys", "_scope")

    def __init__(self):
        self._scope, self._keys = _SCOPE.get(), set()

    def first(self, key) -> bool:
        """True the first time ``key`` is seen in the current scope."""
        scope = _SCOPE.get()
        if scope is not self._scope:
            self._scope, self._keys = scope, set()
        if key in self._keys:
            return False
        self._keys.add(key)
        return True


class CalibrationDomainWarning(HsiffcWarning):
    """Pixels of a calibration hold leakage parameters outside the model (b <= 0): they are
    flagged DO_NOT_USE and their b set to NaN, as a NaN is, instead of failing every frame."""


class MissingMosaicWarning(HsiffcWarning):
    """A frame gives no mosaic layout but its calibration has one: corrected pixel by pixel,
    per-band figures over the whole frame as one band."""
