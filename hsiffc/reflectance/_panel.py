"""The white panel's reflectance factor per band: a number, per-band values, or a spectrum file
interpolated onto the bands' wavelengths."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, ParameterError

__all__ = ["read_panel_spectrum", "panel_per_band"]

#: a panel's reflectance factor above this is refused (no diffuse panel reflects 150 %; a
#: value like 99 means the file or option gives percent)
MAX_PANEL = 1.5
_SPLIT = re.compile(r"[,;\s]+")


def read_panel_spectrum(path) -> tuple[np.ndarray, np.ndarray, str]:
    """Read a panel's reflectance spectrum: two columns, wavelength (nm) and reflectance factor.

    Columns are separated by commas, semicolons, tabs or spaces; lines starting with ``#`` and
    a header line of words are skipped. Values given in percent (every value above
    :data:`MAX_PANEL`, as vendors' certificates often print them) are divided by 100 and the
    returned note says so.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    wavelengths_nm : (N,) float64, increasing
    reflectance : (N,) float64, reflectance factor (1 = perfect diffuse reflector)
    note : str
        How the file was read (e.g. ``"percent, divided by 100"``), for the history.

    Raises
    ------
    DataFormatError
        Missing file, fewer than two rows, a row that is not two numbers, wavelengths not
        increasing, values not positive.
    """
    from ..files.atomic import require_regular_input
    from ..files.limits import default_limits

    path = Path(path)
    if not path.exists():
        raise DataFormatError("panel spectrum not found; give the panel's certificate as a "
                              "two-column file (wavelength in nm, reflectance)", path=path)
    st = require_regular_input(path, what="panel spectrum")  # a FIFO is never opened
    default_limits().check_header_bytes(path=path, nbytes=st.st_size, what="panel spectrum")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataFormatError("panel spectrum not found; give the panel's certificate as a "
                              "two-column file (wavelength in nm, reflectance)", path=path) from None
    except UnicodeDecodeError as exc:
        raise DataFormatError(f"not a text file ({exc.reason}); give the panel's spectrum as a "
                              "two-column CSV (wavelength in nm, reflectance)", path=path) from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c for c in _SPLIT.split(line) if c]
        try:
            values = [float(c) for c in cells]
        except ValueError:
            if not rows:  # a header line (e.g. "wavelength_nm,reflectance")
                continue
            raise DataFormatError(f"line {lineno} ({line!r}) is not two numbers; each line is "
                                  "wavelength (nm) and reflectance", path=path) from None
        if len(values) < 2 or not all(math.isfinite(v) for v in values[:2]):
            raise DataFormatError(f"line {lineno} ({line!r}) is not two finite numbers; each "
                                  "line is wavelength (nm) and reflectance", path=path)
        rows.append(values[:2])
    if len(rows) < 2:
        raise DataFormatError(f"{len(rows)} data row(s); a panel spectrum needs at least two "
                              "(wavelength in nm, reflectance) rows", path=path)
    wl, refl = np.array(rows, np.float64).T
    if np.any(np.diff(wl) <= 0):
        raise DataFormatError("wavelengths are not strictly increasing; sort the rows by "
                              "wavelength", path=path)
    note = "reflectance factor"
    if np.all(refl > MAX_PANEL):
        refl = refl / 100.0
        note = "percent, divided by 100"
    if np.any(refl <= 0) or np.any(refl > MAX_PANEL):
        raise DataFormatError(f"reflectance values from {refl.min():g} to {refl.max():g}; a "
                              f"panel's reflectance factor lies in (0, {MAX_PANEL:g}] (or give "
                              "all values in percent)", path=path)
    return wl, refl, note


def panel_per_band(panel, *, n_bands: int, wavelengths_nm=None, spectrum=None) -> np.ndarray:
    """The panel's reflectance factor for each band.

    Parameters
    ----------
    panel : float or sequence of float or None
        One value for every band, or one value per band (in band order).
    n_bands : int
    wavelengths_nm : sequence of float, optional
        Band centres (band order); needed with ``spectrum``.
    spectrum : (wavelengths_nm, reflectance), optional
        A spectrum (:func:`read_panel_spectrum`) interpolated linearly at the band centres;
        used when ``panel`` is None.

    Returns
    -------
    (n_bands,) float64

    Raises
    ------
    ParameterError
        No value, a value outside (0, 1.5], a wrong count, band wavelengths missing or outside
        the spectrum.

    Examples
    --------
    >>> panel_per_band(0.99, n_bands=3).tolist()
    [0.99, 0.99, 0.99]
    >>> panel_per_band(None, n_bands=2, wavelengths_nm=[500, 700],
    ...                spectrum=([400, 800], [0.9, 1.0])).round(3).tolist()
    [0.925, 0.975]
    """
    if panel is None and spectrum is None:
        raise ParameterError("reflectance: give the white panel's reflectance factor: panel= "
                             "(e.g. 0.99, or one value per band) or panel_file= (its spectrum)")
    if panel is not None:
        values = np.atleast_1d(np.asarray(panel, np.float64))
        if values.ndim != 1 or values.size not in (1, n_bands):
            raise ParameterError(f"reflectance: panel= has {values.size} values but the frames "
                                 f"have {n_bands} bands; give one value, or one per band")
        values = np.broadcast_to(values, (n_bands,)).copy()
    else:
        if wavelengths_nm is None:
            raise ParameterError("reflectance: panel_file= needs the bands' wavelengths, but the "
                                 "frames have none; give the mosaic with wavelengths (--mosaic "
                                 "with an IMEC XML) or panel= as one value per band")
        wl = np.asarray(wavelengths_nm, np.float64)
        sw, sr = (np.asarray(v, np.float64) for v in spectrum)
        outside = [f"{w:g}" for w in wl if not sw[0] <= w <= sw[-1]]
        if outside:
            raise ParameterError(f"reflectance: the panel spectrum covers {sw[0]:g}-{sw[-1]:g} "
                                 f"nm but band(s) at {', '.join(outside)} nm lie outside it; "
                                 "give a spectrum that covers every band")
        values = np.interp(wl, sw, sr)
    if not np.all(np.isfinite(values)) or np.any(values <= 0) or np.any(values > MAX_PANEL):
        raise ParameterError(f"reflectance: panel reflectance factor(s) {values.tolist()} must "
                             f"lie in (0, {MAX_PANEL:g}]: give 0.99, not 99 (percent)")
    return values
