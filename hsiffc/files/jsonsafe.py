"""Turning numpy-laden structures into plain JSON values (one helper for every writer)."""

from __future__ import annotations

import math
import os

import numpy as np


def json_safe(value, *, strict: bool = False, what: str = "the value"):
    """Numpy scalars/arrays -> Python, non-finite floats -> None, tuples -> lists, paths ->
    str, recursively. Anything else passes through unchanged, or with ``strict`` raises
    TypeError naming ``what`` (for documents that must be JSON as written)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v, strict=strict, what=what) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, strict=strict, what=what) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist(), strict=strict, what=what)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if strict and not (value is None or isinstance(value, (str, bool, int, float))):
        raise TypeError(f"{what} holds a {type(value).__name__} ({value!r}), which JSON cannot "
                        "store; keep it to str, numbers, lists and dicts")
    return value
