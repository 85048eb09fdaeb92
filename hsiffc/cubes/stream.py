"""The product files of ``hsiffc correct``: one input's output in the formats asked for.

``--format`` chooses the files (:data:`PRODUCT_FORMATS`, one or several): ``tiff`` the hsiffc
TIFF (``NAME.corrected.tif``, every frame with its provenance), ``envi``, ``ome`` and
``netcdf`` a cube per frame (``NAME.corrected.hdr`` for a file of one frame,
``NAME.corrected_f0000.hdr`` ... for several; a mosaic frame becomes one spectrum per tile).
The batch streams every frame into each format as it is corrected (:class:`ProductWriter`);
nothing is read back, and a file that was not asked for is not written.

Every format holds the whole provenance, so that each one alone resumes a batch: the cube
files carry it in ``attrs["provenance"]`` (ENVI ``hsiffc attrs``, the OME-TIFF's
Description JSON, netCDF's ``provenance`` attribute), each frame's file with that frame's
figures (exposure, statistics) and the same ``"run"``, an id drawn when the input is
corrected. The provenance is final only once the last frame is corrected (the input's
sha256, the statistics, the warnings): the files are written with a placeholder in its place,
then finished in place and renamed as one set (:class:`hsiffc.files.atomic.FileSet`). The
ENVI headers also name their data file's size and modification time (``hsiffc data
stamp``), so that a data file of another run beside them is seen.

:func:`read_product` gives a format's provenance back only when every file of the product is
there and says the same run; otherwise it says what is missing or mixed, and the batch redoes
the product.
"""

from __future__ import annotations

import json
import os
import uuid
from dataclasses import replace
from pathlib import Path

from ..errors import DataFormatError
from ..files.jsonsafe import json_safe
from .export import cube_from_corrected, export_names
from .writers import FORMATS, cube_files, write_cube

__all__ = ["DEFAULT_COMPRESSION", "PRODUCT_FORMATS", "ProductWriter", "compression_for",
           "frame_provenance",
           "product_files", "product_present", "read_product"]

#: the formats ``hsiffc correct --format`` writes (one or several, comma-separated)
PRODUCT_FORMATS = ("tiff", "envi", "ome", "netcdf")
#: what each format is compressed with by default (``compression="auto"``): the DQ plane, which
#: is mostly zeros and shrinks tenfold or more at little cost, with a lossless codec the readers
#: of that format have: zstd in the hsiffc TIFF (read by hsiffc and tifffile with imagecodecs,
#: both installed with hsiffc), deflate (zlib) in the OME-TIFF (Bio-Formats/Fiji, napari,
#: QuPath, GDAL, libtiff) and netCDF-4 (every netCDF library); ENVI has no compression. The
#: float data and alpha planes are left uncompressed: corrected values are noisy, a codec gains
#: ~20 % of their bytes for two to five times the write time (``benchmarks/bench_outputs.py``);
#: ``--compression zstd|zlib|lzma`` compresses every plane
DEFAULT_COMPRESSION = {"tiff": {"dq": "zstd"}, "envi": None, "ome": {"dq": "zlib"},
                       "netcdf": {"dq": "zlib"}}
#: per-frame lists of a batch's provenance (sliced to the frame in each frame's cube)
_PER_FRAME = ("exposure", "kind", "illumination")
_PENDING = "hsiffc-provenance-pending"


def product_files(out, fmt: str, n_frames: int, alpha: bool) -> list[Path]:
    """Every file of the product of ``out`` (the output name, ``NAME.corrected.tif``) in
    format ``fmt`` for ``n_frames`` frames, with alpha planes or not.

    >>> [p.name for p in product_files("a.corrected.tif", "envi", 1, False)]
    ['a.corrected.hdr', 'a.corrected.img', 'a.corrected.dq.hdr', 'a.corrected.dq.img']
    >>> [p.name for p in product_files("a.corrected.tif", "ome", 2, True)]
    ['a.corrected_f0000.ome.tif', 'a.corrected_f0001.ome.tif']
    """
    if fmt == "tiff":
        return [Path(out)]
    return [f for name in export_names(out, n_frames)
            for f in cube_files(name.with_name(name.name + FORMATS[fmt]), fmt, alpha=alpha)]


def _main_files(out, fmt: str, n_frames: int) -> list[Path]:
    return [name.with_name(name.name + FORMATS[fmt]) for name in export_names(out, n_frames)]


def product_present(out, fmt: str) -> list[Path]:
    """The files at the names of the first frame's cube of ``out`` in ``fmt`` (any number of
    frames), or ``[out]`` for the hsiffc TIFF: what the batch finds of an earlier run."""
    if fmt == "tiff":
        return [Path(out)] if os.path.lexists(out) else []
    names = {f for n in (1, 2) for f in product_files(out, fmt, n, True)[:6]}
    return sorted(f for f in names if os.path.lexists(f))


def frame_provenance(prov: dict, k: int) -> dict:
    """The provenance of a batch's input as frame ``k``'s cube stores it: every per-frame
    list (exposure, kind, illumination, the statistics) cut to that frame, and ``"frame"``."""
    doc = {key: v for key, v in prov.items() if key not in _PER_FRAME}
    for key in _PER_FRAME:
        values = prov.get(key) or ()
        doc[key] = [values[k]] if k < len(values) else []
    if isinstance(prov.get("frames"), dict):
        doc["frames"] = {key: [v[k]] if isinstance(v, list) and k < len(v) else v
                         for key, v in prov["frames"].items()}
    doc["frame"] = k
    return doc


class ProductWriter:
    """Writes an input's corrected frames in the product formats as they come, into one
    :class:`~hsiffc.files.atomic.FileSet` (nothing appears under a final name before the
    set is committed).

    Parameters
    ----------
    out : Path
        The output name (``NAME.corrected.tif``; the cubes are named from it).
    formats : tuple of str
        Cube formats among :data:`PRODUCT_FORMATS` (the hsiffc TIFF is written by
        :class:`~hsiffc.io.corrected.CorrectedWriter`; pass it as ``tiff_writer``).
    prov : dict
        The provenance known before the first frame (with ``"cube"``: what
        :func:`hsiffc.batch.task.cube_description` says of a cube's bands, None for mosaic
        frames).
    shape : tuple
        The shape of every frame's data (H, W) or (H, W, B).
    n_frames : int
    fileset : FileSet
    compression : str, optional
        As :func:`compression_for` takes it (``"auto"``: each format's default).
    alpha : bool
        Write the alpha planes of the cubes.
    tiff_writer : CorrectedWriter, optional
        The hsiffc TIFF's writer, fed the same frames.
    """

    def __init__(self, out, formats, prov: dict, *, shape, n_frames: int, fileset,
                 compression=None, alpha: bool = False, tiff_writer=None):
        self.out = Path(out)
        self.shape = tuple(shape)
        self.cube = prov.get("cube")
        self.formats = tuple(f for f in formats if f != "tiff")
        self.n_frames = int(n_frames)
        self.prov = {**prov, "n_frames": self.n_frames}
        self.fileset = fileset
        self.compression = compression
        self.alpha = bool(alpha)
        self.tiff = tiff_writer
        self.run = uuid.uuid4().hex
        self.written = 0
        self._token = {"pending": f"{_PENDING}-{self.run}"}

    def write(self, data, dq, alpha=None) -> None:
        """Write the next frame to every format."""
        if self.tiff is not None:
            self.tiff.write(data, dq, alpha)
        k = self.written
        if self.formats:
            keep = alpha if self.alpha else None
            prov = {**self.prov, "alpha_computed": self.alpha}
            cube = cube_from_corrected(prov, k, data, dq, keep,
                                       source=Path(self.prov["input"]["path"]).name)
            cube = replace(cube, attrs={**cube.attrs, "provenance": self._token})
            for fmt, target in zip(self.formats, self._targets(k)):
                write_cube(cube, target, format=fmt, overwrite=True,
                           compression=compression_for(fmt, self.compression),
                           description=f"hsiffc correct: frame {k} of {cube.attrs['source']}",
                           fileset=self.fileset)
        self.written += 1

    def _targets(self, k: int) -> list[Path]:
        return [_main_files(self.out, fmt, self.n_frames)[k] for fmt in self.formats]

    def sync(self) -> None:
        """Start the disk's write-back of the hsiffc TIFF (see its writer)."""
        if self.tiff is not None:
            self.tiff.sync()

    def finish(self, document: dict) -> dict:
        """Put the final provenance (``document``: the fields known at the end) in every
        file: the hsiffc TIFF's description, each cube's placeholder (with the run id and,
        for ENVI, each data file's stamp). The files stay in the set for its commit."""
        final = {**self.prov, **document, "run": self.run}
        if self.tiff is not None:
            self.tiff.finish(document | {"run": self.run})
        for k in range(self.n_frames if self.formats else 0):
            text = json.dumps(json_safe(frame_provenance(final, k)), allow_nan=False)
            for fmt, target in zip(self.formats, self._targets(k)):
                _finish_cube(fmt, target, self.fileset, json.dumps(self._token), text,
                             self.run, self.alpha)
        return final

    def close(self) -> None:
        """Close the hsiffc TIFF's writer (the cube files are closed frame by frame)."""
        if self.tiff is not None:
            self.tiff.close()


def compression_for(fmt: str, compression):
    """The compression format ``fmt`` is written with when a batch asks for ``compression``:
    ``"auto"`` the format's default (:data:`DEFAULT_COMPRESSION`), None none, another name
    itself for the TIFF formats and zlib for netCDF (its one codec); ENVI never.

    >>> compression_for("tiff", "auto"), compression_for("netcdf", "zstd")
    ({'dq': 'zstd'}, 'zlib')
    >>> compression_for("envi", "auto") is None and compression_for("ome", None) is None
    True
    """
    if compression == "auto":
        return DEFAULT_COMPRESSION[fmt]
    if fmt == "envi" or compression is None:
        return None
    return "zlib" if fmt == "netcdf" else compression


def _finish_cube(fmt: str, target: Path, fileset, token: str, text: str, run: str,
                 alpha: bool) -> None:
    """Replace the provenance placeholder ``token`` of the staged cube ``target`` by the
    JSON ``text``."""
    if fmt == "envi":
        files = cube_files(target, "envi", alpha=alpha)
        for header, data in zip(files[::2], files[1::2]):
            tmp = fileset.temp(header)
            head = Path(tmp).read_text(encoding="utf-8")
            if header == files[0]:
                if token not in head:
                    raise DataFormatError("the provenance placeholder is missing from the "
                                          "header being written", path=header)
                head = head.replace(token, text)
            st = os.stat(fileset.temp(data))
            head += f"hsiffc run = {run}\nhsiffc data stamp = {{{st.st_size}, " \
                    f"{st.st_mtime_ns}}}\n"
            Path(tmp).write_text(head, encoding="utf-8")
    elif fmt == "ome":
        import tifffile

        with tifffile.TiffFile(fileset.temp(target), mode="r+b") as tf:
            tag = tf.pages[0].tags["ImageDescription"]
            xml = tag.value
            old, new = _xml_escape(token), _xml_escape(text)
            if old not in xml:
                raise DataFormatError("the provenance placeholder is missing from the OME-XML "
                                      "being written", path=target)
            tag.overwrite(xml.replace(old, new))
    else:
        import h5py

        with h5py.File(fileset.temp(target), "r+") as h5:
            value = h5.attrs.get("provenance")
            value = value.decode() if isinstance(value, bytes) else str(value)
            if value != token:
                raise DataFormatError("the provenance placeholder is missing from the netCDF "
                                      "being written", path=target)
            h5.attrs["provenance"] = text


def _xml_escape(text: str) -> str:
    """``text`` as tifffile writes it into OME-XML (``&``, ``<``, ``>`` and ``"``)."""
    return (text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .replace('"', "&quot;"))


# -- reading a product back (the batch's resume check) -----------------------------------------
def _cube_provenance(path: Path, fmt: str) -> dict:
    """The provenance a cube file of ``hsiffc correct`` holds (its metadata only: no pixel is
    read); DataFormatError when it holds none, or only the placeholder of an unfinished
    write."""
    from ..files.atomic import require_regular_input
    from ..files.parsers import load_json

    require_regular_input(path, what="cube file")
    if fmt == "envi":
        from ..io.envi import parse_envi_header

        raw = parse_envi_header(path)
        pairs = load_json(_text(raw.get("hsiffc attrs", "[]")), path=path,
                          what="'hsiffc attrs' value")
        found = {str(p[0]): p[1] for p in pairs if isinstance(p, list) and len(p) == 2} \
            if isinstance(pairs, list) else {}
        prov = found.get("provenance")
    elif fmt == "ome":
        import tifffile

        with tifffile.TiffFile(path) as tf:
            xml = tf.pages[0].description or ""
        start, end = xml.find("<Description>"), xml.find("</Description>")
        doc = {}
        if 0 <= start < end:
            import html

            doc = load_json(html.unescape(xml[start + len("<Description>"):end]), path=path,
                            what="OME Description")
        prov = (doc.get("attrs") or {}).get("provenance") if isinstance(doc, dict) else None
    else:
        import h5py

        try:
            with h5py.File(path, "r") as h5:
                value = h5.attrs.get("provenance")
        except OSError as exc:
            raise DataFormatError(f"not a netCDF-4 file hsiffc wrote ({exc})",
                                  path=path) from None
        value = value.decode() if isinstance(value, bytes) else value
        prov = None if value is None else load_json(str(value), path=path,
                                                    what="provenance attribute")
    if not isinstance(prov, dict) or "pending" in prov or not prov.get("run"):
        raise DataFormatError("holds no finished provenance of hsiffc correct (an interrupted "
                              "write, or another program's file)", path=path)
    return prov


def _text(value) -> str:
    return ", ".join(value) if isinstance(value, list) else str(value)


def read_product(out, fmt: str) -> dict:
    """The provenance of the complete product of ``out`` in ``fmt``.

    For a cube format: frame 0's provenance, its per-frame lists gathered from every frame's
    file, after checking that every file of the product is there and says the same run (and
    that each ENVI data file is the one its header was written with).

    Raises
    ------
    DataFormatError
        A file is missing, unreadable, unfinished, or of another run (the product must be
        redone); the message names it.
    """
    from ..io.corrected import read_provenance

    if fmt == "tiff":
        return read_provenance(out)
    out = Path(out)
    one, many = _main_files(out, fmt, 1)[0], _main_files(out, fmt, 2)[0]
    first = one if os.path.lexists(one) else many
    prov = _cube_provenance(first, fmt)
    n = int(prov.get("n_frames") or 0)
    mains = _main_files(out, fmt, max(n, 1))
    if n < 1 or mains[0] != first:
        raise DataFormatError(f"says {n} frames, but is named as a product of "
                              f"{'one frame' if first == one else 'several'}", path=first)
    alpha = bool(prov.get("cube_alpha"))
    files = product_files(out, fmt, n, alpha)
    missing = [f for f in files if not os.path.isfile(f)]
    if missing:
        raise DataFormatError(f"the product is incomplete: {missing[0].name} is missing",
                              path=first)
    gathered = {key: [] for key in _PER_FRAME}
    frames: dict = {}
    for k, main in enumerate(mains):
        doc = prov if k == 0 else _cube_provenance(main, fmt)
        if doc.get("run") != prov["run"] or doc.get("frame") != k:
            raise DataFormatError(f"is frame {doc.get('frame')} of another run than "
                                  f"{first.name}; the product is mixed", path=main)
        for key in _PER_FRAME:
            gathered[key] += list(doc.get(key) or ())
        for key, v in (doc.get("frames") or {}).items():
            if isinstance(v, list):
                frames.setdefault(key, []).extend(v)
            else:
                frames[key] = v
    if fmt == "envi":
        _check_envi_stamps(files, prov["run"])
    return {**prov, **gathered, "frames": frames, "frame": None}


def _check_envi_stamps(files: list[Path], run: str) -> None:
    """Every ENVI header of the product names ``run`` and the size and time of its data
    file as they are (a data file of another run beside it is seen)."""
    from ..io.envi import parse_envi_header

    for header, data in zip(files[::2], files[1::2]):
        head = parse_envi_header(header)
        stamp = head.get("hsiffc data stamp")
        st = os.stat(data)
        if head.get("hsiffc run") != run or stamp != [str(st.st_size), str(st.st_mtime_ns)]:
            raise DataFormatError(f"is not the data file its header {header.name} was "
                                  "written with (another run's, or changed since); the "
                                  "product is mixed", path=data)
