"""Layout quirks of camera files, detected or clearly refused.

* **Equal channels.** A mono mosaic saved as a 3- or 4-channel image (RGB/RGBA with R = G = B,
  alpha constant): channel 0 is taken and a note says so. Channels that differ are a colour
  image, refused.
* **Left-aligned samples.** 10- or 12-bit data stored in the high bits of 16-bit words (every
  value a multiple of 64 or 16): detected from the values of the first frame (or forced with
  ``bit_shift``) and shifted right, so DN mean the ADC's counts. Later frames must have the
  low bits clear too, else the guess was wrong and reading stops with an error.
* **Bit depth from the dtype.** When no source states the bit depth, integer data are taken as
  using the full dtype (8 or 16 bits) with a :class:`LayoutWarning` that the full scale may be
  wrong.
* **Active area.** A mosaic from an IMEC XML covers a filter area offset on the sensor; frames
  of the full sensor are cropped to that area (the same crop for every frame, so calibrations
  and the frames they correct agree).
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import DataFormatError, HsiffcWarning

__all__ = ["LayoutWarning", "single_channel", "detect_left_aligned", "unshift",
           "infer_bit_depth"]


class LayoutWarning(HsiffcWarning):
    """A layout guess hsiffc made about a file (bit depth from the dtype, detected shift).

    Examples
    --------
    >>> import tempfile, warnings, numpy as np, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.io import LayoutWarning, open_source
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frames.tif"          # 16-bit words, no bit depth stated
    >>> tifffile.imwrite(path, np.full((2, 4, 6), 1001, np.uint16), photometric="minisblack")
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     with open_source(path, exposure_ms=1.0) as src:
    ...         bits = src.bit_depth
    >>> bits, [w.category.__name__ for w in caught]      # full scale taken from the dtype
    (16, ['LayoutWarning'])
    >>> tmp.cleanup()
    """


def single_channel(raw: np.ndarray, path, k: int, hint: str = "") -> np.ndarray:
    """Channel 0 of an (H, W, C) frame whose colour channels are equal; (H, W) unchanged.

    Parameters
    ----------
    raw : ndarray, (H, W) or (H, W, C)
        A decoded frame.
    path : str or Path
        Its file (for the message).
    k : int
        Its frame index (for the message).
    hint : str
        Extra advice appended to the message.

    Returns
    -------
    ndarray, (H, W)

    Raises
    ------
    DataFormatError
        Channels that differ (a colour image), or an unsupported shape.
    """
    if raw.ndim == 2:
        return raw
    if raw.ndim != 3 or raw.shape[2] not in (2, 3, 4):
        raise DataFormatError(f"frame {k} has shape {raw.shape}; hsiffc reads single-channel "
                              "(H, W) mosaic frames", path=path)
    colour = raw.shape[2] if raw.shape[2] != 2 else 1
    first = raw[..., 0]
    for c in range(1, colour if colour < 4 else 3):
        if not np.array_equal(first, raw[..., c]):
            raise DataFormatError(
                f"frame {k} is a colour image ({raw.shape[2]} channels that differ); hsiffc "
                "reads raw single-channel mosaic frames - save the camera's mono/raw output"
                + hint, path=path)
    if raw.shape[2] in (2, 4):  # the last channel is alpha: equal to the others or constant
        alpha = raw[..., -1]
        if not (np.array_equal(alpha, first) or np.all(alpha == alpha.flat[0])):
            raise DataFormatError(f"frame {k}: the alpha channel varies; hsiffc reads raw "
                                  "single-channel mosaic frames", path=path)
    return first


def detect_left_aligned(raw: np.ndarray, bit_depth: int | None) -> int:
    """Right shift (0 if none) that left-aligned 16-bit samples need, from one frame's values.

    With ``bit_depth`` known, the shift is ``16 - bit_depth`` when the values exceed the full
    scale and are all multiples of ``2**(16 - bit_depth)``. Without it, a frame whose non-zero
    values are all multiples of 4 or more (at least 2 spare low bits, at most 8) is taken as
    left-aligned by that many bits.

    Parameters
    ----------
    raw : ndarray
        One decoded frame (only uint16 can be left-aligned).
    bit_depth : int or None
        The stated bit depth, if known.

    Returns
    -------
    int
        Bits to shift right (0: none).
    """
    if raw.dtype != np.uint16 or raw.size == 0:
        return 0
    bits = int(np.bitwise_or.reduce(raw, axis=None))
    if bits == 0:
        return 0
    spare = (bits & -bits).bit_length() - 1
    if bit_depth is not None:
        shift = 16 - int(bit_depth)
        if 0 < shift <= spare and int(raw.max()) > 2 ** int(bit_depth) - 1:
            return shift
        return 0
    return spare if 2 <= spare <= 8 else 0


def unshift(raw: np.ndarray, shift: int, path, k: int) -> np.ndarray:
    """``raw >> shift``; an error if any of the dropped low bits is set.

    Parameters
    ----------
    raw : ndarray of unsigned int
        A decoded frame.
    shift : int
        Bits to shift right.
    path : str or Path
        Its file (for the message).
    k : int
        Its frame index (for the message).

    Returns
    -------
    ndarray, same shape and dtype

    Raises
    ------
    DataFormatError
        A dropped low bit is set (the samples are not left-aligned by ``shift``).
    """
    if not shift:
        return raw
    low = int(np.bitwise_or.reduce(raw & ((1 << shift) - 1), axis=None))
    if low:
        raise DataFormatError(
            f"frame {k} has values that are not multiples of {2 ** shift}, so its samples are not "
            f"left-aligned by {shift} bits; give the right --bit-shift (0 for none) and "
            "--bit-depth", path=path)
    return raw >> shift


def infer_bit_depth(dtype: np.dtype, path) -> int:
    """Bit depth of integer samples assumed from their dtype, with a :class:`LayoutWarning`.

    Parameters
    ----------
    dtype : numpy dtype
        Sample type.
    path : str or Path
        The file (for the warning).

    Returns
    -------
    int
        8 times the item size.
    """
    dtype = np.dtype(dtype)
    bits = 8 * dtype.itemsize
    warnings.warn(f"{path}: no bit depth given; assuming {bits} bits from the dtype {dtype} "
                  f"(full scale {2 ** bits - 1} DN), which may be wrong for a 10/12-bit camera: "
                  "give --bit-depth, bit_depth in the sidecar, or --bit-shift",
                  LayoutWarning, stacklevel=3)
    return bits


def active_area_crop(area, shape: tuple[int, int], label):
    """How frames of ``shape`` (H, W) are cropped to a mosaic's active area (an IMEC sensor's
    filter area, :class:`~hsiffc.io._metadata.ActiveArea`).

    Returns
    -------
    area : ActiveArea or None
        The crop to apply to every frame; None when there is none or the frames are already
        cropped to it.
    shape : (int, int)
        (H, W) of the frames after the crop.
    note : str
        What was done, for the source's notes ("" when nothing).

    Raises
    ------
    DataFormatError
        The frames do not contain the area (another sensor's XML).
    """
    h, w = shape
    if area is None or (h, w) == (area.height, area.width):
        return None, (h, w), ""
    rows = f"rows {area.row}..{area.row + area.height - 1}"
    cols = f"columns {area.col}..{area.col + area.width - 1}"
    if h < area.row + area.height or w < area.col + area.width:
        raise DataFormatError(f"frames of {h} x {w} px do not contain the mosaic's filter area "
                              f"({rows}, {cols}); give the matching sensor XML", path=label)
    return area, (area.height, area.width), (f"frames cropped to the mosaic's active area: "
                                             f"{rows}, {cols} (IMEC filter area)")
