"""Size limits checked from a file's header before any pixel is decoded.

A file's header states its frame size, frame count and sample type; hsiffc compares those
numbers with :class:`ReadLimits` *before* it decodes or allocates anything, so a small crafted
file that claims a huge image (a 9 KB deflate TIFF "of 32000 x 32000 pixels") is refused at once
with a one-line error instead of exhausting memory.

Defaults (each can be raised per call, ``open_source(..., limits=ReadLimits(...))``, or for a
whole process with an environment variable):

==========================  ====================  ========================================
limit                       default               environment variable
==========================  ====================  ========================================
pixels per frame            100 000 000 (100 MP)  ``HSIFFC_MAX_FRAME_PIXELS``
frames per input            1 000 000             ``HSIFFC_MAX_FRAMES``
bytes loaded at once        8 GiB                 ``HSIFFC_MAX_BYTES``
samples of a spectral grid  100 000               ``HSIFFC_MAX_SPECTRAL_SAMPLES``
bytes of a text header      16 MiB                ``HSIFFC_MAX_HEADER_BYTES``
==========================  ====================  ========================================

"Bytes loaded at once" is the decoded size of everything a command holds in memory together:
a whole sweep for ``info``/``calibrate``/``fit`` (:meth:`FrameSource.to_sweep`), a single frame
when frames are streamed (``hsiffc correct``). "Samples of a spectral grid" bounds the
wavelength grids a file declares (an IMEC sensor calibration's measurement range and step)
before arrays of that length are made: 100 000 samples is a 0.1 nm grid over 10 um. "Bytes of
a text header" bounds an ENVI header, checked from its ``stat`` before it is read (a sparse
3 GB ``.hdr`` is refused at once; a header with the wavelengths of 10 000 bands is ~100 KB).

Other files are checked from their headers against the same limits: the images an EMVA 1288
descriptor names (each must be the size its ``n`` line declares, read from the PNG or TIFF
header before decoding), the arrays of a calibration or pipeline file (their stored ``.npy``
headers, before they are inflated: :func:`check_npz_members`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from ..errors import DataFormatError

__all__ = ["ReadLimits", "default_limits"]

_ENV = {"max_frame_pixels": "HSIFFC_MAX_FRAME_PIXELS", "max_frames": "HSIFFC_MAX_FRAMES",
        "max_bytes": "HSIFFC_MAX_BYTES", "max_spectral_samples": "HSIFFC_MAX_SPECTRAL_SAMPLES",
        "max_header_bytes": "HSIFFC_MAX_HEADER_BYTES"}


@dataclass(frozen=True)
class ReadLimits:
    """Largest input hsiffc reads without being asked (see the module docstring).

    Parameters
    ----------
    max_frame_pixels : int
        Pixels per frame (H x W x channels).
    max_frames : int
        Frames in one input (a file, folder or glob).
    max_bytes : int
        Decoded bytes held in memory at once.
    max_spectral_samples : int
        Samples of a wavelength grid a file declares.
    max_header_bytes : int
        Bytes of a text header (ENVI ``.hdr``).

    Examples
    --------
    >>> import numpy as np, tempfile, tifffile
    >>> from pathlib import Path
    >>> from hsiffc.errors import DataFormatError
    >>> from hsiffc.io import ReadLimits, open_source
    >>> ReadLimits().max_frames
    1000000
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = Path(tmp.name) / "frames.tif"
    >>> tifffile.imwrite(path, np.zeros((3, 4, 6), np.uint16), photometric="minisblack")
    >>> try:
    ...     open_source(path, limits=ReadLimits(max_frames=2), exposure_ms=1.0, bit_depth=12)
    ... except DataFormatError as err:
    ...     print(str(err).split(": ", 1)[1].split(";")[0])
    the header states 3 frames, more than the limit of 2
    >>> tmp.cleanup()
    """

    max_frame_pixels: int = 100_000_000
    max_frames: int = 1_000_000
    max_bytes: int = 8 * 1024 ** 3
    max_spectral_samples: int = 100_000
    max_header_bytes: int = 16 * 1024 ** 2

    def check_header_bytes(self, *, path, nbytes: int, what: str) -> None:
        """Refuse a text header of more than ``max_header_bytes`` bytes (before reading it).

        Parameters
        ----------
        path : str or Path
            The header (for the message).
        nbytes : int
            Its size.
        what : str
            What it is, e.g. "ENVI header".

        Raises
        ------
        DataFormatError
            One line naming the file, its size, the limit and how to raise it.
        """
        if nbytes > self.max_header_bytes:
            raise DataFormatError(
                f"the {what} is {nbytes:,} bytes, more than the limit of "
                f"{self.max_header_bytes:,}; a genuine header is far smaller: check the file, or "
                f"raise the limit ({_ENV['max_header_bytes']}=...)", path=path)

    def check_spectral_samples(self, *, path, field: str, n: int) -> None:
        """Refuse a wavelength grid of more than ``max_spectral_samples`` samples.

        Parameters
        ----------
        path : str or Path
            The file (for the message).
        field : str
            The element or key that declares the grid (for the message).
        n : int
            Samples the grid would have.

        Raises
        ------
        DataFormatError
            One line naming the file, the field, the count, the limit and how to raise it.
        """
        if n > self.max_spectral_samples:
            raise DataFormatError(
                f"{field} declares a grid of {n:,} samples, more than the limit of "
                f"{self.max_spectral_samples:,}; correct the file, or if it is genuine raise the "
                f"limit ({_ENV['max_spectral_samples']}=...)", path=path)

    def check_frames(self, *, path, n_frames: int, shape, itemsize: int) -> None:
        """Refuse a header that states more than the limits allow (nothing decoded yet).

        Parameters
        ----------
        path : str or Path
            The file (for the message).
        n_frames : int
            Frames the header states.
        shape : tuple of int
            Stored shape of one frame.
        itemsize : int
            Bytes per sample.

        Raises
        ------
        DataFormatError
            One line naming the file, the stated size, the limit and how to raise it.
        """
        pixels = 1
        for s in shape:
            pixels *= int(s)
        dims = " x ".join(str(int(s)) for s in shape)
        if n_frames <= 0 and all(int(s) > 0 for s in shape):
            raise DataFormatError(f"the header states no frames ({n_frames} frames of {dims}); "
                                  "the file is empty or damaged", path=path)
        if any(int(s) <= 0 for s in shape):
            raise DataFormatError(f"the header states an empty or negative size ({n_frames} "
                                  f"frames of {dims}); the file is damaged", path=path)
        if pixels > self.max_frame_pixels:
            raise DataFormatError(
                f"the header states frames of {dims} = {pixels:,} pixels, more than the limit of "
                f"{self.max_frame_pixels:,}; if the file is genuine, raise the limit "
                f"({_ENV['max_frame_pixels']}=...)", path=path)
        if n_frames > self.max_frames:
            raise DataFormatError(
                f"the header states {n_frames:,} frames, more than the limit of "
                f"{self.max_frames:,}; if the file is genuine, raise the limit "
                f"({_ENV['max_frames']}=...)", path=path)
        self.check_bytes(path=path, nbytes=pixels * int(itemsize), what="one frame")

    def check_bytes(self, *, path, nbytes: int, what: str) -> None:
        """Refuse to hold ``nbytes`` decoded bytes in memory at once.

        Parameters
        ----------
        path : str or Path
            The input (for the message).
        nbytes : int
            Bytes that would be held.
        what : str
            What they are (for the message).

        Raises
        ------
        DataFormatError
            Over ``max_bytes``; the message says how to stream instead or raise the limit.
        """
        if nbytes > self.max_bytes:
            raise DataFormatError(
                f"{what} would take {nbytes / 1024 ** 3:.3g} GiB in memory, more than the limit "
                f"of {self.max_bytes / 1024 ** 3:.3g} GiB; read fewer frames, stream them "
                f"(hsiffc correct), or raise the limit ({_ENV['max_bytes']}=...)", path=path)


def default_limits() -> ReadLimits:
    """The limits in force: :class:`ReadLimits` defaults, raised by the environment variables.

    Returns
    -------
    ReadLimits

    Raises
    ------
    DataFormatError
        An environment variable that is not a number.

    Examples
    --------
    >>> import os
    >>> from unittest import mock
    >>> from hsiffc.io import default_limits
    >>> with mock.patch.dict(os.environ, {"HSIFFC_MAX_FRAMES": "5000000"}):
    ...     default_limits().max_frames
    5000000
    """
    values = {}
    for name, env in _ENV.items():
        text = os.environ.get(env)
        if text:
            try:
                values[name] = int(float(text))
            except ValueError:
                raise DataFormatError(f"environment variable {env}={text!r} is not a number; "
                                      "give a whole number") from None
    return ReadLimits(**values)
