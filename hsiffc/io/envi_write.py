"""Writing ENVI pairs (``NAME.hdr`` + ``NAME.img``) for users whose next tool is ENVI or SPy.

The header follows the ENVI header format (see :mod:`hsiffc.io.envi`): ``samples``,
``lines``, ``bands``, ``header offset = 0``, ``file type = ENVI Standard``, ``data type``,
``interleave``, ``byte order = 0`` (little-endian), ``wavelength units = Nanometers`` and
``wavelength = {...}`` when wavelengths are known, ``band names``, ``description`` and any extra
``key = value`` pairs given. Both files are written atomically, the data first, the header last
(a reader that finds the header finds complete data).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..files.atomic import atomic_path
from ..errors import DataFormatError
from .envi import ENVI_DTYPES

__all__ = ["write_envi", "corrected_to_envi", "corrected_envi_names", "corrected_envi_files",
           "written_from"]

_CODES = {np.dtype(v).newbyteorder("<"): k for k, v in ENVI_DTYPES.items()}


def _value(value) -> str:
    if isinstance(value, (list, tuple, np.ndarray)):
        items = [f"{v:.6g}" if isinstance(v, (float, np.floating)) else str(v) for v in value]
        return "{" + ", ".join(items) + "}"
    text = str(value)
    if any(c in text for c in "{}\n"):
        raise DataFormatError(f"ENVI header value {text[:40]!r} may not contain braces or line "
                              "breaks")
    return text


def write_envi(path, cube, *, wavelengths_nm=None, band_names=None, description: str = "",
               interleave: str = "bsq", extra: dict | None = None,
               overwrite: bool | None = None) -> tuple[Path, Path]:
    """Write an (H, W, bands) cube (or an (H, W) image) as an ENVI header + data pair.

    Parameters
    ----------
    path : str or Path
        ``NAME.hdr``, ``NAME.img`` or ``NAME``; the pair ``NAME.hdr`` + ``NAME.img`` is written.
    cube : (H, W) or (H, W, B) ndarray
        Samples kept as they are (uint8/16/32, int16/32/64, float32/64), little-endian.
    wavelengths_nm : sequence of B floats, optional
        Band centres, written as ``wavelength`` with ``wavelength units = Nanometers``.
    band_names : sequence of B str, optional
    description : str
    interleave : {"bsq", "bil", "bip"}
    extra : dict, optional
        More header entries (``key -> value``; lists are written in braces), e.g.
        ``{"exposure time": 20.0, "data ignore value": 0}``.
    overwrite : bool, optional
        Replace existing files (default: the command's write policy; refuse).

    Returns
    -------
    (header path, data path)
    """
    path = Path(path)
    base = path.with_suffix("") if path.suffix.lower() in (".hdr", ".img") else path
    header, data = base.with_name(base.name + ".hdr"), base.with_name(base.name + ".img")
    cube = np.asarray(cube)
    if cube.ndim == 2:
        cube = cube[:, :, None]
    if cube.ndim != 3:
        raise DataFormatError(f"an ENVI cube is (H, W) or (H, W, bands), got shape {cube.shape}",
                              path=header)
    dtype = cube.dtype.newbyteorder("<")
    if dtype not in _CODES:
        raise DataFormatError(f"samples of dtype {cube.dtype} cannot be written to ENVI; convert "
                              "to float32 or uint16", path=header)
    lines, samples, bands = cube.shape
    if interleave not in ("bsq", "bil", "bip"):
        raise ValueError(f"interleave must be bsq, bil or bip, got {interleave!r}")
    axes = {"bsq": (2, 0, 1), "bil": (0, 2, 1), "bip": (0, 1, 2)}[interleave]
    entries = {"description": _value(description or "written by hsiffc"),
               "samples": samples, "lines": lines, "bands": bands, "header offset": 0,
               "file type": "ENVI Standard", "data type": _CODES[dtype],
               "interleave": interleave, "byte order": 0}
    if wavelengths_nm is not None:
        wavelengths = [float(w) for w in wavelengths_nm]
        if len(wavelengths) != bands:
            raise DataFormatError(f"{len(wavelengths)} wavelengths for {bands} bands", path=header)
        entries["wavelength units"] = "Nanometers"
        entries["wavelength"] = _value(wavelengths)
    if band_names is not None:
        entries["band names"] = _value(list(band_names))
    for key, value in (extra or {}).items():
        entries[str(key).lower()] = _value(value)
    text = "ENVI\n" + "".join(f"{k} = {v if isinstance(v, str) else _value(v)}\n"
                              for k, v in entries.items())
    with atomic_path(data, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            np.ascontiguousarray(cube.transpose(axes), dtype=dtype).tofile(fh)
    with atomic_path(header, overwrite=overwrite) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return header, data


def corrected_envi_names(path, n_frames: int) -> list[Path]:
    """The ENVI names :func:`corrected_to_envi` gives the frames of the corrected file ``path``
    (without suffix): ``NAME`` for one frame, ``NAME_f0000``, ``NAME_f0001``, ... for several;
    each frame's files are ``NAME.hdr``, ``NAME.img``, ``NAME.dq.hdr`` and ``NAME.dq.img``.

    >>> [p.name for p in corrected_envi_names("a.corrected.tif", 2)]
    ['a.corrected_f0000', 'a.corrected_f0001']
    """
    base = Path(path).with_suffix("")
    if n_frames == 1:
        return [base]
    return [base.with_name(f"{base.name}_f{k:04d}") for k in range(n_frames)]


def corrected_envi_files(path, n_frames: int) -> list[Path]:
    """Every file :func:`corrected_to_envi` writes for ``path`` (headers and data, DQ
    included)."""
    return [name.with_name(name.name + tail) for name in corrected_envi_names(path, n_frames)
            for tail in (".hdr", ".img", ".dq.hdr", ".dq.img")]


def corrected_to_envi(path, *, overwrite: bool | None = None) -> list[Path]:
    """Write a corrected file (an output of ``hsiffc correct``) as ENVI cubes beside it.

    Each frame becomes ``NAME.hdr``/``NAME.img`` (``NAME_fKKKK`` when the file holds several
    frames; ``NAME`` is the corrected file's name without ``.tif``) with its DQ as
    ``NAME.dq.hdr``/``.img`` (and alpha as ``NAME.alpha.*`` when computed): a cube file as it
    is, a mosaic frame as one spectrum per tile; bands by wavelength, ascending
    (:func:`hsiffc.cubes.export.export_corrected`).

    Parameters
    ----------
    path : str or Path
        A complete corrected file.
    overwrite : bool, optional
        Replace existing ENVI files (default: the current write policy, which refuses).

    Returns
    -------
    list of Path
        The header files written (data, DQ and alpha for every frame).
    """
    from ..cubes.export import export_corrected

    return [p for p in export_corrected(path, "envi", overwrite=overwrite)
            if p.suffix == ".hdr"]


def written_from(envi_file, corrected) -> bool:
    """Whether the ENVI file ``envi_file`` (a header or its data file) is one
    :func:`corrected_to_envi` wrote from the corrected file ``corrected``: its header exists,
    says hsiffc wrote it, and names that file as its ``source``. A file that is not such a
    pair (the user's own, another program's) is never replaced without ``--overwrite``."""
    from .envi import parse_envi_header

    header = Path(envi_file).with_suffix(".hdr")
    try:
        head = parse_envi_header(header)
    except (OSError, ValueError, DataFormatError):
        return False

    def text(key):
        value = head.get(key, "")
        return (", ".join(value) if isinstance(value, list) else str(value)).strip()

    return text("description").startswith("hsiffc ") and text("source") == Path(corrected).name
