"""Measurements stored in the native EMVA 1288 format (descriptor + image files): finding the
descriptor in a folder, parsing it and reading the sweep it describes.

An EMVA 1288 descriptor is a text file with one record per line:

* ``# ...`` comment (kept in ``meta["comments"]``); blank lines are ignored;
* ``v <version>`` version of the standard the measurement follows;
* ``n <bits> <width> <height>`` ADC bit depth and image size in pixels;
* ``b <exposure> <photons>`` a bright (light) step: exposure time and mean photons per pixel;
* ``d <exposure>`` a dark step;
* ``i <path>`` an image of the preceding ``b``/``d`` step, relative to the descriptor's folder
  (``\\`` separators, as written on Windows, are accepted).

Exposure times in EMVA 1288 descriptors are in nanoseconds (the convention of the standard and
of its reference implementation); :func:`read_emva1288` converts them to milliseconds. Pass
``exposure_unit`` when a descriptor was written in another unit.

A measurement holds the *sweep* (every step with 2 images) and usually a *spatial* set: one
bright and one dark step with many images (e.g. 100) at a single exposure, for the
non-uniformity statistics. Steps with more than twice the median number of images per step are
taken as spatial steps; their step ids are listed in ``meta["spatial_steps"]`` and the others in
``meta["sweep_steps"]``.

A folder holds one descriptor (:func:`find_emva_descriptor`; the usual name is
:data:`DEFAULT_DESCRIPTOR_NAME`); :func:`parse_descriptor` checks its lines and
:func:`read_emva1288` / :func:`open_emva1288` build the sweep from them.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import numpy as np
import tifffile

from ..data.sweep import Sweep
from ..errors import DataFormatError
from ..files.limits import ReadLimits, default_limits
from .tiff import EXPOSURE_UNITS_MS, exposure_to_ms
from ._layout import FileLayout

__all__ = ["DEFAULT_DESCRIPTOR_NAME", "emva_files", "find_emva_descriptor", "has_emva_descriptor",
           "image_path", "parse_descriptor", "read_emva1288", "open_emva1288"]


# --- The descriptor ---------------------------------------------------------------------------

DEFAULT_DESCRIPTOR_NAME = "EMVA1288_Data.txt"
_VERSION_LINE = re.compile(r"^\s*v\s+\S", re.MULTILINE)


def has_emva_descriptor(folder) -> bool:
    """True when ``folder`` holds exactly one EMVA 1288 descriptor.

    Parameters
    ----------
    folder : str or Path
        Any folder.

    Returns
    -------
    bool
    """
    try:
        find_emva_descriptor(folder)
    except DataFormatError:
        return False
    return True


def find_emva_descriptor(folder) -> Path:
    """The descriptor of an EMVA 1288 measurement folder.

    ``EMVA1288_Data.txt`` if present, otherwise the only ``*.txt`` file that has a ``v`` line.

    Parameters
    ----------
    folder : str or Path
        The measurement folder.

    Returns
    -------
    Path

    Raises
    ------
    DataFormatError
        No descriptor, or several candidates (the message lists them).
    """
    folder = Path(folder)
    named = folder / DEFAULT_DESCRIPTOR_NAME
    if named.is_file():
        return named
    found = []
    for txt in sorted(folder.glob("*.txt")):
        try:
            if not stat.S_ISREG(os.stat(txt).st_mode):
                continue  # a FIFO, device or socket named *.txt is never opened (it may block)
            text = txt.read_text(errors="replace")
        except OSError:
            continue
        if _VERSION_LINE.search(text):
            found.append(txt)
    if len(found) == 1:
        return found[0]
    if not found:
        raise DataFormatError(
            f"no EMVA 1288 descriptor in this folder (looked for {DEFAULT_DESCRIPTOR_NAME} or a "
            "*.txt file with a 'v <version>' line); give the descriptor file itself", path=folder)
    raise DataFormatError(
        f"several EMVA 1288 descriptors in this folder ({', '.join(p.name for p in found)}); "
        "give the one to read as a file path", path=folder)


class _Step:
    __slots__ = ("kind", "exposure", "photons", "line", "images")

    def __init__(self, kind, exposure, photons, line):
        self.kind, self.exposure, self.photons, self.line = kind, exposure, photons, line
        self.images: list[tuple[str, int]] = []  # (path text, line number)


def _numbers(parts, count, descriptor, lineno, line, usage):
    if len(parts) - 1 not in count:
        raise DataFormatError(f"line {lineno}: malformed {parts[0]!r} line {line!r}; expected "
                              f"{usage!r}", path=descriptor)
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError:
        raise DataFormatError(f"line {lineno}: {line!r} holds a value that is not a number; "
                              f"expected {usage!r}", path=descriptor) from None
    if not all(np.isfinite(values)) or any(v < 0 for v in values):
        raise DataFormatError(f"line {lineno}: {line!r} holds a negative or non-finite value; "
                              f"expected {usage!r}", path=descriptor)
    return values


def emva_files(path) -> list[Path]:
    """The files of an EMVA 1288 measurement: its descriptor and every image its ``i`` lines
    name (whether or not they exist), as :func:`open_emva1288` would read them; the command
    line protects them all from being written.

    Parameters
    ----------
    path : str or Path
        The descriptor ``.txt`` or its folder.

    Raises
    ------
    DataFormatError
        No descriptor, or an invalid descriptor line.
    """
    path = Path(path)
    descriptor = find_emva_descriptor(path) if path.is_dir() else path
    _, steps = parse_descriptor(descriptor)
    return [descriptor] + [descriptor.parent / image_path(name) for s in steps
                           for name, _ in s.images]


def image_path(name: str) -> str:
    """An ``i`` line's image path, relative to the descriptor's folder (``\\`` as ``/``)."""
    return name.replace("\\", "/")


def parse_descriptor(descriptor: Path):
    from ..files.atomic import require_regular_input

    require_regular_input(descriptor, what="EMVA 1288 descriptor")
    try:
        text = descriptor.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DataFormatError(f"cannot read the descriptor ({exc}); check the file permissions",
                              path=descriptor) from exc
    header = {"version": None, "bits": None, "width": None, "height": None, "comments": []}
    steps: list[_Step] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            header["comments"].append(line[1:].strip())
            continue
        parts = line.split()
        tag = parts[0]
        if tag == "v":
            if len(parts) != 2:
                raise DataFormatError(f"line {lineno}: malformed version line {line!r}; expected "
                                      "'v <version>'", path=descriptor)
            header["version"] = parts[1]
        elif tag == "n":
            usage = "n <bits> <width> <height>"
            values = _numbers(parts, (3,), descriptor, lineno, line, usage)
            if not all(v == int(v) for v in values):
                raise DataFormatError(f"line {lineno}: {line!r} must hold whole numbers; expected "
                                      f"{usage!r}", path=descriptor)
            bits, width, height = (int(v) for v in values)
            if not 1 <= bits <= 16:
                raise DataFormatError(f"line {lineno}: unknown bit depth {bits} in {line!r}; "
                                      "EMVA 1288 images have 1..16 bits", path=descriptor)
            if width < 1 or height < 1:
                raise DataFormatError(f"line {lineno}: image size must be positive in {line!r}",
                                      path=descriptor)
            if header["bits"] is not None and (bits, width, height) != (
                    header["bits"], header["width"], header["height"]):
                raise DataFormatError(f"line {lineno}: second 'n' line {line!r} contradicts the "
                                      "first; keep one", path=descriptor)
            header.update(bits=bits, width=width, height=height)
        elif tag == "b":
            exposure, photons = _numbers(parts, (2,), descriptor, lineno, line,
                                         "b <exposure> <photons>")
            steps.append(_Step("light", exposure, photons, lineno))
        elif tag == "d":
            values = _numbers(parts, (1, 2), descriptor, lineno, line, "d <exposure>")
            if len(values) == 2 and values[1] != 0:
                raise DataFormatError(f"line {lineno}: a dark step cannot have photons "
                                      f"({line!r}); use 'd <exposure>'", path=descriptor)
            steps.append(_Step("dark", values[0], np.nan, lineno))
        elif tag == "i":
            name = line[1:].strip()
            if not name:
                raise DataFormatError(f"line {lineno}: 'i' line without an image path",
                                      path=descriptor)
            if not steps:
                raise DataFormatError(f"line {lineno}: image {name!r} comes before any 'b' or "
                                      "'d' step line; put it after the step it belongs to",
                                      path=descriptor)
            steps[-1].images.append((name, lineno))
        else:
            raise DataFormatError(f"line {lineno}: malformed line {line!r}; EMVA 1288 descriptor "
                                  "lines start with #, v, n, b, d or i", path=descriptor)
    if header["bits"] is None:
        raise DataFormatError("unknown bit depth: the descriptor has no 'n <bits> <width> "
                              "<height>' line; add it before the steps", path=descriptor)
    if not steps:
        raise DataFormatError("the descriptor has no 'b' or 'd' step; nothing to read",
                              path=descriptor)
    for s in steps:
        if not s.images:
            raise DataFormatError(f"line {s.line}: the step on this line has no 'i' image lines; "
                                  "add its images or remove the step", path=descriptor)
    return header, steps


# --- Reading the measurement ------------------------------------------------------------------

SPATIAL_FACTOR = 2.0  # a step with more than this x the median images per step is "spatial"


def _load_image(image: Path, descriptor: Path, lineno: int, shape: tuple) -> np.ndarray:
    """Decode one image named by an ``i`` line, after checking from its header (PNG ``IHDR``,
    TIFF page) that it is one plane of the size the ``n`` line declares: the descriptor's size
    is what the limits were checked against, so an image claiming more is refused before any
    pixel is decoded."""
    from ..files.atomic import require_regular_input
    from ._images import decode_png, png_header

    where = f"line {lineno}: image {image}"
    if not os.path.lexists(image):
        raise DataFormatError(f"{where} not found; check the 'i' line and that the images were "
                              "copied with the descriptor", path=descriptor)
    try:
        require_regular_input(image, what="image")
        if image.suffix.lower() in (".tif", ".tiff"):
            with tifffile.TiffFile(image) as tf:
                pages = tf.pages
                found = (len(pages),) + tuple(pages[0].shape) if len(pages) else (0,)
                if found != (1,) + tuple(shape):
                    _wrong_size(where, found[1:] if found[0] == 1 else found, shape,
                                descriptor)
                return pages[0].asarray()
        facts = png_header(image)
        channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(facts["colour_type"], 1)
        found = (facts["height"], facts["width"]) + ((channels,) if channels > 1 else ())
        if found != tuple(shape):
            _wrong_size(where, found, shape, descriptor)
        return decode_png(image, facts)
    except DataFormatError as exc:
        if exc.path == str(descriptor):
            raise
        text = str(exc)
        if exc.path and text.startswith(f"{exc.path}: "):
            text = text[len(exc.path) + 2:]
        raise DataFormatError(f"{where} is unreadable or truncated: {text}",
                              path=descriptor) from exc
    except Exception as exc:  # tifffile, OpenCV: a damaged or cut file
        raise DataFormatError(f"{where} is unreadable or truncated ({type(exc).__name__}: "
                              f"{' '.join(str(exc).split())[:200]}); copy it again",
                              path=descriptor) from exc


def _wrong_size(where: str, found: tuple, shape: tuple, descriptor: Path):
    dims = " x ".join(str(int(s)) for s in found)
    raise DataFormatError(f"{where} is {dims} but the 'n' line says {shape[0]} rows x "
                          f"{shape[1]} columns (single channel); nothing was decoded: fix the "
                          "'n' line or the image", path=descriptor)


def read_emva1288(path, *, exposure_unit: str = "ns", steps=None,
                  max_frames_per_step: int | None = None) -> Sweep:
    """Read an EMVA 1288 measurement (descriptor + PNG/TIFF images) into a Sweep.

    Parameters
    ----------
    path : str or Path
        The descriptor ``.txt`` file, or the folder holding it (see
        :func:`find_emva_descriptor`).
    exposure_unit : {"ns", "us", "ms", "s"}
        Unit of the exposure times in the descriptor. Default "ns", the EMVA 1288 convention.
    steps : iterable of int, optional
        Read only these step ids (0-based index of the ``b``/``d`` line in the descriptor).
    max_frames_per_step : int, optional
        Read at most this many images of each step (the first ones).

    Returns
    -------
    Sweep
        Frames in descriptor order (= acquisition order) with their original integer dtype
        (``uint8`` up to 8 bits, else ``uint16``); ``exposure_ms`` in milliseconds; ``kind``
        "light" for ``b`` steps and "dark" for ``d`` steps; ``photons`` mean photons per pixel
        (NaN for darks); ``step`` the step id of every frame; ``illumination`` "" (descriptors do
        not name the light source; ``photons`` carries the light level); ``bit_depth`` from the
        ``n`` line. ``meta`` holds ``format`` ("emva1288"), ``version``, ``comments``,
        ``descriptor``, ``exposure_unit_in_descriptor``, ``spatial_steps``, ``sweep_steps``
        (step ids read, in order) and ``image_files`` (per-frame paths as in the descriptor).

    Raises
    ------
    DataFormatError
        Missing descriptor, malformed line, image before any step, step without images, unknown
        bit depth, missing/unreadable/truncated image, image of the wrong size or with values
        beyond the bit depth. Messages name the descriptor, the line number and the image.

    Examples
    --------
    >>> import tempfile, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import read_emva1288
    >>> tmp = tempfile.TemporaryDirectory()
    >>> folder = Path(tmp.name)
    >>> lines = ["v 4.0", "n 12 6 4"]                    # 12-bit ADC, 6 x 4 px images
    >>> for k, step in enumerate(["b 1000000 50.0", "d 1000000"]):   # exposure 1 ms in ns
    ...     lines.append(step)
    ...     for j in range(2):
    ...         tifffile.imwrite(folder / f"s{k}_{j}.tif", np.full((4, 6), 200 - 150 * k, np.uint16))
    ...         lines.append(f"i s{k}_{j}.tif")
    >>> _ = (folder / "EMVA1288_Data.txt").write_text("\\n".join(lines) + "\\n")
    >>> sweep = read_emva1288(folder)
    >>> sweep.kind.tolist(), sweep.exposure_ms.tolist(), sweep.photons[:2].tolist(), sweep.bit_depth
    (['light', 'light', 'dark', 'dark'], [1.0, 1.0, 1.0, 1.0], [50.0, 50.0], 12)
    >>> tmp.cleanup()
    """
    from .source import FrameSource
    from ._metadata import Overrides

    limits = default_limits()
    layout = open_emva1288(path, limits, exposure_unit=exposure_unit, steps=steps,
                           max_frames_per_step=max_frames_per_step)
    with FrameSource([layout], Overrides(), limits, label=str(layout.path)) as src:
        return src.to_sweep()


def open_emva1288(path, limits: ReadLimits, *, exposure_unit: str = "ns", steps=None,
                  max_frames_per_step: int | None = None) -> FileLayout:
    """The :class:`~hsiffc.io._layout.FileLayout` of an EMVA 1288 measurement (see
    :func:`read_emva1288`); images are decoded one at a time when read.

    Parameters
    ----------
    path : str or Path
        The descriptor ``.txt`` or its folder.
    limits : ReadLimits
        Size limits.
    exposure_unit : {"ns", "us", "ms", "s"}
        Unit of the descriptor's exposure times (EMVA 1288: ns).
    steps : sequence of int, optional
        Steps to read (default: all).
    max_frames_per_step : int, optional
        Read at most this many images of each step.

    Returns
    -------
    FileLayout
        One frame per image, with exposure (ms), kind, photons and step per frame.

    Raises
    ------
    DataFormatError
        Missing descriptor or images, or an invalid descriptor line.
    ValueError
        Unknown ``exposure_unit`` or ``max_frames_per_step`` < 1.
    """
    path = Path(path)
    if not path.exists():
        raise DataFormatError("EMVA 1288 descriptor or folder not found; check the path",
                              path=path)
    descriptor = find_emva_descriptor(path) if path.is_dir() else path
    if exposure_unit not in EXPOSURE_UNITS_MS:
        raise ValueError(f"exposure_unit must be one of {sorted(EXPOSURE_UNITS_MS)}, "
                         f"got {exposure_unit!r}")
    if max_frames_per_step is not None and int(max_frames_per_step) < 1:
        raise ValueError(f"max_frames_per_step must be >= 1, got {max_frames_per_step}")
    header, all_steps = parse_descriptor(descriptor)

    counts = np.array([len(s.images) for s in all_steps])
    spatial_all = set(np.flatnonzero(counts > SPATIAL_FACTOR * np.median(counts)).tolist())
    wanted = range(len(all_steps)) if steps is None else sorted({int(s) for s in steps})
    if not wanted:
        raise ValueError("steps selects no step; give at least one step id or steps=None")
    bad = [s for s in wanted if not 0 <= s < len(all_steps)]
    if bad:
        raise ValueError(f"steps {bad} do not exist; the descriptor has steps 0..{len(all_steps) - 1}")

    bits, height, width = header["bits"], header["height"], header["width"]
    full_scale = 2 ** bits - 1
    dtype = np.dtype(np.uint8 if bits <= 8 else np.uint16)
    plan = []  # (step id, step, image text, line)
    for sid in wanted:
        s = all_steps[sid]
        images = s.images if max_frames_per_step is None else s.images[:int(max_frames_per_step)]
        plan.extend((sid, s, name, lineno) for name, lineno in images)
    limits.check_frames(path=descriptor, n_frames=len(plan), shape=(height, width),
                        itemsize=dtype.itemsize)
    root = descriptor.parent

    def read(k: int) -> np.ndarray:
        _, _, name, lineno = plan[k]
        image = root / image_path(name)
        array = _load_image(image, descriptor, lineno, (height, width))
        if array.shape != (height, width):
            raise DataFormatError(
                f"line {lineno}: image {image} is {array.shape} but the 'n' line says "
                f"{height} rows x {width} columns (single channel); fix the 'n' line or the "
                "image", path=descriptor)
        if not np.issubdtype(array.dtype, np.integer) or array.dtype.itemsize > dtype.itemsize:
            raise DataFormatError(
                f"line {lineno}: image {image} has dtype {array.dtype}, which does not fit a "
                f"{bits}-bit measurement; fix the bit depth on the 'n' line", path=descriptor)
        if int(array.max()) > full_scale:
            raise DataFormatError(
                f"line {lineno}: image {image} has values up to {int(array.max())} DN, above "
                f"the {bits}-bit full scale {full_scale} DN; fix the bit depth on the 'n' line",
                path=descriptor)
        return array.astype(dtype, copy=False)

    step_ids = np.array([p[0] for p in plan], dtype=np.int64)
    read_ids = list(dict.fromkeys(step_ids.tolist()))
    layout = FileLayout(path=descriptor, format="emva1288", n_frames=len(plan),
                        shape=(height, width), dtype=dtype, read=read, strict=True)
    origin = "file (EMVA 1288 descriptor)"
    layout.give("exposure_ms", exposure_to_ms([p[1].exposure for p in plan], exposure_unit),
                origin)
    layout.give("kind", np.array([p[1].kind for p in plan], dtype=object), origin)
    layout.give("photons", np.array([p[1].photons for p in plan], dtype=np.float64), origin)
    layout.give("step", step_ids, origin)
    layout.give("bit_depth", bits, origin)
    layout.give("illumination", "", origin)
    layout.meta.update({
        "format": "emva1288",
        "version": header["version"],
        "comments": header["comments"],
        "descriptor": str(descriptor),
        "exposure_unit_in_descriptor": exposure_unit,
        "spatial_steps": [s for s in read_ids if s in spatial_all],
        "sweep_steps": [s for s in read_ids if s not in spatial_all],
        "image_files": [p[2] for p in plan],
    })
    return layout
