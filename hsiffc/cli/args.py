"""Argument checking for every command: typed options and one-line usage errors.

An option's value is checked when it is parsed (``type=``), so a bad value is reported before
any file is read: one line naming the option, what came, what is expected, and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import re
import sys

__all__ = ["OneLineParser", "count", "exposure_ms", "percent", "positive", "real", "seed"]


def _option_strings(parser) -> set:
    """Every long option of ``parser`` and of its sub-commands."""
    out = set()
    for action in parser._actions:
        out |= {s for s in action.option_strings if s.startswith("--")}
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                out |= _option_strings(child)
    return out


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (and exit status 2), like every other
    expected error of the command line.

    Parameters
    ----------
    *args, **kwargs
        As for :class:`argparse.ArgumentParser`.
    """

    def error(self, message):
        """Print ``message`` as one line with a pointer to ``--help`` and exit with status 2.

        Parameters
        ----------
        message : str
            argparse's description of the usage error.
        """
        text = " ".join(message.split()) + self._suggestion(message)
        self.exit(2, f"{self.prog}: error: {text} (see {self.prog} --help)\n")

    def _suggestion(self, message: str) -> str:
        """``"; did you mean 'x'?"`` for a misspelt choice or option (difflib), else ""."""
        from ..data.params import did_you_mean

        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            hint = did_you_mean(m.group(1), re.findall(r"'([^']*)'", m.group(2)))
        else:
            m = re.search(r"unrecognized arguments: (.*)", message)
            given = [w.split("=")[0] for w in (m.group(1).split() if m else [])
                     if w.startswith("--")]
            hint = did_you_mean(given[0], sorted(_option_strings(self))) if given else ""
        return f"; {hint.strip()}" if hint else ""

    def exit(self, status=0, message=None):
        """Write ``message`` (if any) to stderr and raise SystemExit(``status``).

        Parameters
        ----------
        status : int
            Exit status.
        message : str, optional
            Text to print first.
        """
        if message:
            sys.stderr.write(message)
        sys.exit(status)


def _number(text, kind, what):
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} (not a finite number)")
    return value


def _checked(kind, what: str, low=None, *, strict: bool = False, doc: str = ""):
    """An argparse ``type=`` for numbers of ``kind`` at least (``strict``: above) ``low``."""

    def parse(text: str):
        value = _number(text, kind, what)
        if low is not None and (value < low or (strict and value == low)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    parse.__doc__ = doc
    return parse


real = _checked(float, "a finite number", doc="Any finite number.")
positive = _checked(float, "a finite number > 0", 0.0, strict=True, doc="A finite number > 0.")
exposure_ms = _checked(float, "an exposure time in ms (a finite number >= 0)", 0.0,
                       doc="An exposure time in milliseconds: finite and >= 0.")
percent = _checked(float, "a percentage (a finite number > 0)", 0.0, strict=True,
                   doc="A threshold in percent: finite and > 0.")
count = _checked(int, "a whole number >= 1", 1, doc="A whole number >= 1.")
seed = _checked(int, "a whole number >= 0", 0, doc="A random seed: a whole number >= 0.")
index = _checked(int, "a row or column index (a whole number >= 0; rows and columns count from 0)",
                 0, doc="A pixel index: a whole number >= 0 (rows and columns count from 0).")
