"""The one place where hsiffc parses JSON and TOML text from files it reads.

Sidecars and pipeline descriptions (TOML), product manifests and TIFF descriptions (JSON) all go
through :func:`load_json` / :func:`load_toml`: a syntax error, a document nested so deeply that
the parser runs out of stack (``RecursionError``, e.g. 100 000 ``[`` in a row) or nested deeper
than :data:`MAX_NESTING` levels (which no hsiffc document needs, and which would make every later
walk over it recursive too) is one :class:`~hsiffc.errors.DataFormatError` naming the file and
what it is, never an internal error.
"""

from __future__ import annotations

import json
import tomllib

from ..errors import DataFormatError

__all__ = ["MAX_NESTING", "load_json", "load_toml", "nesting_depth"]

#: Deepest nesting of lists and tables/objects accepted in a document hsiffc reads.
MAX_NESTING = 64


def nesting_depth(doc, stop: int = MAX_NESTING + 1) -> int:
    """Levels of nested lists and dicts in ``doc`` (0 for a scalar), counted without recursion
    and without going deeper than ``stop``."""
    deepest, todo = 0, [(doc, 0)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, (list, tuple, dict)):
            depth += 1
            deepest = max(deepest, depth)
            if depth >= stop:
                return depth
            todo.extend((v, depth) for v in (item.values() if isinstance(item, dict) else item))
    return deepest


def _error(message: str, path, hint: str) -> DataFormatError:
    return DataFormatError(f"{message}; {hint}" if hint else message, path=path)


def _check_depth(doc, path, what: str, hint: str = ""):
    if nesting_depth(doc) > MAX_NESTING:
        raise _error(f"the {what} nests lists or tables more than {MAX_NESTING} levels deep "
                     "(no hsiffc document does): the file is damaged", path, hint)
    return doc


def load_json(text, *, path=None, what: str = "JSON document", hint: str = "", **kwargs):
    """Parse JSON ``text`` (str or bytes) from a file hsiffc reads.

    Parameters
    ----------
    text : str or bytes
    path : str or Path, optional
        The file (for the message).
    what : str
        What the text is ("pipeline manifest", "TIFF description"), for the message.
    hint : str
        How to make a good file, appended to the message after "; ".
    **kwargs
        Passed to :func:`json.loads` (e.g. ``parse_constant``).

    Returns
    -------
    object

    Raises
    ------
    DataFormatError
        Not valid JSON (or not UTF-8), or nested too deeply; one line naming the file.
    """
    try:
        doc = json.loads(text, **kwargs)
    except RecursionError:
        raise _error(f"the {what} is nested too deeply to parse (more than {MAX_NESTING} "
                     "levels); the file is damaged", path, hint) from None
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise _error(f"the {what} is not valid JSON ({exc})", path, hint) from exc
    return _check_depth(doc, path, what, hint)


def load_toml(text: str, *, path=None, what: str = "TOML file", hint: str = "") -> dict:
    """Parse TOML ``text`` from a file hsiffc reads (see :func:`load_json`).

    Raises
    ------
    DataFormatError
        Not valid TOML, or nested too deeply; one line naming the file.
    """
    try:
        doc = tomllib.loads(text)
    except RecursionError:
        raise _error(f"the {what} is nested too deeply to parse (more than {MAX_NESTING} "
                     "levels); the file is damaged", path, hint) from None
    except tomllib.TOMLDecodeError as exc:
        raise _error(f"the {what} is not valid TOML ({exc})", path, hint) from exc
    return _check_depth(doc, path, what, hint)
