"""An hsiffc TIFF's frames as cubes of another format: :func:`export_corrected`.

``hsiffc correct --format envi|ome|netcdf`` writes its cubes straight from the correction
(:mod:`hsiffc.cubes.stream`); this module turns a corrected file that is already on disk
(``NAME.corrected.tif``) into the same cubes, one frame at a time: ``NAME.corrected`` + the
format's suffix for a file of one frame, ``NAME.corrected_f0000`` ... for several
(:func:`export_names`). A corrected file of cubes is written as it is; a corrected file of
mosaic frames becomes one spectrum per mosaic tile (:func:`hsiffc.reconstruct.tile_cube`).
:func:`cube_from_corrected` makes the :class:`Cube` of one frame for both.
"""

from __future__ import annotations

import glob
from pathlib import Path

from ..errors import DataFormatError
from .product import Cube
from .writers import FORMATS, cube_files, write_cube

__all__ = ["cube_from_corrected", "export_corrected", "export_files", "export_names",
           "written_by_hsiffc", "written_from"]


def export_names(path, n_frames: int) -> list[Path]:
    """The base name of every frame's export of the corrected file ``path`` (no suffix).

    >>> [p.name for p in export_names("a.corrected.tif", 2)]
    ['a.corrected_f0000', 'a.corrected_f0001']
    """
    base = Path(path).with_suffix("")
    if n_frames == 1:
        return [base]
    return [base.with_name(f"{base.name}_f{k:04d}") for k in range(n_frames)]


def export_files(path, fmt: str, prov: dict) -> list[Path]:
    """Every file :func:`export_corrected` writes for the corrected file ``path`` whose
    provenance is ``prov``."""
    alpha = bool(prov.get("alpha_computed"))
    return [f for name in export_names(path, int(prov["n_frames"]))
            for f in cube_files(name.with_name(name.name + FORMATS[fmt]), fmt, alpha=alpha)]


def cube_from_corrected(prov: dict, k: int, data, dq, alpha, *, source: str = "") -> Cube:
    """Frame ``k`` of a corrected file as a :class:`Cube`: the stored cube with the bands its
    provenance describes, or, for a mosaic frame, one spectrum per tile."""
    from ..data.mosaic import Mosaic
    from ..reconstruct import reconstruct_alpha, tile_cube
    from ..data.mosaic import band_positions

    computed = bool(prov.get("alpha_computed"))
    exposure = (prov.get("exposure") or [None] * (k + 1))[k]
    attrs = {"exposure_ms": exposure, "exposure_unit": "ms",
             "kind": (prov.get("kind") or [None] * (k + 1))[k],
             "illumination": (prov.get("illumination") or [None] * (k + 1))[k],
             "source": source, "frame": k,
             "input": (prov.get("input") or {}).get("path"),
             "pipeline_fingerprint": (prov.get("pipeline") or {}).get("fingerprint")}
    attrs = {key: v for key, v in attrs.items() if v is not None}
    history = [{"name": s.get("name"), "stage": s.get("stage"), "params": s.get("params")}
               for s in ((prov.get("pipeline") or {}).get("steps") or [])]
    if data.ndim == 3:
        info = prov.get("cube") or {}
        attrs["reconstruction"] = info.get("reconstruction")
        return Cube(data, dq, alpha if computed else None, info.get("wavelengths_nm"),
                    info.get("fwhm_nm"), info.get("band_positions"), info.get("band_index"),
                    unit=info.get("unit", "DN"),
                    history=history, attrs=attrs)
    if prov.get("mosaic") is None:
        return Cube(data[:, :, None], dq[:, :, None],
                    alpha[:, :, None] if computed else None, history=history, attrs=attrs)
    mosaic = Mosaic.from_dict(prov["mosaic"])
    cube, cube_dq = tile_cube(data, mosaic, dq=dq)
    cube_alpha = reconstruct_alpha(alpha, mosaic, resolution="tile") if computed else None
    attrs["reconstruction"] = {"method": None, "resolution": "tile", "correction": None}
    return Cube(cube, cube_dq, cube_alpha, mosaic.wavelengths_nm, mosaic.fwhm_nm,
                band_positions(mosaic), history=history, attrs=attrs)


def export_corrected(path, fmt: str, *, compression: str | None = None,
                     overwrite: bool | None = None,
                     remove_leftovers: bool = False) -> list[Path]:
    """Write every frame of the corrected file ``path`` as a cube in format ``fmt``.

    Parameters
    ----------
    path : str or Path
        A complete output of ``hsiffc correct``.
    fmt : {"envi", "ome", "netcdf", "tiff"}
    compression : str, optional
        As :func:`~hsiffc.cubes.write_cube` takes it.
    overwrite : bool, optional
        Replace existing files (default: the current write policy, which refuses).
    remove_leftovers : bool
        First remove the temporary files (``.NAME.*.part``) an interrupted export of these
        cubes left; only for a caller that holds the output folder's lock (another run's
        temporary files must not be removed).

    Returns
    -------
    list of Path
        Every file written.
    """
    from ..files.atomic import PART_SUFFIX
    from ..io.corrected import iter_corrected, read_provenance

    path = Path(path)
    if fmt not in FORMATS:
        raise DataFormatError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}",
                              path=path)
    prov = read_provenance(path)
    names = export_names(path, int(prov["n_frames"]))
    if remove_leftovers:
        for file in export_files(path, fmt, prov):
            for stale in file.parent.glob(f".{glob.escape(file.name)}.*{PART_SUFFIX}"):
                stale.unlink(missing_ok=True)
    written: list[Path] = []
    for k, data, dq, alpha in iter_corrected(path):
        cube = cube_from_corrected(prov, k, data, dq, alpha, source=path.name)
        target = names[k].with_name(names[k].name + FORMATS[fmt])
        written += write_cube(cube, target, format=fmt, compression=compression,
                              overwrite=overwrite,
                              description=f"hsiffc corrected frame {k} of {path.name}",
                              extra={"source": path.name} if fmt == "envi" else None)
        del cube
    return written


def written_from(file, corrected) -> bool:
    """Whether ``file`` is an export :func:`export_corrected` wrote from the corrected file
    ``corrected`` (it names that file as its source). Files that are not (the user's own,
    another program's) are never replaced without ``--overwrite``."""
    from ..io.envi import parse_envi_header

    file, name = Path(file), Path(corrected).name
    low = file.name.lower()
    try:
        if low.endswith((".hdr", ".img")):
            head = parse_envi_header(file.with_suffix(".hdr"))

            def text(key):
                value = head.get(key, "")
                return (", ".join(value) if isinstance(value, list) else str(value)).strip()

            return text("description").startswith("hsiffc ") and text("source") == name
        if low.endswith(".tif"):
            import tifffile

            with tifffile.TiffFile(file) as tf:
                desc = tf.pages[0].description or ""
            return f"&quot;source&quot;: &quot;{name}&quot;" in desc or \
                f'"source": "{name}"' in desc
        if low.endswith(".nc"):
            import h5py

            with h5py.File(file, "r") as h5:
                source = h5.attrs.get("source")
            source = source.decode() if isinstance(source, bytes) else source
            return str(source) == name
    except Exception:  # unreadable or not ours
        return False
    return False


def written_by_hsiffc(file) -> bool:
    """Whether ``file`` is a cube file hsiffc wrote: an ENVI header (or the data file of one)
    with hsiffc's keys, an OME-TIFF whose Description is hsiffc's cube document, a netCDF file
    with hsiffc's attributes. The batch replaces such a file at one of its product's names
    (an earlier or interrupted run's); any other file only with ``--overwrite``."""
    file = Path(file)
    low = file.name.lower()
    try:
        if low.endswith((".hdr", ".img")):
            from ..io.envi import parse_envi_header

            head = parse_envi_header(file.with_suffix(".hdr"))
            return "hsiffc version" in head or "dq bit names" in head or \
                str(head.get("description", "")).startswith("hsiffc")
        if low.endswith((".tif", ".tiff")):
            import tifffile

            with tifffile.TiffFile(file) as tf:
                return "hsiffc-cube" in (tf.pages[0].description or "")
        if low.endswith(".nc"):
            import h5py

            with h5py.File(file, "r") as h5:
                return "json_attrs" in h5.attrs and "dq_bits" in h5.attrs
    except Exception:  # unreadable or not ours
        return False
    return False
