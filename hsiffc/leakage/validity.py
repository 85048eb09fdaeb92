"""Leakage percentage maps, data-quality flags and training-set selection (paper IV.2).

Given a calibration, every response gets its leakage percentage alpha (eq. 4). The paper's rule
selects, per band, the longest candidate exposure whose alpha stays under a user threshold.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import model
from ..spectral.bandstats import STATISTICS as BAND_STATISTICS
from ..spectral.bandstats import band_layout, band_mean, band_reduce
from ..data.dq import DQ, DQ_DTYPE
from ..data.mosaic import band_numbers, wavelength_order
from ..kernels import leakage
from ..kernels.bands import block_arrays
from ..kernels.operands import flat_operands
from ..data.params import validate_method
from ..data.sweep import Sweep

STATISTICS = BAND_STATISTICS

#: "No alpha" (no light rate can be estimated: the signal is not positive) is ``+inf``
#: everywhere, always with the LEAKAGE bit. inf compares greater than every threshold and
#: survives the max-reductions of cube reconstruction, so such a pixel can never pass as valid;
#: NaN would fail every comparison (``NaN > threshold`` is False: it would pass as valid) and a
#: large finite stand-in is a magic number.
NO_ALPHA = np.inf


def alpha_paper(response, exposure_ms: float, a, b, dark) -> np.ndarray:
    """Leakage percentage of eq. (4) with k estimated as ``(Y - dark) / exposure`` (the paper).

    ``alpha = 100 a e^{bY} / ((Y - dark) / t)`` in percent, element-wise: the compiled kernel
    of :func:`hsiffc.leakage.model.leakage_percentage_paper` (double precision, rounded once to float32).

    Parameters
    ----------
    response : (H, W) array_like, DN
        Raw response Y (the leakage acts on it).
    exposure_ms : float, ms
    a : (H, W) array_like, DN/ms
    b : (H, W) array_like, 1/DN
    dark : float or (H, W) array_like, DN
        The dark under Y (0 gives the paper's literal ``Y / t``).

    Returns
    -------
    (H, W) float32, percent; :data:`NO_ALPHA` where the signal is not positive.

    Examples
    --------
    >>> alpha_paper(np.array([110.0, 5.0]), 10.0, 0.1, 0.0, np.array([10.0, 6.0])).tolist()
    [1.0, inf]
    """
    out = np.empty(np.broadcast_shapes(np.shape(response), np.shape(a), np.shape(b),
                                       np.shape(dark)), np.float32)
    return model.leakage_percentage_paper_into(out, response, exposure_ms, a, b, dark)


def alpha_model(response, exposure_ms: float, a, b, dark_dn, *, full_scale_dn=None,
                inversion=None) -> np.ndarray:
    """Leakage percentage of eq. (4) with k from inverting the calibrated model.

    Parameters
    ----------
    response : (H, W) array_like, DN
    exposure_ms : float, ms
    a, b, dark_dn : (H, W) array_like
        Leakage amplitude (DN/ms), exponent (1/DN) and dark level at zero exposure (DN).
    full_scale_dn : float, optional
    inversion : :class:`hsiffc.leakage.model.Inversion`, optional
        The result of :func:`hsiffc.leakage.model.invert_response` on these arguments, if already made.

    Returns
    -------
    (H, W) float32, percent; :data:`NO_ALPHA` where the response is below what zero light gives.
    """
    if inversion is None:
        inversion = model.invert_response(response, exposure_ms, np.asarray(a, np.float64),
                                          np.asarray(b, np.float64),
                                          np.asarray(dark_dn, np.float64),
                                          full_scale=full_scale_dn)
    alpha = model.leakage_percentage(response, np.maximum(inversion.k, 1e-300), a, b)
    return np.where(inversion.flags & int(DQ.BELOW_DARK), NO_ALPHA, alpha).astype(np.float32)


def _flags(alpha, response, exposure_ms, a, b, dark, *, threshold_percent, full_scale_dn,
           in_domain, pixel_flags, dq, extra_dq=None, with_signal=False, sums_by=None):
    """alpha (computed when ``alpha`` is None: paper form) and DQ in one compiled pass; with
    ``with_signal`` also ``response - dark`` (float32), returned first. ``sums_by``: a 2-D
    frame's ``(band_map, row_period > 0, n_bands)``, checked by the caller; then the
    :func:`~hsiffc.spectral.bandstats.band_reduce` mean of ``response`` over the pixels whose DQ is 0
    is returned last."""
    shape, (y, t, a_, b_, d) = flat_operands(
        response, exposure_ms, a, b, dark, names=("response", "exposure_ms", "a", "b", "dark"))
    def plane(v):
        if v is None:
            return None
        v = np.asarray(v)
        if v.shape != tuple(shape):
            raise ValueError(f"a DQ plane has shape {v.shape} but the frame has {tuple(shape)}")
        return np.ascontiguousarray(v, DQ_DTYPE).reshape(-1)

    given = (None if alpha is None
             else np.ascontiguousarray(np.broadcast_to(alpha, shape), np.float32).reshape(-1))
    alpha = np.empty(shape, np.float32) if given is None else None
    out = np.empty(shape, DQ_DTYPE)
    signal = np.empty(shape, np.float32) if with_signal else None
    const = 0 if in_domain else int(DQ.OUT_OF_DOMAIN)
    flat = (lambda v: None if v is None else v.reshape(-1))
    groups = (leakage.PixelModel(y, t, a_, b_, d),
              leakage.FlagRule(float(threshold_percent), float(full_scale_dn), const),
              leakage.FlagPlanes(plane(pixel_flags), plane(dq), plane(extra_dq)))
    if sums_by is None:
        leakage.alpha_flags_kernel(*groups, leakage.FlagOutputs(given, flat(alpha),
                                                                out.reshape(-1), flat(signal)))
        return (signal, alpha, out) if with_signal else (alpha, out)
    band_map, period, n_bands = sums_by
    sums, counts = block_arrays(shape[0], n_bands)
    leakage.alpha_flags_sums_kernel(
        *groups, leakage.FlagOutputs(None, flat(alpha), out.reshape(-1), flat(signal)),
        leakage.BandSums(band_map, period, sums, counts))
    return signal, alpha, out, band_mean(sums.sum(axis=0), counts.sum(axis=0))


def leakage_dq(alpha, response, *, threshold_percent: float, full_scale_dn: float,
               in_domain: bool = True, pixel_flags=None, dq=None) -> np.ndarray:
    """DQ bits of one frame from its alpha map (element-wise, one compiled pass).

    LEAKAGE where alpha is over ``threshold_percent`` or :data:`NO_ALPHA`; SATURATED where the
    response is at ``full_scale_dn``; OUT_OF_DOMAIN everywhere when not ``in_domain``; the
    calibration's own ``pixel_flags``; and the bits already in ``dq`` (the frame's DQ).

    Returns
    -------
    (H, W) uint32
    """
    return _flags(alpha, response, 1.0, 0.0, 1.0, 0.0, threshold_percent=threshold_percent,
                  full_scale_dn=full_scale_dn, in_domain=in_domain, pixel_flags=pixel_flags,
                  dq=dq)[1]


def alpha_map(frame, exposure_ms: float, calibration, *, method: str = "paper",
              subtract_dark: bool = True, dark=None) -> np.ndarray:
    """Per-pixel leakage percentage alpha (percent, float32) of one raw frame (DN).

    ``method="paper"``: :func:`alpha_paper` with ``dark`` when given (e.g. the master dark a
    stage removed), else the calibrated dark level and dark current at this exposure
    (``subtract_dark=False`` divides the raw response, literally as the paper writes it).
    ``method="model"``: :func:`alpha_model`. :data:`NO_ALPHA` where no light rate can be
    estimated.

    Parameters
    ----------
    frame : (H, W) array_like, DN
        Raw response.
    exposure_ms : float
        Exposure time (ms).
    calibration : Calibration or PreparedCalibration
        Supplies a (DN/ms), b (1/DN), the dark level (DN) and dark current (DN/ms) per pixel.
    method : str
        One of :data:`ALPHA_METHODS` ("paper", "model").
    subtract_dark : bool
        Paper method only: subtract the calibrated dark before dividing by the exposure.

    Returns
    -------
    (H, W) float32 ndarray, percent
    """
    how = validate_method(method, ALPHA_METHODS, "alpha method")
    cal = calibration
    y = np.asarray(frame, np.float32)
    cal.check_compatible(frame_shape=y.shape, what="the frame")
    return how.alpha(y, exposure_ms, cal, dark=dark, subtract_dark=subtract_dark)


def _paper_alpha(y, exposure_ms, cal, *, dark=None, subtract_dark=True):
    """The "paper" entry's alpha (see :func:`alpha_map`)."""
    prep = cal.prepare()
    if dark is None:
        dark = prep.dark_at(exposure_ms) if subtract_dark else 0.0
    return alpha_paper(y, exposure_ms, prep.a, prep.b, dark)


def _model_alpha(y, exposure_ms, cal, *, dark=None, subtract_dark=True):
    """The "model" entry's alpha (see :func:`alpha_map`; the calibrated dark, always)."""
    cal = getattr(cal, "calibration", cal)  # in float64: a prepared one's plain calibration
    return alpha_model(y, exposure_ms, cal.a, cal.b, cal.dark,
                       full_scale_dn=cal.domain.get("full_scale_dn"))


def _paper_flags(frame, exposure_ms, cal, *, dark, options):
    """The "paper" entry's alpha and DQ: one compiled pass."""
    y = np.asarray(frame, np.float32)
    cal.check_compatible(frame_shape=y.shape, what="the frame")
    prep = cal.prepare()
    return _flags(None, y, exposure_ms, prep.a, prep.b,
                  prep.dark_at(exposure_ms) if dark is None else dark, **options)


def _model_flags(frame, exposure_ms, cal, *, dark, options):
    """The "model" entry's alpha and DQ: the inversion, then :func:`leakage_dq`."""
    alpha = alpha_map(frame, exposure_ms, cal, method="model", dark=dark)
    return alpha, leakage_dq(alpha, frame, **options)


@dataclass(frozen=True)
class AlphaMethod:
    """A registered definition of the leakage percentage alpha (eq. 4).

    Attributes
    ----------
    summary : str
        How the method estimates the light rate k, in one line.
    alpha : callable
        ``alpha(y, exposure_ms, calibration, *, dark=None, subtract_dark=True)`` -> (H, W)
        float32 percent, ``y`` the frame as float32, already checked against the calibration
        (the body of :func:`alpha_map`).
    flags : callable
        ``flags(frame, exposure_ms, calibration, *, dark, options)`` -> ``(alpha, dq)``,
        ``options`` the DQ settings of :func:`leakage_dq` (the body of
        :func:`validity_flags`).
    one_pass : bool
        :func:`subtract_dark_and_flag` computes this alpha (in its one pass with the dark
        subtraction), so a fused front end can stand in for the alpha mask.
    """

    summary: str
    alpha: Callable
    flags: Callable
    one_pass: bool = False


#: Registered alpha methods: name -> :class:`AlphaMethod`.
#:
#: Adding a method: write its ``alpha`` and ``flags`` functions with the signatures of
#: :class:`AlphaMethod` and register them here; :func:`alpha_map`, :func:`validity_flags`,
#: :func:`alpha_table_of` and the ``alpha_mask`` stage then take its name (looked up with
#: :func:`~hsiffc.data.params.validate_method`: an unknown name is one line listing these).
ALPHA_METHODS = {
    "paper": AlphaMethod("k = (Y - dark) / t, as the paper estimates it (eq. 4)", _paper_alpha,
                         _paper_flags, one_pass=True),
    "model": AlphaMethod("k from inverting the calibrated model dY/dt = k - a e^{bY}",
                         _model_alpha, _model_flags),
}


class AlphaFlags(NamedTuple):
    """What :func:`validity_flags` returns: ``alpha`` (H, W) float32 percent (:data:`NO_ALPHA`
    where not computable) and ``dq`` (H, W) uint32."""

    alpha: np.ndarray
    dq: np.ndarray


def validity_flags(frame, exposure_ms: float, calibration, *, threshold_percent: float,
                   method: str = "paper", dark=None, dq=None):
    """alpha map (:func:`alpha_map`) and DQ flags (:func:`leakage_dq`) of one raw frame.

    Parameters
    ----------
    frame : (H, W) array_like, DN
    exposure_ms : float
    calibration : Calibration or PreparedCalibration
    threshold_percent : float
        alpha above this (percent) is flagged LEAKAGE.
    method : str
        One of :data:`ALPHA_METHODS` ("paper", "model").
    dark : float or (H, W) array_like, DN, optional
        See :func:`alpha_map`.
    dq : (H, W) uint32, optional
        The frame's DQ so far; its bits are kept in the returned plane (merged in the same
        pass).

    Returns
    -------
    AlphaFlags
        ``(alpha, dq)``: alpha (H, W) float32 percent (:data:`NO_ALPHA` where not computable),
        dq (H, W) uint32.
    """
    opts = _options(calibration, exposure_ms, threshold_percent, dq)
    how = validate_method(method, ALPHA_METHODS, "alpha method")
    return AlphaFlags(*how.flags(frame, exposure_ms, calibration, dark=dark, options=opts))


def _options(cal, exposure_ms, threshold_percent, dq) -> dict:
    return {"threshold_percent": threshold_percent, "full_scale_dn": cal.domain["full_scale_dn"],
            "in_domain": bool(cal.in_domain(exposure_ms)),
            "pixel_flags": cal.flags, "dq": dq}


class DarkFlagged(NamedTuple):
    """What :func:`subtract_dark_and_flag` returns.

    Attributes
    ----------
    signal : (H, W) float32, DN
        ``frame - dark``, nothing clipped.
    alpha : (H, W) float32, percent
    dq : (H, W) uint32
    band_mean : (n_bands,) float64, DN, or None
        The per-band mean of the frame over the pixels whose ``dq`` is 0 (NaN for a band
        without one); None unless a ``band_map`` with a known row period was given.
    """

    signal: np.ndarray
    alpha: np.ndarray
    dq: np.ndarray
    band_mean: np.ndarray | None


def subtract_dark_and_flag(frame, dark, exposure_ms: float, calibration, *,
                           threshold_percent: float, dq=None, extra_dq=None, band_map=None,
                           n_bands: int | None = None) -> DarkFlagged:
    """:func:`hsiffc.data.dark.subtract_dark` and :func:`validity_flags` (paper alpha, on the
    response ``frame`` with this ``dark`` under it) in one compiled pass over the pixels
    instead of two: the same values, bit for bit, as the two calls, with the planes read
    once.

    Parameters
    ----------
    frame : (H, W) array_like, DN
        Raw response.
    dark : (H, W) array_like, DN
        The dark to subtract, also the dark under the response for alpha.
    exposure_ms, calibration, threshold_percent, dq
        As for :func:`validity_flags`.
    extra_dq : (H, W) uint32, optional
        More bits to merge into the returned DQ (e.g. a flat field's own flags). A plane that
        does not change is better merged once into a prepared calibration's flags
        (:meth:`hsiffc.calibrate.prepared.PreparedCalibration.with_flags`, as a pipeline's
        fused front end does): the pass then reads one flag plane for both.
    band_map : (H, W) int array, optional
        A mosaic's band map (:meth:`hsiffc.data.mosaic.Mosaic.band_map`, whose row period is
        known): the same pass then also takes the per-band mean of ``frame`` over the pixels
        whose returned DQ is 0, as :func:`hsiffc.spectral.bandstats.band_reduce` gives it (bit for bit:
        the same sums in the same order). ``n_bands``: its length (default: the map's).

    Returns
    -------
    DarkFlagged
        ``(signal, alpha, dq, band_mean)``; ``band_mean`` is None unless ``band_map`` is given
        and its row period is known.
    """
    cal = calibration
    y = np.asarray(frame, np.float32)
    if y.ndim != 2 or np.shape(dark) != y.shape:
        raise ValueError(f"dark has shape {np.shape(dark)} but the frame has {y.shape}; use a "
                         "dark of the frame's shape")
    cal.check_compatible(frame_shape=y.shape, what="the frame")
    sums_by = None
    if band_map is not None:  # band_layout checks the map's shape: the kernel indexes it
        bm, period, n = band_layout(y, band_map, what="the frame")
        sums_by = (np.ascontiguousarray(bm, np.int64), period,
                   n if n_bands is None else int(n_bands)) if period else None
    prep = cal.prepare()
    options = _options(prep, exposure_ms, threshold_percent, dq)
    out = _flags(None, y, exposure_ms, prep.a, prep.b, dark,
                 **options, extra_dq=extra_dq, with_signal=True, sums_by=sums_by)
    return DarkFlagged(*out) if sums_by is not None else DarkFlagged(*out, None)


@dataclass(frozen=True)
class AlphaTable:
    """alpha (percent) per band and candidate exposure, in the shape of the paper's Table I."""

    exposures_ms: np.ndarray  # (E,)
    alpha: np.ndarray  # (n_bands, E)
    wavelengths_nm: tuple | None
    statistic: str
    method: str
    threshold_percent: float | None = None
    selected_ms: np.ndarray | None = None  # (n_bands,), NaN where no candidate qualifies

    def select(self, threshold_percent: float) -> "AlphaTable":
        """The paper's rule: per band, the longest exposure with alpha under the threshold."""
        if not np.isfinite(threshold_percent) or threshold_percent <= 0:
            raise ValueError(f"threshold must be a positive percentage, got {threshold_percent}")
        ok = self.alpha < threshold_percent
        sel = np.full(self.alpha.shape[0], np.nan)
        for i in range(self.alpha.shape[0]):
            idx = np.flatnonzero(ok[i])
            if idx.size:
                sel[i] = self.exposures_ms[idx].max()
        return AlphaTable(self.exposures_ms, self.alpha, self.wavelengths_nm, self.statistic,
                          self.method, float(threshold_percent), sel)

    def to_text(self) -> str:
        """Readable table; the selected exposure of each band is marked with brackets."""
        head = f"{'band':>6} {'nm':>6} " + " ".join(f"{e:>9.4g}ms" for e in self.exposures_ms)
        lines = [f"leakage percentage alpha (%), {self.method} definition, {self.statistic} "
                 "over each band's pixels" + (f"; [selected] at threshold "
                                              f"{self.threshold_percent:g} %"
                                              if self.threshold_percent is not None else ""),
                 head]
        n = self.alpha.shape[0]
        number = band_numbers(n, self.wavelengths_nm or None)  # by wavelength, from 1
        for i in wavelength_order(n, self.wavelengths_nm or None):
            wl = self.wavelengths_nm[i] if self.wavelengths_nm else float("nan")
            cells = []
            for j, e in enumerate(self.exposures_ms):
                v = self.alpha[i, j]
                txt = f"{v:.2f}" if np.isfinite(v) else "inf"
                if self.selected_ms is not None and e == self.selected_ms[i]:
                    txt = f"[{txt}]"
                cells.append(f"{txt:>11}")
            lines.append(f"{number[i]:>6} {wl:>6.0f} " + " ".join(cells))
        if self.selected_ms is not None and np.isnan(self.selected_ms).any():
            miss = [str(k) for k in sorted(number[i]
                                           for i in np.flatnonzero(np.isnan(self.selected_ms)))]
            lines.append(f"no candidate under the threshold for band(s) {', '.join(miss)}: "
                         "record shorter exposures or raise the threshold")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-safe dict (lists, NaN as None where needed); :meth:`from_dict` inverts it."""
        return {"exposures_ms": self.exposures_ms.tolist(),
                "alpha_percent": [[v if np.isfinite(v) else None for v in row]
                                  for row in self.alpha.tolist()],
                "wavelengths_nm": list(self.wavelengths_nm) if self.wavelengths_nm else None,
                "statistic": self.statistic, "method": self.method,
                "threshold_percent": self.threshold_percent,
                "selected_ms": None if self.selected_ms is None else
                [None if np.isnan(v) else float(v) for v in self.selected_ms]}


def alpha_table_of(responses, exposures_ms, calibration, *, darks=None, band_map=None,
                   method: str = "paper", statistic: str = "median",
                   wavelengths_nm=None) -> AlphaTable:
    """alpha per band of one averaged raw frame per exposure.

    Parameters
    ----------
    responses : (E, H, W) array_like, DN
        Raw response at each exposure (e.g. the mean of its frames).
    exposures_ms : (E,) array_like, ms
    calibration : Calibration or PreparedCalibration
    darks : (E, H, W) array_like, DN, optional
        The dark under each response (default: the calibrated dark at each exposure).
    band_map : (H, W) int array, optional
    method, statistic : see :func:`alpha_map` and :func:`hsiffc.spectral.bandstats.band_reduce`
    wavelengths_nm : sequence of float, optional

    Returns
    -------
    AlphaTable
        ``alpha`` (n_bands, E); a band without a finite alpha gets :data:`NO_ALPHA`.
    """
    validate_method(statistic, STATISTICS, "alpha statistic")
    exposures = np.asarray(exposures_ms, np.float64)
    columns = []
    for j, e in enumerate(exposures):
        alpha = alpha_map(responses[j], float(e), calibration, method=method,
                          dark=None if darks is None else darks[j])
        columns.append(band_reduce(alpha, band_map, statistic=statistic))
    table = np.stack(columns, axis=1)
    return AlphaTable(exposures, np.where(np.isnan(table), NO_ALPHA, table),
                      tuple(wavelengths_nm) if wavelengths_nm else None, statistic, method)


def alpha_table(sweep: Sweep, calibration, *, method: str = "paper",
                statistic: str = "median") -> AlphaTable:
    """alpha per band for every light exposure of ``sweep`` (frames of a step are averaged,
    like the paper's 10-frame training images).

    Parameters
    ----------
    sweep : Sweep
        Light frames at the candidate exposures (darks are ignored).
    calibration : Calibration or PreparedCalibration
        Of the same sensor (checked).
    method : str
        One of :data:`ALPHA_METHODS` ("paper", "model").
    statistic : "median" or another :func:`hsiffc.spectral.bandstats.band_reduce` statistic

    Returns
    -------
    AlphaTable
        ``alpha`` of shape (n_bands, n_exposures), percent; ``.select(12)`` applies the
        paper's rule (the longest exposure under the threshold, per band).
    """
    calibration.check_compatible(sweep)
    means = sweep.step_means()
    light = means["kind"] == "light"
    if not light.any():
        raise ValueError("the sweep has no light frames: nothing to select from")
    mosaic = sweep.mosaic or calibration.mosaic
    band_map = mosaic.band_map(sweep.frame_shape) if mosaic is not None else None
    exposures = np.unique(means["exposure_ms"][light])
    frames = np.stack([means["data"][light & (means["exposure_ms"] == e)].mean(axis=0)
                       for e in exposures])
    return alpha_table_of(frames, exposures, calibration, band_map=band_map, method=method,
                          statistic=statistic,
                          wavelengths_nm=mosaic.wavelengths_nm if mosaic else None)
