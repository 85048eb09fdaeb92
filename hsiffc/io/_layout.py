"""What a format reader knows about one file from its header, before any pixel is decoded.

Every format module (:mod:`~hsiffc.io.tiff`, :mod:`~hsiffc.io._images`,
:mod:`~hsiffc.io.envi`, :mod:`~hsiffc.io._fits`, :mod:`~hsiffc.io.emva`) turns a path into a
:class:`FileLayout`; :func:`hsiffc.io.open_source` checks the layouts against the size limits,
resolves the metadata and streams the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["FileLayout", "FrameMeta", "FIELDS", "PER_FRAME_FIELDS"]

#: Metadata fields a frame source resolves (see :mod:`hsiffc.io._metadata`).
FIELDS = ("exposure_ms", "kind", "illumination", "photons", "step", "bit_depth", "mosaic",
          "bit_shift")
#: Fields that may differ from frame to frame (a scalar means "the same for every frame").
PER_FRAME_FIELDS = ("exposure_ms", "kind", "illumination", "photons", "step")


@dataclass
class FileLayout:
    """One input file as its header describes it.

    Attributes
    ----------
    path : Path
    format : str
        ``"hsiffc-tiff"``, ``"tiff"``, ``"png"``, ``"envi"``, ``"fits"`` or ``"emva1288"``.
    n_frames : int
    shape : tuple of int
        Stored shape of one frame: ``(H, W)``, or ``(H, W, C)`` for multi-channel images.
    dtype : numpy.dtype
        Stored sample type.
    read : callable
        ``read(k) -> ndarray`` decodes frame ``k`` (stored shape and dtype).
    close : callable
        Releases the open file handle, if any (``read`` reopens it when called again).
    fields : dict
        Metadata found in the file itself: field name -> scalar or per-frame sequence.
    origins : dict
        Field name -> where in the file it was found (e.g. ``"EXIF ExposureTime"``).
    meta : dict
        Anything else worth keeping (JSON-serialisable): header text fields, gain, ...
    strict : bool
        The file is self-describing (hsiffc TIFF, EMVA 1288): values it gives are not
        overridden by a sidecar or options.
    parallel : bool
        ``read`` may run on several threads at once (frames are decoded ahead).
    """

    path: Path
    format: str
    n_frames: int
    shape: tuple
    dtype: np.dtype
    read: Callable[[int], np.ndarray]
    close: Callable[[], None] = lambda: None
    fields: dict = field(default_factory=dict)
    origins: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    strict: bool = False
    parallel: bool = True

    def give(self, name: str, value, origin: str) -> None:
        """Record a metadata field found in the file (ignored when ``value`` is None).

        Parameters
        ----------
        name : str
            Field, e.g. ``"exposure_ms"`` (ms), ``"bit_depth"``, ``"kind"``.
        value : object or None
            Its value (scalar or one per frame).
        origin : str
            Where it was found, e.g. ``"file (EXIF ExposureTime)"``.
        """
        if value is not None:
            self.fields[name] = value
            self.origins[name] = origin


@dataclass(frozen=True)
class FrameMeta:
    """Metadata of one frame of a :class:`FrameSource`.

    Attributes
    ----------
    index : int
        Position in the source (acquisition order).
    exposure_ms : float
        Exposure time in milliseconds.
    kind : str
        "light" or "dark".
    illumination : str
    photons : float
        Mean photons per pixel (NaN when unknown).
    step : int or None
        Acquisition step, when the file states it.
    path : str
        File the frame comes from.
    page : int
        Frame index inside that file.

    Examples
    --------
    The metadata an hsiffc TIFF records per frame come back with each frame:

    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> from hsiffc import Sweep
    >>> from hsiffc.io import open_source, write_sweep
    >>> tmp = tempfile.TemporaryDirectory()
    >>> frames = Sweep(np.zeros((2, 4, 6), np.uint16), exposure_ms=[5.0, 5.0],
    ...                kind=["light", "dark"], bit_depth=12)
    >>> with open_source(write_sweep(Path(tmp.name) / "sweep.tif", frames)) as src:
    ...     metas = [meta for _, meta in src]
    >>> [(m.index, m.kind, m.exposure_ms, m.page) for m in metas]
    [(0, 'light', 5.0, 0), (1, 'dark', 5.0, 1)]
    >>> tmp.cleanup()
    """

    index: int
    exposure_ms: float
    kind: str
    illumination: str
    photons: float
    step: int | None
    path: str
    page: int
