"""Reading and writing frames, sweeps and cubes.

* :func:`open_source` opens files, folders or globs of any supported format as one
  :class:`FrameSource`: headers parsed once, size limits and file structure checked, metadata
  resolved (file, then sidecar, then options), frames decoded one at a time.
* :func:`read_sweep` = ``open_source(...).to_sweep()``: a :class:`~hsiffc.Sweep` in memory.
* :func:`write_sweep` writes a sweep as an hsiffc TIFF (atomically).
* :func:`read_sweep_tiff` and :func:`read_emva1288` read the two self-describing formats with
  their specific options; :func:`read_corrected` reads what ``hsiffc correct`` wrote and
  :func:`write_cube` writes a reconstructed cube.
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
from ._sidecar import find_sidecar
from .source import FrameMeta, FrameSource, expand_inputs, open_source
from .tiff import TIFF_SUFFIXES, read_sweep_tiff, write_sweep

__all__ = ["open_source", "FrameSource", "FrameMeta", "Overrides", "ReadLimits",
           "default_limits", "expand_inputs", "read_sweep", "read_sweep_tiff", "read_emva1288",
           "write_sweep", "read_corrected", "LayoutWarning", "MetadataConflictWarning",
           "TIFF_SUFFIXES", "IMAGE_SUFFIXES", "ACCEPTED", "find_sidecar", "write_cube"]


def write_cube(cube, path, **options):
    """Write a reconstructed cube (a :class:`~hsiffc.data.frame.Frame` or
    :class:`~hsiffc.cubes.Cube`) with its DQ and alpha as hsiffc TIFF, ENVI, OME-TIFF or
    netCDF, chosen by ``format=`` or the file name.

    Parameters
    ----------
    cube : Cube or Frame
        The cube, (H, W, B) values with their DQ bits and alpha.
    path : str or Path
        The main file; its suffix chooses the format when ``format`` is not given.
    **options
        ``format``, ``compression``, ``overwrite``, ``description``, ``extra``: see
        :func:`hsiffc.cubes.write_cube`.

    Returns
    -------
    list of Path
        The files written.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> from hsiffc.cubes import Cube
    >>> from hsiffc.io import write_cube
    >>> tmp = tempfile.TemporaryDirectory()
    >>> cube = Cube(np.ones((4, 6, 3), np.float32), np.zeros((4, 6, 3), np.uint32),
    ...             wavelengths_nm=(500.0, 600.0, 700.0))
    >>> [p.name for p in write_cube(cube, Path(tmp.name) / "cube.hdr")]   # ENVI, by the suffix
    ['cube.hdr', 'cube.img', 'cube.dq.hdr', 'cube.dq.img']
    >>> tmp.cleanup()
    """
    from .. import cubes

    return cubes.write_cube(cube, path, **options)


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
