"""The one streaming reader: :func:`open_source` -> :class:`FrameSource`.

A frame source is opened from a file, a folder, a glob or a list of them. It parses every
header once, checks the size limits and the file structure, resolves the metadata of every
frame (file, then sidecar, then options) and then knows, before any pixel is decoded, the
number of frames, their shape, dtype, exposure, kind, bit depth and mosaic (resolved over all
files: the helpers at the end of this module). Frames are decoded one at a time::

    from hsiffc.io import open_source

    with open_source("raw/", exposure_ms=20, bit_depth=12, mosaic="5x5") as src:
        print(src.n_frames, src.frame_shape, src.origins["exposure_ms"])
        for raw, meta in src:            # (H, W) ndarray in DN, FrameMeta
            ...
    sweep = open_source("sweep.tif").to_sweep()   # everything in memory, as a Sweep

Formats: hsiffc TIFF and plain TIFF (any compression imagecodecs decodes), PNG (8/16-bit),
ENVI (``.hdr`` + data), FITS (with astropy), EMVA 1288 descriptors; see
``docs/formats-and-metadata.md``.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ._quirks import (LayoutWarning, active_area_crop, detect_left_aligned, infer_bit_depth,
                      single_channel, unshift)
from ..data.frame import Frame
from ..data.sweep import Sweep
from ..errors import DataFormatError
from ..files.limits import ReadLimits, default_limits
from ._layout import FileLayout, FrameMeta
from ._metadata import Overrides, missing_field_error, missing_origin, resolve_fields
from ._readers import expand_inputs, open_layout
from ._sidecar import Sidecar, find_sidecar
from .envi import envi_paths

__all__ = ["open_source", "FrameSource", "FrameMeta", "expand_inputs"]


# --- The frame source -------------------------------------------------------------------------

def open_source(inputs, *, limits: ReadLimits | None = None, overrides: Overrides | None = None,
                inspect: bool = False, **options) -> "FrameSource":
    """Open files, folders or globs as one stream of frames (nothing decoded yet).

    Parameters
    ----------
    inputs : path, str or sequence of them
        Files of any supported format, folders (their image files, sorted by name, or the
        EMVA 1288 measurement they hold) or glob patterns (``"raw/*.tif"``).
    limits : ReadLimits, optional
        Size limits (default :func:`~hsiffc.files.limits.default_limits`).
    overrides : Overrides, optional
        Metadata from the command line; or give its fields as keywords: ``exposure_ms``,
        ``bit_depth``, ``kind``, ``mosaic``, ``illumination``, ``bit_shift``, ``sidecar``.
    inspect : bool
        Describe rather than use (``hsiffc info``): a missing exposure time (NaN) or bit depth
        of float data (None) is listed in :attr:`FrameSource.missing` instead of raising.

    Returns
    -------
    FrameSource
        Iterate over it for ``(raw, FrameMeta)`` pairs (raw: (H, W) array of DN in the file's
        dtype), or call :meth:`FrameSource.frames` / :meth:`FrameSource.to_sweep`. Use it as a
        context manager (or call ``close()``) to release the files.

    Raises
    ------
    DataFormatError
        A missing or unreadable input, a header over the limits, a truncated file, missing
        metadata (the message names the file, the field and the three ways to give it), or files
        that disagree on frame shape, bit depth or mosaic.

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "frames.tif"      # a plain TIFF: 3 frames of 4 x 6 px
    >>> tifffile.imwrite(path, np.full((3, 4, 6), 100, np.uint16), photometric="minisblack")
    >>> with open_source(path, exposure_ms=10.0, bit_depth=12) as src:
    ...     print(len(src), src.frame_shape, src.origins["exposure_ms"])
    ...     for raw, meta in src:                                 # one frame at a time
    ...         pass
    3 (4, 6) --exposure-ms
    >>> raw.shape, meta.index, meta.exposure_ms, meta.kind
    ((4, 6), 2, 10.0, 'light')
    """
    if overrides is None:
        overrides = Overrides(**options)
    elif options:
        raise TypeError("give either overrides= or metadata keywords, not both")
    limits = limits or default_limits()
    files = expand_inputs(inputs)
    if not files:
        raise DataFormatError(f"no image file in {inputs}; give TIFF, PNG, ENVI (.hdr), FITS "
                              "files or an EMVA 1288 descriptor")
    layouts = []
    try:
        for f in files:
            layouts.append(open_layout(f, limits))
        limits.check_frames(path=files[0], n_frames=sum(lay.n_frames for lay in layouts),
                            shape=layouts[0].shape, itemsize=layouts[0].dtype.itemsize)
        return FrameSource(layouts, overrides, limits, label=_label(inputs, files),
                           inspect=inspect)
    except BaseException:
        for lay in layouts:
            lay.close()
        raise


def _label(inputs, files) -> str:
    if isinstance(inputs, (str, Path)):
        return str(files[0]) if len(files) == 1 else str(inputs)
    return str(files[0]) if len(files) == 1 else f"{len(files)} files from {files[0].parent}"


class FrameSource:
    """Frames of one or more files with their resolved metadata (see :func:`open_source`).

    Attributes
    ----------
    n_frames : int
    frame_shape : (int, int)
        (H, W) of the frames yielded (after channel selection and active-area crop).
    dtype : numpy.dtype
        Sample type of the frames yielded.
    bit_depth : int
    mosaic : Mosaic or None
    exposure_ms, kind, illumination, photons : (N,) arrays
    step : (N,) int array or None
    origins : dict
        Field -> where its value came from (``"file (EXIF ExposureTime)"``, ``"sidecar
        hsiffc.toml"``, ``"--exposure-ms"``, ...); several origins are joined with " + ".
    notes : list of str
        Layout quirks handled (equal channels, shift, crop).
    missing : list of str
        Fields no source gives (only with ``inspect=True``; otherwise missing ones raise).
    files : list of Path
    metadata_files : list of Path
        Other files whose content gave metadata: sidecars, IMEC XML, the ENVI header of a data
        file named.
    data_files : list of Path
        Other files the frames are read from: the data file of an ENVI header named.
    sidecar_lookup : bool
        Whether a sidecar next to the data would be read (no ``sidecar`` override and a file
        that is not self-describing).
    meta : dict

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import open_source
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frames.tif"                 # a plain TIFF: 2 frames of 4 x 6 px
    >>> tifffile.imwrite(path, np.arange(48, dtype=np.uint16).reshape(2, 4, 6),
    ...                  photometric="minisblack")
    >>> with open_source(path, exposure_ms=5.0, bit_depth=12) as src:
    ...     print(src.n_frames, src.frame_shape, src.dtype, src.bit_depth)
    ...     first = src.read(0)                               # one frame, (H, W) in DN
    ...     sweep = src.to_sweep()                            # or all of them
    2 (4, 6) uint16 12
    >>> int(first[1, 0]), sweep.data.shape
    (6, (2, 4, 6))
    >>> tmp.cleanup()
    """

    def __init__(self, layouts: list[FileLayout], overrides: Overrides, limits: ReadLimits,
                 *, label: str = "", inspect: bool = False):
        self.layouts, self.limits, self.label = layouts, limits, label
        self.files = [lay.path for lay in layouts]
        self.notes: list[str] = []
        self.missing: list[str] = []
        self._inspect = inspect
        self._peeked = None
        #: Frames decoded ahead on worker threads while iterating (0: none).
        self.prefetch = 2 if (os.cpu_count() or 1) > 1 else 0
        sidecars: dict[Path, Sidecar | None] = {}
        xmls: list = []
        resolved = []
        for lay in layouts:
            if overrides.sidecar is not None:
                side_path = Path(overrides.sidecar)
            else:
                side_path = None if lay.strict else find_sidecar(lay.path.parent)
            if side_path is not None and side_path not in sidecars:
                sidecars[side_path] = Sidecar(side_path)
            resolved.append(resolve_fields(lay, sidecars.get(side_path), overrides,
                                           missing=self.missing if inspect else None,
                                           sources=xmls))
        self._starts = np.cumsum([0] + [lay.n_frames for lay in layouts])
        self.n_frames = int(self._starts[-1])
        facts = resolve_facts(layouts, resolved, label=self.label, inspect=inspect,
                              n_frames=self.n_frames,
                              first_frame=lambda: self._decode(0, peek=True),
                              notes=self.notes, missing=self.missing)
        self.dtype, self.mosaic, self.active_area = facts.dtype, facts.mosaic, facts.active_area
        self.channels, self.bit_shift, self.bit_depth = (facts.channels, facts.bit_shift,
                                                         facts.bit_depth)
        self.frame_shape = facts.frame_shape
        self._bits_origin = facts.bits_origin
        self._peeked = facts.peeked  # frame 0, decoded once: reused by the first read
        columns = frame_columns(layouts, resolved, label=self.label, inspect=inspect)
        self.exposure_ms, self.kind = columns["exposure_ms"], columns["kind"]
        self.illumination, self.photons = columns["illumination"], columns["photons"]
        self.step = columns["step"]
        self.origins = merge_origins(resolved)
        self.origins.setdefault("bit_depth", self._bits_origin)
        self.format = "+".join(sorted({lay.format for lay in layouts}))
        self.strict = all(lay.strict for lay in layouts)
        self.meta = dict(layouts[0].meta) if len(layouts) == 1 else {
            "files": [str(p) for p in self.files]}
        pairs = [(lay.path, *envi_paths(lay.path)) for lay in layouts if lay.format == "envi"]
        #: Files besides the data whose content gave metadata (sidecars, IMEC XML, the ENVI
        #: header of a data file named), without repeats: the batch's resume check compares
        #: their content.
        self.metadata_files = list(dict.fromkeys(
            [*sidecars, *xmls, *(head for named, head, _ in pairs if head != named)]))
        #: Files the frames are read from besides those named (the data file of an ENVI
        #: header): the resume check compares their size and modification time, as the
        #: input's.
        self.data_files = list(dict.fromkeys(data for named, _, data in pairs if data != named))
        #: Whether a sidecar next to the data would have been read (a file not self-describing).
        self.sidecar_lookup = overrides.sidecar is None and not all(lay.strict
                                                                    for lay in layouts)

    # -- decoding -------------------------------------------------------------------------------
    def _locate(self, index: int) -> tuple[FileLayout, int]:
        if not 0 <= index < self.n_frames:
            raise IndexError(f"frame {index} out of range (0..{self.n_frames - 1})")
        f = int(np.searchsorted(self._starts, index, side="right") - 1)
        return self.layouts[f], index - int(self._starts[f])

    def _decode(self, index: int, peek: bool = False) -> np.ndarray:
        lay, k = self._locate(index)
        if index == 0 and self._peeked is not None:
            raw, self._peeked = self._peeked, None
            return raw if peek else self._finish(raw, lay, k)
        raw = read_stored(lay, k)
        return raw if peek else self._finish(raw, lay, k)

    def _finish(self, raw, lay, k):
        raw = unshift(raw, self.bit_shift, lay.path, k)
        if self.active_area is not None:
            raw = self.active_area.crop(raw)
        if raw.dtype.kind in "ui" and raw.size and int(raw.max()) > 2 ** self.bit_depth - 1:
            raise DataFormatError(
                f"frame {k}: data exceed the stated bit depth: maximum {int(raw.max())} DN > "
                f"{2 ** self.bit_depth - 1} DN (2**{self.bit_depth}-1); fix the bit depth "
                f"(from {self._bits_origin or 'the file'}) or give --bit-shift", path=lay.path)
        return raw

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as an (H, W) array of DN (decoded now).

        Parameters
        ----------
        index : int
            Frame number, 0 <= index < ``n_frames`` (over all files, in order).

        Returns
        -------
        ndarray, DN
            Shape ``frame_shape``, dtype ``dtype`` (the file's samples, never rescaled).
        """
        return self._decode(index)

    def frame_meta(self, index: int) -> FrameMeta:
        """The metadata of frame ``index``.

        Parameters
        ----------
        index : int
            Frame number, 0 <= index < ``n_frames``.

        Returns
        -------
        FrameMeta
            Index, exposure (ms), kind, illumination, photons, step, file path and page.
        """
        lay, k = self._locate(index)
        return FrameMeta(index, float(self.exposure_ms[index]), str(self.kind[index]),
                         str(self.illumination[index]), float(self.photons[index]),
                         None if self.step is None else int(self.step[index]), str(lay.path), k)

    def __iter__(self) -> Iterator[tuple[np.ndarray, FrameMeta]]:
        """Frames in order as ``(raw, FrameMeta)``. With ``prefetch`` > 0 (default: 2 on a
        machine with several cores) the next frames are decoded on worker threads while the
        caller works on the current one (codecs release the GIL); at most ``prefetch + 1``
        frames are in memory."""
        if self.prefetch < 1 or self.n_frames < 2 or not all(lay.parallel
                                                              for lay in self.layouts):
            yield from self._sequential()
            return
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        ends = {int(self._starts[f + 1]) - 1: lay for f, lay in enumerate(self.layouts)}
        with ThreadPoolExecutor(self.prefetch, thread_name_prefix="hsiffc-read") as pool:
            queue: deque = deque()
            ahead = iter(range(self.n_frames))
            try:
                for index in ahead:
                    queue.append((index, pool.submit(self._decode, index)))
                    if len(queue) > self.prefetch:
                        yield self._take(queue, ends)
                while queue:
                    yield self._take(queue, ends)
            finally:
                for _, future in queue:
                    future.cancel()
                for _, future in queue:
                    if not future.cancelled():
                        future.exception()
                self.close()

    def _take(self, queue, ends):
        index, future = queue.popleft()
        raw = future.result()
        if index in ends:
            done = ends[index]
            if not any(self._locate(i)[0] is done for i, _ in queue):
                done.close()
        return raw, self.frame_meta(index)

    def _sequential(self):
        for f, lay in enumerate(self.layouts):
            try:
                for k in range(lay.n_frames):
                    index = int(self._starts[f]) + k
                    yield self._decode(index), self.frame_meta(index)
            finally:
                lay.close()

    def __len__(self) -> int:
        return self.n_frames

    def frames(self) -> Iterator[Frame]:
        """Every frame as a :class:`~hsiffc.data.frame.Frame` (float32 DN, DQ plane), streamed.

        Yields
        ------
        Frame
            (H, W) float32 data in DN with its DQ plane, exposure (ms), kind, mosaic and
            source, one at a time (the next is decoded ahead on a worker thread).
        """
        for raw, m in self:
            extra = {} if m.step is None else {"step": m.step}
            yield Frame.from_raw(raw, exposure_ms=m.exposure_ms, bit_depth=self.bit_depth,
                                 mosaic=self.mosaic, kind=m.kind, illumination=m.illumination,
                                 source=m.path, **extra)

    def to_sweep(self) -> Sweep:
        """All frames in memory as a :class:`~hsiffc.Sweep` (checked against ``max_bytes``).

        Returns
        -------
        Sweep
            ``data`` (N, H, W) in the file's dtype and the per-frame metadata.

        Raises
        ------
        DataFormatError
            The frames would exceed the limit on bytes in memory, or their metadata disagree.
        """
        shape = (self.n_frames,) + self.frame_shape
        self.limits.check_bytes(path=self.label, nbytes=int(np.prod(shape)) * self.dtype.itemsize,
                                what=f"{self.n_frames} frames of {self.frame_shape}")
        data = np.empty(shape, self.dtype)
        for raw, m in self:
            data[m.index] = raw
        meta = dict(self.meta)
        if not self.strict:  # self-describing files keep their meta as written
            meta["layout_notes"] = list(self.notes)
            meta["metadata_origins"] = dict(self.origins)
        try:
            return Sweep(data=data, exposure_ms=self.exposure_ms, kind=self.kind,
                         bit_depth=self.bit_depth, step=self.step, photons=self.photons,
                         illumination=self.illumination, mosaic=self.mosaic,
                         source=self.label, meta=meta)
        except ValueError as exc:
            raise DataFormatError(f"inconsistent metadata: {exc}", path=self.label) from exc

    def close(self) -> None:
        """Close the open files (also done at the end of iteration and by ``with``)."""
        for lay in self.layouts:
            lay.close()

    def __enter__(self):
        return self

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: nothing left to release
            pass

    def __exit__(self, *exc):
        self.close()

    def describe(self) -> str:
        """A few lines: frames, shape, dtype, bit depth, mosaic, each field's origin, notes.

        Returns
        -------
        str
            What ``hsiffc inspect`` prints for the input.
        """
        mos = "none" if self.mosaic is None else self.mosaic.describe()
        lines = [f"{self.label}: {self.n_frames} frames of {self.frame_shape[0]} x "
                 f"{self.frame_shape[1]} px, {self.dtype}, "
                 f"{'unknown bit depth' if self.bit_depth is None else f'{self.bit_depth}-bit'}, "
                 f"mosaic {mos} "
                 f"({self.format})"]
        for name in ("exposure_ms", "kind", "illumination", "bit_depth", "mosaic", "bit_shift"):
            origin = self.origins.get(name)
            if origin is not None:
                lines.append(f"  {name:<13} {'' if origin.startswith('MISSING') else 'from '}"
                             f"{origin}")
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)


# --- What a source knows before decoding: frame columns, source facts, stored frames ----------

@dataclass
class SourceFacts:
    """The per-source facts of a frame source (see :func:`resolve_facts`).

    Attributes
    ----------
    dtype : numpy.dtype
        Sample type of the stored frames.
    mosaic : Mosaic or None
    active_area : ActiveArea or None
    bits_origin : str
        Where the bit depth came from ("" when a file states it).
    channels : int
        Channels of a stored (H, W, C) frame (0 for (H, W)).
    bit_shift : int
        Bits the samples are shifted right by.
    bit_depth : int or None
        None only for float data without a stated bit depth (``inspect``).
    frame_shape : (int, int)
        (H, W) of the frames yielded (after channel selection and active-area crop).
    peeked : ndarray or None
        Frame 0 as read to detect a layout (channel 0 only, not yet shifted or cropped), or
        None if it was not read.
    """

    dtype: np.dtype
    mosaic: object
    active_area: object
    bits_origin: str
    channels: int
    bit_shift: int
    bit_depth: int | None
    frame_shape: tuple[int, int]
    peeked: np.ndarray | None


def agree(name, values, layouts):
    """The one value of a per-source field over all files (None if none gives it).

    Parameters
    ----------
    name : str
        Field name (``"mosaic"``, ``"bit_depth"``, ...).
    values : list of (dict, dict)
        Per file, the resolved ``(values, origins)`` of :func:`hsiffc.io._metadata.resolve_fields`.
    layouts : list of FileLayout
        The files, in the order of ``values``.

    Returns
    -------
    object or None
        The value the files give (None when none gives it).

    Raises
    ------
    DataFormatError
        Two files give different values.
    """
    found = [(v[name], lay.path) for (v, _), lay in zip(values, layouts) if name in v]
    if not found:
        return None
    first, where = found[0]
    for value, path in found[1:]:
        same = first == value if not isinstance(first, np.ndarray) else np.array_equal(
            first, value)
        if not same:
            raise DataFormatError(f"{name} differs between {where} ({first!r}) and this file "
                                  f"({value!r}); read them separately", path=path)
    return first


def attach_wavelengths(mosaic, layouts, resolved):
    """Band centres a file states apart from its mosaic (ENVI ``wavelength``, hsiffc JSON
    ``wavelengths_nm``) join a mosaic that has none, when the band counts agree.

    Parameters
    ----------
    mosaic : Mosaic or None
        The mosaic the files agree on.
    layouts : list of FileLayout
        The files (the first one's ``meta["wavelengths_nm"]`` is used).
    resolved : list of (dict, dict)
        Per file ``(values, origins)``; the origins get ``"wavelengths_nm"`` when the centres
        are attached.

    Returns
    -------
    Mosaic or None
        The mosaic with the band centres, or ``mosaic`` unchanged.
    """
    from ..data.mosaic import Mosaic

    wl = layouts[0].meta.get("wavelengths_nm")
    m = mosaic
    if m is None or m.wavelengths_nm is not None or wl is None or len(wl) != m.n_bands:
        return mosaic
    mosaic = Mosaic(m.pattern, tuple(wl), m.offset, name=m.name)
    for _, origins in resolved:
        origins["wavelengths_nm"] = f"file ({layouts[0].format} wavelengths)"
    return mosaic


def resolve_facts(layouts, resolved, *, label: str, inspect: bool, n_frames: int,
                  first_frame: Callable[[], np.ndarray], notes: list,
                  missing: list) -> SourceFacts:
    """Shape, dtype, mosaic, active area, bit depth and bit shift over all files.

    Frame 0 is read (once) when the layout must be detected from the values: several channels,
    an integer bit depth no source gives, or 16-bit words that may hold left-aligned samples.

    Parameters
    ----------
    layouts : list of FileLayout
        The files.
    resolved : list of (dict, dict)
        Per file ``(values, origins)`` from :func:`hsiffc.io._metadata.resolve_fields`.
    label : str
        Name of the source in messages.
    inspect : bool
        Describe rather than use: a float source without a bit depth lists ``"bit_depth"`` in
        ``missing`` instead of raising.
    n_frames : int
        Frames over all files.
    first_frame : callable
        Returns frame 0 as :func:`read_stored` reads it.
    notes, missing : list of str
        Appended to: layout quirks handled, fields no source gives.

    Returns
    -------
    SourceFacts

    Raises
    ------
    DataFormatError
        Files of different shapes or dtypes, frames that are not images, files that disagree
        on a per-source field, or float data without a bit depth (unless ``inspect``).
    """
    shapes = {lay.shape for lay in layouts}
    dtypes = {lay.dtype for lay in layouts}
    if len(shapes) != 1 or len(dtypes) != 1:
        raise DataFormatError(f"the files hold frames of different shapes or dtypes "
                              f"({sorted(map(str, shapes))}, {sorted(map(str, dtypes))}); "
                              "read them separately", path=label)
    stored = layouts[0].shape
    dtype = layouts[0].dtype
    mosaic = attach_wavelengths(agree("mosaic", resolved, layouts), layouts, resolved)
    active_area = agree("active_area", resolved, layouts)
    bits = agree("bit_depth", resolved, layouts)
    shift = agree("bit_shift", resolved, layouts)
    bits_origin = resolved[0][1].get("bit_depth", "")
    channels = stored[2] if len(stored) == 3 else 0
    if len(stored) not in (2, 3):
        raise DataFormatError(f"frames of shape {stored} are not images", path=label)
    needs_peek = channels or (bits is None and shift is None and dtype.kind in "ui")
    needs_peek = needs_peek or (shift is None and dtype == np.uint16 and bits and bits < 16)
    strict = any(lay.strict for lay in layouts)
    first = first_frame() if needs_peek and n_frames else None
    if shift is None and first is not None and dtype == np.uint16 and not strict:
        shift = detect_left_aligned(first, bits)
        if shift:
            notes.append(f"samples left-aligned in 16-bit words: shifted right by {shift} bits "
                         "(detected from the values; --bit-shift 0 turns this off)")
            if bits is None:
                bits = 16 - shift
                bits_origin = f"detected (left-aligned by {shift} bits)"
                # stacklevel: here, FrameSource.__init__, open_source, its caller
                warnings.warn(f"{label}: {notes[-1]}; bit depth {bits}",
                              LayoutWarning, stacklevel=4)
    bit_shift = int(shift or 0)
    if bit_shift and (dtype.kind not in "ui" or bit_shift >= 8 * dtype.itemsize):
        origin = resolved[0][1].get("bit_shift", "the bit shift")
        raise DataFormatError(f"bit_shift {bit_shift} from {origin} cannot apply to {dtype} "
                              f"samples (only integers, by fewer bits than the "
                              f"{8 * dtype.itemsize}-bit words); remove it or give the right "
                              "one", path=label)
    if bits is None and bit_shift:
        bits = 8 * dtype.itemsize - bit_shift
        bits_origin = "--bit-shift"
    if bits is None:
        if dtype.kind == "f" and inspect:
            missing.append("bit_depth")
            bits_origin = missing_origin("bit_depth")
        elif dtype.kind == "f":
            raise missing_field_error(label, "bit_depth")
        else:
            bits = infer_bit_depth(dtype, label)
            bits_origin = f"dtype {dtype} (assumed; full scale may be wrong)"
    h, w = stored[:2]
    active_area, (h, w), note = active_area_crop(active_area, (h, w), label)
    if note:
        notes.append(note)
    if channels:
        notes.append(f"{channels}-channel image with equal channels: channel 0 used")
    return SourceFacts(dtype=dtype, mosaic=mosaic, active_area=active_area,
                       bits_origin=bits_origin, channels=channels, bit_shift=bit_shift,
                       bit_depth=None if bits is None else int(bits),
                       frame_shape=(int(h), int(w)), peeked=first)


def frame_columns(layouts, resolved, *, label: str, inspect: bool) -> dict:
    """The per-frame metadata over all files, one (N,) array per field.

    Parameters
    ----------
    layouts : list of FileLayout
        The files.
    resolved : list of (dict, dict)
        Per file ``(values, origins)``; a value is one for the file or one per frame.
    label : str
        Name of the source in messages.
    inspect : bool
        Allow a missing (NaN) exposure time.

    Returns
    -------
    dict
        ``exposure_ms`` (float64), ``kind``, ``illumination`` (str), ``photons`` (float64, NaN
        when unknown) and ``step`` (int64, or None unless every file gives it).

    Raises
    ------
    DataFormatError
        An exposure time that is not finite and >= 0 ms (NaN allowed with ``inspect``).
    """
    def column(name, dtype):
        parts = [np.broadcast_to(np.asarray(values[name], dtype=dtype), (lay.n_frames,))
                 for lay, (values, _) in zip(layouts, resolved)]
        return np.concatenate(parts) if parts else np.empty(0, dtype)

    exposure_ms = column("exposure_ms", np.float64)
    out = {"exposure_ms": exposure_ms,
           "kind": column("kind", object).astype(str),
           "illumination": column("illumination", object).astype(str),
           "photons": np.concatenate([np.broadcast_to(np.asarray(
               v.get("photons", np.nan), np.float64), (lay.n_frames,))
               for lay, (v, _) in zip(layouts, resolved)]),
           "step": (column("step", np.int64) if all("step" in v for v, _ in resolved)
                    else None)}
    bad = ~np.isfinite(exposure_ms) | (exposure_ms < 0)
    if np.any(bad & ~(np.isnan(exposure_ms) & inspect)):
        raise DataFormatError("exposure times must be finite and >= 0 ms", path=label)
    return out


def merge_origins(resolved) -> dict:
    """Field -> where its value came from, over all files (several origins joined by " + ").

    Parameters
    ----------
    resolved : list of (dict, dict)
        Per file ``(values, origins)``.

    Returns
    -------
    dict of str
        Field name -> origin(s), in the order first seen.
    """
    merged: dict = {}
    for _, origins in resolved:
        for name, origin in origins.items():
            known = merged.setdefault(name, [])
            if origin not in known:
                known.append(origin)
    return {k: " + ".join(v) for k, v in merged.items()}


def read_stored(lay: FileLayout, k: int) -> np.ndarray:
    """Frame ``k`` of one file as stored, checked against its header, channel 0 only.

    Parameters
    ----------
    lay : FileLayout
        The file.
    k : int
        Frame number within the file.

    Returns
    -------
    ndarray, DN
        (H, W) in the file's dtype, not yet shifted or cropped.

    Raises
    ------
    DataFormatError
        The frame decodes to another shape than the header says, or its channels differ.
    """
    raw = lay.read(k)
    if raw.shape != lay.shape:
        raise DataFormatError(f"frame {k} decodes to shape {raw.shape} but the header says "
                              f"{lay.shape}; the file is damaged", path=lay.path)
    return single_channel(raw, lay.path, k, lay.meta.get("channel_hint", ""))
