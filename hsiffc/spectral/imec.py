"""Reader for IMEC snapshot-mosaic sensor calibration files (``<sensor_calibration>`` XML).

What the file holds and how it is interpreted (checked on CMV2K-SSM5x5-600_875-5.5.9.2.xml):

* ``bands/band`` (one per mosaic position, attribute ``pattern_position_index`` p, position
  row ``p // pattern_width``, column ``p % pattern_width``): ``peaks/peak`` (wavelength_nm,
  fwhm_nm, QE, attribute ``order``), ``response_composition`` and ``response_decomposition``
  (``nr_elements`` samples on the calibration grid, 400-1000 nm at 1 nm).
* ``response_composition`` is the band's response WITHOUT the rejection (band-pass) filter, on
  the same percent scale as the peaks' ``QE``: ``max(composition * rejection)`` equals the peak
  ``QE`` to 4 digits for every band, while the composition alone is ~1.1 at 400 nm where the
  rejection filter blocks. The band responses are therefore ``composition * rejection / 100``.
  The vendor's "QE" reaches 146 on this file, so it is not an absolute quantum efficiency in
  percent; treat the scale as relative (``max_qe`` rescales it).
* ``response_decomposition`` is the dual basis of the filtered responses:
  ``decomposition @ responses.T`` is the identity (to ~2 %).
* ``spectral_correction_info/virtual_bands/band``: ``wavelength_nm`` and a
  ``custom_spectral_correction`` row of ``n_bands`` coefficients. Stacked they form a matrix
  ``C`` (n_virtual, n_bands) whose COLUMNS ARE INDEXED BY PATTERN POSITION:
  ``virtual = C @ b`` for a vector ``b`` of band signals ordered by ``pattern_position_index``.
  With that ordering ``C @ responses`` peaks within 1 nm of every stated virtual wavelength;
  with bands ordered by wavelength it does not.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import DataFormatError
from ..data.mosaic import Mosaic
from .grid import readonly
from .bands import BandSet

#: Pixel pitch of the CMOSIS/ams CMV2000 (its datasheet value); the XML's pixel_pitch is 0.
CMV2000_PIXEL_PITCH_UM = 5.5


class FilterArea(NamedTuple):
    """The part of the sensor covered by the filter mosaic (pixels)."""
    offset_x: int
    offset_y: int
    width: int
    height: int


@dataclass(frozen=True)
class ImecPeak:
    """A peak of a band's response as reported by the vendor (``qe`` on the band set's scale)."""
    wavelength_nm: float
    fwhm_nm: float
    qe: float
    order: int


@dataclass(frozen=True, eq=False)
class ImecSensorCalibration:
    """Contents of an IMEC sensor calibration XML.

    Band-indexed arrays are ordered by ``pattern_position_index`` (band i sits at tile row
    ``i // pattern_shape[1]``, column ``i % pattern_shape[1]``).

    Attributes
    ----------
    bands : BandSet
        Responses as QE fraction including the rejection filter (vendor percent / 100, or
        rescaled by ``max_qe``); centres and FWHM from each band's order-1 peak.
    peaks : tuple (per band) of tuple of ImecPeak
    rejection_filter : (L,) transmission (fraction) on ``bands.wavelengths_nm``.
    virtual_wavelengths_nm : (n_virtual,)
    correction_matrix : (n_virtual, n_bands)
        Vendor spectral correction, ``virtual = correction_matrix @ b`` with ``b`` ordered by
        pattern position (see :meth:`correct`). Kept exactly as in the file.
    decomposition : (n_bands, L) or None
        Vendor ``response_decomposition`` rescaled so that ``decomposition @ bands.responses.T``
        is close to the identity.
    qe_scale : float
        Factor applied to the file's percent-scale values to get ``bands.responses``.
    """

    path: str
    width: int
    height: int
    input_bpp: int
    effective_bpp: int
    adc_gain: float | None
    pixel_pitch_um: float | None
    filter_area: FilterArea
    pattern_shape: tuple[int, int]
    bands: BandSet
    peaks: tuple
    rejection_filter: np.ndarray
    rejection_filter_type: str
    virtual_wavelengths_nm: np.ndarray
    virtual_fwhm_nm: float | None
    correction_matrix: np.ndarray
    decomposition: np.ndarray | None
    selected: tuple
    qe_scale: float

    @property
    def n_bands(self) -> int:
        return self.bands.n_bands

    def mosaic(self) -> Mosaic:
        """The mosaic layout: band i at tile position i (row-major), band centre wavelengths,
        and the filter-area offset as (row, col) = (offset_y, offset_x)."""
        ph, pw = self.pattern_shape
        return Mosaic(np.arange(ph * pw).reshape(ph, pw),
                      tuple(float(c) for c in self.bands.centres_nm),
                      (self.filter_area.offset_y, self.filter_area.offset_x),
                      name=f"IMEC {Path(self.path).stem}",
                      fwhm_nm=tuple(float(f) for f in self.bands.fwhm_nm))

    def correct(self, band_values, axis: int = -1) -> np.ndarray:
        """Apply the vendor correction to band signals along ``axis`` (n_bands long, ordered by
        pattern position); returns the same array with that axis of length n_virtual."""
        b = np.moveaxis(np.asarray(band_values, dtype=np.float64), axis, -1)
        if b.shape[-1] != self.n_bands:
            raise ValueError(f"expected {self.n_bands} band values along axis {axis}, "
                             f"got {b.shape[-1]}")
        return np.moveaxis(b @ self.correction_matrix.T, -1, axis)

    def virtual_responses(self) -> np.ndarray:
        """(n_virtual, L) ``correction_matrix @ bands.responses`` (scale follows ``qe_scale``)."""
        return self.correction_matrix @ self.bands.responses


# -- parsing helpers -------------------------------------------------------------------------------

class _Reader:
    def __init__(self, path: Path):
        self.path = path

    def fail(self, message: str):
        raise DataFormatError(message, path=self.path)

    def child(self, parent, tag: str, where: str):
        e = parent.find(tag)
        if e is None:
            self.fail(f"missing element <{where}/{tag}>; not a complete IMEC sensor calibration")
        return e

    def text(self, parent, tag: str, where: str) -> str:
        e = self.child(parent, tag, where)
        if e.text is None or not e.text.strip():
            self.fail(f"element <{where}/{tag}> is empty")
        return e.text.strip()

    def number(self, parent, tag: str, where: str, kind=float, *, positive: bool = False,
               nonnegative: bool = False):
        s = self.text(parent, tag, where)
        try:
            v = float(s)
        except ValueError:
            self.fail(f"element <{where}/{tag}> is not a number: {s!r}")
        if not np.isfinite(v):
            self.fail(f"element <{where}/{tag}> is not finite: {s!r}")
        if positive and v <= 0:
            self.fail(f"element <{where}/{tag}> must be > 0, got {s!r}")
        if nonnegative and v < 0:
            self.fail(f"element <{where}/{tag}> must be >= 0, got {s!r}")
        if kind is int:
            if v != round(v):
                self.fail(f"element <{where}/{tag}> must be an integer, got {s!r}")
            return int(round(v))
        return v

    def optional(self, parent, tag: str, where: str, kind=float, default=None):
        if parent is None or parent.find(tag) is None:
            return default
        return self.number(parent, tag, where, kind)

    def vector(self, elem, where: str, n_expected: int | None) -> np.ndarray:
        data = elem.find("data")
        if data is None or data.text is None:
            self.fail(f"missing <data> in <{where}>")
        try:
            v = np.array([float(x) for x in data.text.replace("\n", " ").split(",") if x.strip()])
        except ValueError:
            self.fail(f"<{where}/data> is not a comma-separated list of numbers")
        declared = elem.get("nr_elements")
        if declared is not None and declared.strip().isdecimal() and int(declared) != v.size:
            self.fail(f"<{where}> has {v.size} samples but declares nr_elements={declared}")
        if n_expected is not None and v.size != n_expected:
            self.fail(f"<{where}> has {v.size} samples, expected {n_expected}")
        if not np.all(np.isfinite(v)):
            self.fail(f"<{where}> contains non-finite values")
        return v


def _grid_count(start: float, end: float, step: float) -> int:
    """Samples of the grid start..end at step (a count past any limit when it overflows)."""
    ratio = (end - start) / step
    return int(round(ratio)) + 1 if np.isfinite(ratio) and abs(ratio) < 2 ** 62 else 2 ** 62


def read_imec_xml(path, *, max_qe: float | None = None) -> ImecSensorCalibration:
    """Read an IMEC sensor calibration XML (see the module docstring for the interpretation).

    Parameters
    ----------
    path : str or Path
    max_qe : float, optional
        If given, rescale all responses (and peak QEs) so the highest band response equals this
        fraction, e.g. an absolute peak QE taken from the sensor datasheet. By default the
        file's percent values are divided by 100, which is the vendor's relative scale (its
        maximum exceeds 1 on real files).

    Raises
    ------
    DataFormatError
        Naming the file and the missing or bad element: file missing, not XML, not a sensor
        calibration, missing element, wrong sample count, bad number.
    """
    p = Path(path)
    rd = _Reader(p)
    from ..files.atomic import require_regular_input

    if not p.exists():
        rd.fail("file not found (expected an IMEC sensor calibration .xml)")
    require_regular_input(p, what="IMEC sensor calibration")  # a FIFO would block
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        rd.fail(f"not a well-formed XML file ({exc})")
    except OSError as exc:
        rd.fail(f"cannot read the file ({exc})")
    if root.tag != "sensor_calibration":
        rd.fail(f"root element is <{root.tag}>, expected <sensor_calibration> "
                "(an IMEC sensor calibration file)")

    # sensor
    si = rd.child(root, "sensor_info", "sensor_calibration")
    w_s = "sensor_info"
    width = rd.number(si, "width", w_s, int)
    height = rd.number(si, "height", w_s, int)
    input_bpp = rd.number(si, "input_bpp", w_s, int)
    effective_bpp = rd.optional(si, "effective_bpp", w_s, int, input_bpp)
    adc_gain = rd.optional(si, "adc_gain", w_s, float)
    pitch = rd.optional(si, "pixel_pitch", w_s, float)
    pitch = pitch if pitch else None

    # filter layout
    fi = rd.child(root, "filter_info", "sensor_calibration")
    w_f = "filter_info"
    fa_e = rd.child(fi, "filter_area", w_f)
    w_fa = "filter_info/filter_area"
    fa = FilterArea(*(rd.number(fa_e, t, w_fa, int)
                      for t in ("offset_x", "offset_y", "width", "height")))
    if width < 1 or height < 1:
        rd.fail(f"<{w_s}/width> x <{w_s}/height> is {width} x {height}; a sensor is at least "
                "1 x 1 px")
    if (fa.offset_x < 0 or fa.offset_y < 0 or fa.width < 1 or fa.height < 1
            or fa.offset_x + fa.width > width or fa.offset_y + fa.height > height):
        rd.fail(f"<{w_fa}> (offset {fa.offset_x}, {fa.offset_y}, size {fa.width} x {fa.height}) "
                f"is not an area inside the {width} x {height} px sensor; offsets must be >= 0 "
                "and the size >= 1 px")
    pw = rd.number(fi, "pattern_width", w_f, int)
    ph = rd.number(fi, "pattern_height", w_f, int)
    if pw < 1 or ph < 1:
        rd.fail(f"pattern_width/pattern_height must be >= 1, got {pw} x {ph}")
    n_bands = pw * ph

    # wavelength grid of the measured responses
    ci = fi.find("calibration_info")
    w_ci = "filter_info/calibration_info"
    if ci is not None:
        start = rd.number(ci, "measurement_range_start_nm", w_ci)
        end = rd.number(ci, "measurement_range_end_nm", w_ci)
        step = rd.optional(ci, "measurement_resolution_nm", w_ci, float, 1.0)
    else:
        start = rd.number(fi, "spectral_range_start_nm", w_f)
        end = rd.number(fi, "spectral_range_end_nm", w_f)
        step = 1.0
    if step <= 0 or end <= start:
        rd.fail(f"bad measurement range {start:g}-{end:g} nm at {step:g} nm")
    n_samples = _grid_count(start, end, step)
    from ..files.limits import default_limits

    limits = default_limits()
    limits.check_spectral_samples(path=p, field=f"<{w_ci if ci is not None else w_f}> "
                                  f"({start:g}-{end:g} nm at {step:g} nm)", n=n_samples)
    declared = rd.optional(ci, "nr_measurements", w_ci, int)
    if declared is not None and declared != n_samples:
        rd.fail(f"<{w_ci}/nr_measurements> is {declared} but {start:g}-{end:g} nm at "
                f"{step:g} nm has {n_samples} samples")
    wl = start + step * np.arange(n_samples)

    # rejection (band-pass) filter
    rf = fi.find("rejection_filter")
    if rf is not None:
        w_rf = "filter_info/rejection_filter"
        r_start = rd.optional(rf, "wavelength_start_nm", w_rf, float, start)
        r_end = rd.optional(rf, "wavelength_end_nm", w_rf, float, end)
        r_step = rd.optional(rf, "wavelength_resolution_nm", w_rf, float, step)
        r_n = _grid_count(r_start, r_end, r_step) if r_step > 0 else 0
        limits.check_spectral_samples(path=p, field=f"<{w_rf}> ({r_start:g}-{r_end:g} nm at "
                                      f"{r_step:g} nm)", n=r_n)
        rej_raw = rd.vector(rd.child(rf, "filter_response", w_rf),
                            w_rf + "/filter_response", r_n)
        rej = np.interp(wl, r_start + r_step * np.arange(r_n), rej_raw, left=0.0, right=0.0)
        rej_type = (rf.findtext("type") or "").strip()
    else:
        rej, rej_type = np.ones_like(wl), ""

    # bands
    be = rd.child(fi, "bands", w_f)
    band_elems = be.findall("band")
    if len(band_elems) != n_bands:
        rd.fail(f"<filter_info/bands> has {len(band_elems)} <band> elements, expected "
                f"{n_bands} for a {ph} x {pw} pattern")
    by_pos: dict[int, ET.Element] = {}
    for i, b in enumerate(band_elems):
        s = b.get("pattern_position_index")
        if s is None or not s.strip().isdecimal():
            rd.fail(f"<bands/band> #{i} lacks a valid pattern_position_index attribute")
        pos = int(s)
        if pos >= n_bands or pos in by_pos:
            rd.fail(f"<bands/band> pattern_position_index={pos} is out of range or repeated "
                    f"(expected each of 0..{n_bands - 1} once)")
        by_pos[pos] = b

    comp = np.empty((n_bands, n_samples))
    decomp = np.empty((n_bands, n_samples))
    has_decomp = True
    raw_peaks = []
    selected = []
    for pos in range(n_bands):
        b = by_pos[pos]
        where = f"bands/band[@pattern_position_index='{pos}']"
        comp[pos] = rd.vector(rd.child(b, "response_composition", where),
                              where + "/response_composition", n_samples)
        de = b.find("response_decomposition")
        if de is None:
            has_decomp = False
        else:
            decomp[pos] = rd.vector(de, where + "/response_decomposition", n_samples)
        peak_elems = rd.child(b, "peaks", where).findall("peak")
        if not peak_elems:
            rd.fail(f"<{where}/peaks> has no <peak>")
        band_peaks = []
        for k, pe in enumerate(peak_elems):
            w_pk = f"{where}/peaks/peak[{k}]"
            order_s = pe.get("order", "1")
            try:
                order = int(order_s)
            except ValueError:
                rd.fail(f"<{w_pk}> has a bad order attribute {order_s!r}")
            band_peaks.append((rd.number(pe, "wavelength_nm", w_pk, positive=True),
                               rd.number(pe, "fwhm_nm", w_pk, nonnegative=True),
                               rd.number(pe, "QE", w_pk, nonnegative=True), order))
        raw_peaks.append(band_peaks)
        selected.append(b.get("selected", "true").strip().lower() != "false")

    responses_pct = comp * rej            # vendor percent scale, rejection filter included
    if max_qe is None:
        qe_scale = 0.01
    else:
        if not np.isfinite(max_qe) or max_qe <= 0:
            raise ValueError(f"max_qe must be a positive fraction, got {max_qe!r}")
        top = float(responses_pct.max())
        if top <= 0:
            rd.fail("band responses are all <= 0; cannot rescale to max_qe")
        qe_scale = float(max_qe) / top

    peaks = tuple(tuple(ImecPeak(w, f, q * qe_scale, o) for (w, f, q, o) in bp)
                  for bp in raw_peaks)
    centres, fwhms = [], []
    for bp in peaks:
        main = [pk for pk in bp if pk.order == 1] or list(bp)
        main = max(main, key=lambda pk: pk.qe)
        centres.append(main.wavelength_nm)
        fwhms.append(main.fwhm_nm)
    bands = BandSet(wl, responses_pct * qe_scale, centres, fwhms, name=f"IMEC {p.stem}")

    # virtual bands and vendor correction matrix
    sc = fi.find("spectral_correction_info")
    v_wl, v_rows, v_fwhm = [], [], None
    if sc is not None:
        w_sc = "filter_info/spectral_correction_info"
        v_fwhm = rd.optional(sc, "fwhm_virtual_filters_nm", w_sc, float)
        vb = sc.find("virtual_bands")
        for k, ve in enumerate([] if vb is None else vb.findall("band")):
            w_v = f"{w_sc}/virtual_bands/band[{k}]"
            v_wl.append(rd.number(ve, "wavelength_nm", w_v, positive=True))
            v_rows.append(rd.vector(rd.child(ve, "custom_spectral_correction", w_v),
                                    w_v + "/custom_spectral_correction", n_bands))
    correction = np.array(v_rows).reshape(len(v_rows), n_bands)

    return ImecSensorCalibration(
        path=str(p), width=width, height=height, input_bpp=input_bpp,
        effective_bpp=effective_bpp, adc_gain=adc_gain, pixel_pitch_um=pitch,
        filter_area=fa, pattern_shape=(ph, pw), bands=bands, peaks=peaks,
        rejection_filter=readonly(rej), rejection_filter_type=rej_type,
        virtual_wavelengths_nm=readonly(v_wl), virtual_fwhm_nm=v_fwhm,
        correction_matrix=readonly(correction),
        decomposition=readonly(decomp / qe_scale) if has_decomp else None,
        selected=tuple(selected), qe_scale=qe_scale)
