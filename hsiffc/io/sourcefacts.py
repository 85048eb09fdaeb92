"""What a frame source knows before it decodes a frame for the caller.

:class:`hsiffc.io.source.FrameSource` resolves the metadata of every file (file, then sidecar,
then options: :mod:`hsiffc.io.metadata`) and then, from those per-file values, builds what this
module holds:

* the per-frame columns (exposure, kind, illumination, photons, step) and where each field came
  from (:func:`frame_columns`, :func:`merge_origins`);
* the per-source facts every file must agree on (:func:`agree`): frame shape and dtype, mosaic
  (with band centres the file states apart from it: :func:`attach_wavelengths`), active area,
  bit depth and bit shift, detected from the first frame's values when no source states them
  (:func:`resolve_facts`);
* the decoding of one stored frame with its structural checks (:func:`read_stored`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import DataFormatError
from . import quirks
from .layout import FileLayout
from .metadata import missing_field_error, missing_origin

__all__ = ["SourceFacts", "agree", "attach_wavelengths", "frame_columns", "merge_origins",
           "read_stored", "resolve_facts"]


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
        Per file, the resolved ``(values, origins)`` of :func:`hsiffc.io.metadata.resolve_fields`.
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
        Per file ``(values, origins)`` from :func:`hsiffc.io.metadata.resolve_fields`.
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
        shift = quirks.detect_left_aligned(first, bits)
        if shift:
            notes.append(f"samples left-aligned in 16-bit words: shifted right by {shift} bits "
                         "(detected from the values; --bit-shift 0 turns this off)")
            if bits is None:
                bits = 16 - shift
                bits_origin = f"detected (left-aligned by {shift} bits)"
                # stacklevel: here, FrameSource.__init__, open_source, its caller
                warnings.warn(f"{label}: {notes[-1]}; bit depth {bits}",
                              quirks.LayoutWarning, stacklevel=4)
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
            bits = quirks.infer_bit_depth(dtype, label)
            bits_origin = f"dtype {dtype} (assumed; full scale may be wrong)"
    h, w = stored[:2]
    active_area, (h, w), note = quirks.active_area_crop(active_area, (h, w), label)
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
    return quirks.single_channel(raw, lay.path, k, lay.meta.get("channel_hint", ""))
