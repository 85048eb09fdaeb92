"""Warnings as data: every warning given while a batch corrects a file is recorded for that
file (its result, ``--json`` record and output provenance), one record per warning class.

A record is ``{"class": name, "message": first message, "figures": {...}, "count": n}``
(``figures``: the numbers a :class:`~hsiffc.errors.HsiffcWarning` carries). With
``fail_on_warning`` a class (or a base class, or ``"all"``) turns into a failure of the file:
its output is not written.

>>> from hsiffc.batch.warnrec import FileWarnings
>>> import warnings
>>> with FileWarnings() as caught:
...     warnings.warn("one", RuntimeWarning)
...     warnings.warn("two", RuntimeWarning)
>>> [(r["class"], r["message"], r["count"]) for r in caught.records()]
[('RuntimeWarning', 'one', 2)]
"""

from __future__ import annotations

import warnings

from ..data.params import did_you_mean
from ..errors import HsiffcError, HsiffcWarning, warning_scope
from ..files.jsonsafe import json_safe
from .plan import BatchError

__all__ = ["FileWarnings", "NonFiniteInputWarning", "NonFiniteOutputWarning",
           "WarningAsFailure", "add_record", "check_classes", "failing_record", "known_classes"]

#: categories about the code, not the data: shown as Python shows them, never recorded
NOT_DATA = (DeprecationWarning, PendingDeprecationWarning, FutureWarning, ImportWarning,
            ResourceWarning)


class NonFiniteInputWarning(HsiffcWarning):
    """NaN/inf pixels in a float input, flagged NONFINITE and set to 0 DN (``--nan flag``)."""


class NonFiniteOutputWarning(HsiffcWarning):
    """The correction gave NaN/inf values, flagged NONFINITE + DO_NOT_USE, written as 0 DN."""


class WarningAsFailure(HsiffcError):
    """A warning of a class given to ``fail_on_warning`` (``--fail-on-warning``)."""


def known_classes() -> dict:
    """``{name: class}`` of every hsiffc warning class (the names ``--fail-on-warning``
    takes, besides ``all``), with Python's RuntimeWarning and UserWarning."""
    from .. import io, reflectance, stages  # noqa: F401  (their warning classes register)

    out, todo = {}, [HsiffcWarning]
    while todo:
        cls = todo.pop()
        out[cls.__name__] = cls
        todo += cls.__subclasses__()
    return {"RuntimeWarning": RuntimeWarning, "UserWarning": UserWarning, **out}


def check_classes(names) -> tuple:
    """``names`` as a sorted tuple after checking each is ``all`` or a known class
    (:class:`~hsiffc.batch.plan.BatchError` with "did you mean" otherwise)."""
    known = known_classes()
    out = set()
    for name in names or ():
        name = str(name).strip()
        if name != "all" and name not in known:
            raise BatchError(f"--fail-on-warning {name}: not a warning class; "
                              f"{did_you_mean(name, [*known, 'all'])}valid: all, "
                              f"{', '.join(sorted(known))}")
        out.add(name)
    return tuple(sorted(out))


def _names(category) -> list:
    """The class's name and its bases' (so a base class matches its subclasses)."""
    return [c.__name__ for c in category.__mro__ if issubclass(c, Warning)]


def failing_record(records, fail_on) -> dict | None:
    """The first of ``records`` whose class (or a base of it, for hsiffc's classes) is in
    ``fail_on`` (``"all"``: any), else None."""
    if not fail_on:
        return None
    known = known_classes()
    for r in records:
        cls = known.get(r["class"])
        names = _names(cls) if cls is not None else [r["class"]]
        if "all" in fail_on or any(n in fail_on for n in names):
            return r
    return None


def add_record(records: list, record: dict) -> None:
    """Add ``record`` to ``records``, one per class: a repeat adds to the first's count."""
    for r in records:
        if r["class"] == record["class"]:
            r["count"] += record.get("count", 1)
            return
    records.append({"count": 1, **record})


class FileWarnings:
    """Catch the warnings given while one file is corrected (in its own
    :func:`~hsiffc.errors.warning_scope`, so that a stage's once-only warnings are given once
    per file). Warnings about code (deprecations) are shown as usual, not recorded."""

    def __init__(self):
        self._records: list = []
        self._failing: dict = {}
        self._other: list = []
        self._caught: list = []

    def __enter__(self):
        self._catch = warnings.catch_warnings(record=True)
        self._caught = self._catch.__enter__()
        warnings.simplefilter("always")
        self._scope = warning_scope()
        self._scope.__enter__()
        return self

    def __exit__(self, *exc):
        self._scope.__exit__(*exc)
        self._take()
        self._catch.__exit__(*exc)
        for w in self._other:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return False

    def _take(self) -> None:
        for w in self._caught:
            if issubclass(w.category, NOT_DATA):
                self._other.append(w)
                continue
            text = " ".join(str(w.message).split())
            add_record(self._records, {"class": w.category.__name__, "message": text,
                                       "figures": json_safe(getattr(w.message, "figures",
                                                                    None) or {})})
            for name in _names(w.category):
                self._failing.setdefault(name, w.category.__name__)
        del self._caught[:]

    def records(self) -> list:
        """The records so far, one per class, in the order first given."""
        self._take()
        return [dict(r) for r in self._records]

    def check(self, fail_on: tuple) -> None:
        """Raise :class:`WarningAsFailure` when a recorded class (or a base of one) is in
        ``fail_on`` (``"all"``: any)."""
        if not fail_on:
            return
        self.records()
        hit = next((self._failing[n] for n in self._failing if n in fail_on), None)
        if hit is None and "all" in fail_on and self._records:
            hit = self._records[0]["class"]
        if hit is not None:
            rec = next(r for r in self._records if r["class"] == hit)
            raise WarningAsFailure(f"{hit} (--fail-on-warning): {rec['message']}; no output "
                                   "written")
