"""The input side of a task: one file opened once with io's streaming reader.

:func:`open_input` is :func:`hsiffc.io.open_source` on one file (its header parsed once, the size
limits and the file structure checked before any pixel is decoded), after refusing outputs of
``hsiffc correct`` as inputs. The task uses only the reader's public interface: ``n_frames``,
``frame_shape``, ``dtype``, ``bit_depth``, ``mosaic``, per-frame ``exposure_ms``, ``kind``,
``illumination``, and iteration over ``(raw, meta)`` pairs, one frame decoded at a time.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataFormatError
from ..io import Overrides, open_source
from ..io.corrected import is_corrected_file

__all__ = ["open_input"]


def open_input(path, overrides=(), limits=None):
    """Open one input file for a batch task (nothing decoded yet).

    Parameters
    ----------
    path : path-like
    overrides : iterable of (name, value)
        Metadata for files that do not carry it (fields of :class:`hsiffc.io.Overrides`).
    limits : hsiffc.files.limits.ReadLimits, optional
        Size limits (default: io's documented defaults).

    Returns
    -------
    hsiffc.io.FrameSource

    Raises
    ------
    DataFormatError
        An output of ``hsiffc correct``, or anything :func:`hsiffc.io.open_source` refuses
        (unreadable, truncated, over the size limits, missing metadata).
    """
    path = Path(path)
    if is_corrected_file(path):
        raise DataFormatError("this is an output of hsiffc correct, not raw frames; give the raw "
                              "input", path=path)
    return open_source(path, limits=limits, overrides=Overrides(**dict(overrides)))
