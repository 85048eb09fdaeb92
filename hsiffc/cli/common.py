"""What every command shares: the JSON writer and small formatting helpers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

DEFAULT_SAMPLES = Path("sample_cubes")


def write_json(path: Path, doc) -> None:
    """Write ``doc`` as indented JSON to ``path`` atomically."""
    from ..atomic import atomic_write_text

    atomic_write_text(Path(path), json.dumps(doc, indent=2, default=json_default) + "\n")


def json_default(obj):
    """JSON encoder fallback for numpy scalars and arrays and paths."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")
