"""Leakage percentage maps, data-quality flags and training-set selection (paper IV.2).

Given a calibration, every response gets its leakage percentage alpha (eq. 4). The paper's rule
selects, per band, the longest candidate exposure whose alpha stays under a user threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import model
from .dq import DQ, DQ_DTYPE
from .sweep import Sweep

ALPHA_METHODS = ("paper", "model")
STATISTICS = ("median", "mean", "p95")


def alpha_map(frame, exposure_ms: float, calibration, *, method: str = "paper",
              subtract_dark: bool = True):
    """Per-pixel leakage percentage alpha (percent) of one frame (DN).

    ``method="paper"``: eq. (4) with k ~ signal / exposure, the signal being the response less
    the calibrated dark level and dark current (``subtract_dark=False`` divides the raw
    response, literally as the paper writes it). ``method="model"``: k from inverting the
    calibrated model at this exposure. Non-finite where no light rate can be estimated (signal
    not positive); :func:`validity_flags` turns those into flags.
    """
    if method not in ALPHA_METHODS:
        raise ValueError(f"method must be one of {ALPHA_METHODS}, got {method!r}")
    y = np.asarray(frame, np.float64)
    cal = calibration
    cal.check_compatible(frame_shape=y.shape, what="the frame")
    a, b = cal.a.astype(np.float64), cal.b.astype(np.float64)
    if method == "paper":
        dark = cal.dark + cal.dark_current * exposure_ms if subtract_dark else 0.0
        return model.leakage_percentage_paper(y, exposure_ms, a, b, dark)
    inv = model.invert_response(y, exposure_ms, a, b, cal.dark.astype(np.float64),
                                full_scale=cal.domain.get("full_scale_dn"))
    k_light = inv.k
    alpha = model.leakage_percentage(y, np.maximum(k_light, 1e-300), a, b)
    return np.where(inv.flags & int(DQ.BELOW_DARK), np.inf, alpha)


def validity_flags(frame, exposure_ms: float, calibration, *, threshold_percent: float,
                   method: str = "paper"):
    """alpha map and DQ flags of one frame.

    Flags: LEAKAGE where alpha exceeds ``threshold_percent`` (or cannot be computed because the
    signal is not positive), SATURATED where the frame is at full scale, OUT_OF_DOMAIN when the
    exposure lies outside the calibrated range, and the calibration's own per-pixel flags.
    """
    y = np.asarray(frame)
    alpha = alpha_map(y, exposure_ms, calibration, method=method)
    dq = np.zeros(y.shape, DQ_DTYPE)
    signal_ok = np.isfinite(alpha)
    dq[~signal_ok | (alpha > threshold_percent)] |= DQ_DTYPE(DQ.LEAKAGE)
    dq[y >= calibration.domain["full_scale_dn"]] |= DQ_DTYPE(DQ.SATURATED)
    if not calibration.in_domain(exposure_ms):
        dq |= DQ_DTYPE(DQ.OUT_OF_DOMAIN)
    if "flags" in calibration.arrays:
        dq |= calibration["flags"].astype(DQ_DTYPE)
    alpha = np.where(np.isfinite(alpha), alpha, np.inf).astype(np.float32)
    return alpha, dq


def _stat(values, statistic):
    v = values[np.isfinite(values)]
    if v.size == 0:
        return np.inf
    if statistic == "median":
        return float(np.median(v))
    if statistic == "mean":
        return float(np.mean(v))
    if statistic == "p95":
        return float(np.percentile(v, 95))
    raise ValueError(f"statistic must be one of {STATISTICS}, got {statistic!r}")


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
        for i in range(self.alpha.shape[0]):
            wl = self.wavelengths_nm[i] if self.wavelengths_nm else float("nan")
            cells = []
            for j, e in enumerate(self.exposures_ms):
                v = self.alpha[i, j]
                txt = f"{v:.2f}" if np.isfinite(v) else "inf"
                if self.selected_ms is not None and e == self.selected_ms[i]:
                    txt = f"[{txt}]"
                cells.append(f"{txt:>11}")
            lines.append(f"{i + 1:>6} {wl:>6.0f} " + " ".join(cells))
        if self.selected_ms is not None and np.isnan(self.selected_ms).any():
            miss = [str(i + 1) for i in np.flatnonzero(np.isnan(self.selected_ms))]
            lines.append(f"no candidate under the threshold for band(s) {', '.join(miss)}: "
                         "record shorter exposures or raise the threshold")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"exposures_ms": self.exposures_ms.tolist(),
                "alpha_percent": [[v if np.isfinite(v) else None for v in row]
                                  for row in self.alpha.tolist()],
                "wavelengths_nm": list(self.wavelengths_nm) if self.wavelengths_nm else None,
                "statistic": self.statistic, "method": self.method,
                "threshold_percent": self.threshold_percent,
                "selected_ms": None if self.selected_ms is None else
                [None if np.isnan(v) else float(v) for v in self.selected_ms]}


def alpha_table(sweep: Sweep, calibration, *, method: str = "paper",
                statistic: str = "median") -> AlphaTable:
    """alpha per band for every light exposure of ``sweep`` (frames of a step are averaged,
    like the paper's 10-frame training images)."""
    calibration.check_compatible(sweep)
    means = sweep.step_means()
    light = means["kind"] == "light"
    if not light.any():
        raise ValueError("the sweep has no light frames: nothing to select from")
    mosaic = sweep.mosaic or calibration.mosaic
    band_map = (mosaic.band_map(sweep.frame_shape) if mosaic is not None
                else np.zeros(sweep.frame_shape, int))
    n_bands = int(band_map.max()) + 1
    exposures = np.unique(means["exposure_ms"][light])
    table = np.empty((n_bands, exposures.size))
    for j, e in enumerate(exposures):
        sel = light & (means["exposure_ms"] == e)
        frame = means["data"][sel].mean(axis=0)
        alpha = alpha_map(frame, e, calibration, method=method)
        for band in range(n_bands):
            table[band, j] = _stat(alpha[band_map == band], statistic)
    return AlphaTable(exposures, table, mosaic.wavelengths_nm if mosaic else None,
                      statistic, method)
