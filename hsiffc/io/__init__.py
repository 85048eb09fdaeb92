"""Reading and writing frames, sweeps and cubes.

* :func:`open_source` opens files, folders or globs of any supported format as one
  :class:`FrameSource`: headers parsed once, size limits and file structure checked, metadata
  resolved (file, then sidecar, then options), frames decoded one at a time.
* :func:`read_sweep` = ``open_source(...).to_sweep()``: a :class:`~hsiffc.Sweep` in memory.
* :func:`write_sweep` writes a sweep as an hsiffc TIFF (atomically).
* :func:`read_sweep_tiff` and :func:`read_emva1288` read the two self-describing formats with
  their specific options; :func:`read_corrected` reads what ``hsiffc correct`` wrote
  (:func:`hsiffc.cubes.write_cube` writes a reconstructed cube).
* ``TIFF_SUFFIXES``, ``IMAGE_SUFFIXES`` (the file suffixes a folder is searched for) and
  ``ACCEPTED`` (the inputs, in words, as error messages list them).

The public modules behind this face are one per format or reader: :mod:`hsiffc.io.source` (the
frame source), :mod:`hsiffc.io.tiff`, :mod:`hsiffc.io.corrected`, :mod:`hsiffc.io.envi` and
:mod:`hsiffc.io.emva`; the modules whose names start with an underscore are plumbing whose
API may change without notice.

Formats, the metadata order, the sidecar format and the limits are documented in
``docs/formats-and-metadata.md``.

Examples
--------
>>> import tempfile, numpy as np
>>> from pathlib import Path
>>> from hsiffc import Sweep
>>> from hsiffc.io import read_sweep, write_sweep
>>> tmp = tempfile.TemporaryDirectory()
>>> sweep = Sweep(np.zeros((3, 4, 6), np.uint16), exposure_ms=[1.0, 2.0, 4.0], kind="light",
...               bit_depth=12)
>>> path = write_sweep(Path(tmp.name) / "sweep.tif", sweep)
>>> read_sweep(path).exposure_ms.tolist()       # any supported input: file, folder or glob
[1.0, 2.0, 4.0]
>>> tmp.cleanup()
"""

from __future__ import annotations

from .corrected import read_corrected
from .emva import read_emva1288
from ..files.limits import ReadLimits, default_limits
from ._metadata import MetadataConflictWarning, Overrides
from ._quirks import LayoutWarning
from ._readers import ACCEPTED, IMAGE_SUFFIXES
from .source import FrameMeta, FrameSource, expand_inputs, open_source
from .tiff import TIFF_SUFFIXES, read_sweep_tiff, write_sweep

__all__ = ["open_source", "FrameSource", "FrameMeta", "Overrides", "ReadLimits",
           "default_limits", "expand_inputs", "read_sweep", "read_sweep_tiff", "read_emva1288",
           "write_sweep", "read_corrected", "LayoutWarning", "MetadataConflictWarning",
           "TIFF_SUFFIXES", "IMAGE_SUFFIXES", "ACCEPTED"]


def __getattr__(name):
    if name == "write_cube":  # moved: io sits beside cubes, which reads and writes through it
        raise AttributeError("hsiffc.io.write_cube moved to hsiffc.cubes.write_cube (hsiffc "
                             "0.2): import it from there")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def read_sweep(path, **options):
    """Read frames and their metadata from ``path`` into a :class:`~hsiffc.Sweep`.

    Parameters
    ----------
    path : str, Path or sequence of them
        Any input :func:`open_source` accepts: an hsiffc or plain TIFF, PNG, ENVI ``.hdr``,
        FITS, an EMVA 1288 descriptor (``.txt``; exposure times in ns, the EMVA 1288 convention;
        call :func:`read_emva1288` to choose another unit), a folder or a glob.
    **options
        Metadata for files that lack it (``exposure_ms``, ``bit_depth``, ``kind``, ``mosaic``,
        ``illumination``, ``bit_shift``, ``sidecar``) and ``limits``.

    Returns
    -------
    Sweep
        ``data`` (N, H, W) in the file's dtype (DN, never rescaled), ``exposure_ms`` (N,) in
        ms, per-frame ``kind``, ``illumination``, ``photons`` and ``step``, the bit depth, the
        mosaic (or None) and where each value came from (``meta["metadata_origins"]``).

    Raises
    ------
    DataFormatError
        The path does not exist or is none of the accepted inputs (the message lists them), or
        the file itself is invalid, or metadata are missing.

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "frames.tif"      # a plain TIFF: 3 frames of 4 x 6 px
    >>> tifffile.imwrite(path, np.full((3, 4, 6), 100, np.uint16), photometric="minisblack")
    >>> sweep = read_sweep(path, exposure_ms=10.0, bit_depth=12)   # metadata it lacks
    >>> sweep.data.shape, sweep.data.dtype.name, sweep.exposure_ms.tolist(), sweep.kind.tolist()
    ((3, 4, 6), 'uint16', [10.0, 10.0, 10.0], ['light', 'light', 'light'])
    """
    with open_source(path, **options) as src:
        return src.to_sweep()
