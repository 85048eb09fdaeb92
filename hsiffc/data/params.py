"""Parameter validation in one place: declared types and ranges, and method names.

A stage declares its parameters once, as a mapping from name to :class:`Param`; the pipeline
checks them when it is built, fitted or loaded (:func:`check_params`), so a wrong value fails
at once with one line naming the parameter, the value and what is valid - not later, in every
file of a batch. Functions that pick an algorithm by name use :func:`validate_method`.

Examples
--------
>>> check_params("alpha_mask", {"threshold_percent": Param("number", low=0, low_open=True)},
...              {"threshold_percent": "twelve"})
Traceback (most recent call last):
...
hsiffc.errors.ParameterError: alpha_mask: threshold_percent='twelve' is not valid; expected a number > 0
>>> validate_method("ppid", {"nearest": 1, "ppid": 2}, "demosaicking method")
2
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import ParameterError

KINDS = ("number", "integer", "choice", "bool", "string", "path", "calibration")


class LiveChoices(Sequence):
    """The names of a method registry, read each time they are looked at, so that a method
    registered after a stage or a command-line parser was defined is one of its choices.

    Parameters
    ----------
    source : mapping or callable
        A registry (its keys are the names) or a function returning the names.

    Examples
    --------
    >>> registry = {"a": 1}
    >>> names = LiveChoices(registry)
    >>> registry["b"] = 2
    >>> "b" in names, names == ("a", "b"), list(names)
    (True, True, ['a', 'b'])
    """

    def __init__(self, source: Mapping | Callable[[], Iterable[str]]):
        self._source = source

    def _names(self) -> tuple:
        return tuple(self._source if isinstance(self._source, Mapping) else self._source())

    def __getitem__(self, index):
        return self._names()[index]

    def __len__(self) -> int:
        return len(self._names())

    def __contains__(self, value) -> bool:
        return value in self._names()

    def __iter__(self):
        return iter(self._names())

    def __eq__(self, other) -> bool:
        return self._names() == (other._names() if isinstance(other, LiveChoices) else other)

    def __hash__(self) -> int:
        return hash(self._names())

    def __repr__(self) -> str:
        return repr(self._names())


@dataclass(frozen=True)
class Param:
    """What one parameter accepts.

    Parameters
    ----------
    kind : str
        ``"number"`` (finite int or float, not bool), ``"integer"``, ``"choice"`` (one of
        ``choices``), ``"bool"``, ``"string"``, ``"path"`` (str or path-like) or
        ``"calibration"`` (a :class:`hsiffc.calibrate.Calibration` or the path of one).
    low, high : float, optional
        Range of a number or integer (inclusive unless ``low_open`` / ``high_open``).
    choices : tuple
        Valid values of a ``"choice"`` parameter (any iterable, kept as a tuple; a method
        registry or a :class:`LiveChoices` gives its names as they are when a value is
        checked).
    optional : bool
        None is accepted.
    unit : str
        Appended to the description (e.g. ``"ms"``, ``"percent"``).
    """

    kind: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple | LiveChoices = ()
    optional: bool = False
    unit: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Param kind must be one of {KINDS}, got {self.kind!r}")
        if isinstance(self.choices, Mapping):  # a registry: its names, live
            object.__setattr__(self, "choices", LiveChoices(self.choices))
        elif not isinstance(self.choices, (tuple, LiveChoices)):
            object.__setattr__(self, "choices", tuple(self.choices))

    def describe(self) -> str:
        """What is valid, in words (used in the error message)."""
        if self.kind == "choice":
            text = "one of " + ", ".join(repr(c) for c in self.choices)
        elif self.kind == "calibration":
            text = "a Calibration or the path of a calibration file (.npz)"
        else:
            text = {"number": "a number", "integer": "an integer", "bool": "true or false",
                    "string": "a string", "path": "a file path"}[self.kind]
            bounds = []
            if self.low is not None:
                bounds.append(f"{'>' if self.low_open else '>='} {self.low:g}")
            if self.high is not None:
                bounds.append(f"{'<' if self.high_open else '<='} {self.high:g}")
            if bounds:
                text += " " + " and ".join(bounds)
        if self.unit:
            text += f" ({self.unit})"
        return text + (" or None" if self.optional else "")

    def accepts(self, value) -> bool:
        """True when ``value`` is valid for this parameter."""
        if value is None:
            return self.optional or (self.kind == "choice" and None in self.choices)
        if self.kind == "choice":
            return any(value == c and type(value) is type(c) for c in self.choices)
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "string":
            return isinstance(value, str)
        if self.kind == "path":
            return isinstance(value, (str, Path))
        if self.kind == "calibration":
            # a path, or a calibration object (hsiffc.calibrate.Calibration, recognised by its
            # compatibility check: the data model does not import the layer above it)
            return isinstance(value, (str, Path)) or callable(getattr(value,
                                                                      "check_compatible", None))
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if self.kind == "integer" and not float(value).is_integer():
            return False
        v = float(value)
        if not math.isfinite(v):
            return False
        if self.low is not None and (v <= self.low if self.low_open else v < self.low):
            return False
        return not (self.high is not None and (v >= self.high if self.high_open else v > self.high))


def check_params(owner: str, spec: Mapping[str, Param], values: Mapping) -> None:
    """Raise :class:`ParameterError` for the first value in ``values`` that ``spec`` refuses.

    Parameters
    ----------
    owner : str
        Who the parameters belong to (a stage name), for the message.
    spec : mapping of str to Param
        Declared parameters; names not in ``spec`` are not checked.
    values : mapping of str to object
        Current parameter values.
    """
    for name, param in spec.items():
        if name in values and not param.accepts(values[name]):
            raise ParameterError(f"{owner}: {name}={values[name]!r} is not valid; expected "
                                 f"{param.describe()}")


def short_repr(value, limit: int = 60) -> str:
    """A parameter value as a repr fit for one line: arrays by shape and dtype, long texts and
    containers cut, objects with a short repr (a Calibration) as that.

    Examples
    --------
    >>> import numpy as np
    >>> short_repr(np.zeros((96, 128), np.float32))
    'array((96, 128) float32)'
    >>> short_repr(12)
    '12'
    """
    import numpy as np

    if isinstance(value, np.ndarray):
        return f"array({value.shape} {value.dtype})"
    text = repr(value)
    if len(text) > limit and isinstance(getattr(value, "identity", None), str):
        return f"<{type(value).__name__} {value.identity}>"  # e.g. a Calibration
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def did_you_mean(name, valid) -> str:
    """``"did you mean 'x'? "`` when ``name`` is close to one of ``valid`` (difflib), else "".

    Parameters
    ----------
    name : object
        The name given (anything: only a string gets a suggestion).
    valid : iterable of str
        The valid names.

    Returns
    -------
    str
        The suggestion, ending with a space, or an empty string.

    Examples
    --------
    >>> did_you_mean("threshold_percnt", ["calibration", "threshold_percent"])
    "did you mean 'threshold_percent'? "
    >>> did_you_mean("x", ["calibration"])
    ''
    """
    import difflib

    if not isinstance(name, str):
        return ""
    close = difflib.get_close_matches(name, [str(v) for v in valid], n=1, cutoff=0.6)
    return f"did you mean {close[0]!r}? " if close else ""


def unknown_parameters(owner: str, given, valid) -> None:
    """Raise :class:`ParameterError` for the first of ``given`` that is not in ``valid``: one
    line naming the owner, the parameter, the closest valid name and every valid one.

    Parameters
    ----------
    owner : str
        Whose parameters (e.g. ``"stage 'alpha_mask'"``), for the message.
    given : iterable of str
        The parameter names passed.
    valid : iterable of str
        The names the owner takes.

    Examples
    --------
    >>> unknown_parameters("stage 'alpha_mask'", ["threshold_percnt"],
    ...                    ["calibration", "threshold_percent"])
    Traceback (most recent call last):
    ...
    hsiffc.errors.ParameterError: stage 'alpha_mask' has no parameter 'threshold_percnt'; did you mean 'threshold_percent'? valid: calibration, threshold_percent
    """
    valid = list(valid)
    for name in given:
        if name not in valid:
            raise ParameterError(f"{owner} has no parameter {name!r}; "
                                 f"{did_you_mean(name, valid)}valid: "
                                 f"{', '.join(valid) or '(none)'}")


def validate_method(name, registry, what: str):
    """Look up ``name`` in a method registry; an unknown name lists the valid ones.

    Parameters
    ----------
    name : str
        The method asked for.
    registry : mapping or sequence of str
        Valid names (a mapping from name to implementation, or a sequence of names).
    what : str
        What the name selects, for the message (e.g. ``"demosaicking method"``).

    Returns
    -------
    object
        ``registry[name]`` for a mapping, else ``name``.
    """
    names = list(registry)
    if not isinstance(name, str) or name not in names:
        raise ParameterError(f"unknown {what} {name!r}; {did_you_mean(name, names)}valid: "
                             f"{', '.join(map(str, names))}")
    return registry[name] if isinstance(registry, Mapping) else name
