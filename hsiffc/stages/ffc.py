"""Flat-field correction stages: two-point (eq. 5) with alpha-selected training, polynomial."""

from __future__ import annotations

import warnings

import numpy as np

from ..dq import DQ, DQ_DTYPE
from ..errors import HsiffcWarning
from ..ffc import two_point_gain
from ..frame import stack_mean
from ..validity import AlphaTable
from .. import model
from ._common import (band_means, find_exposure, group_by_exposure, load_calibration,
                      raw_response)
from .base import Stage


def _signal(stack, darks_by_exposure, exposure, robust):
    """Mean flat signal (DN above dark) at one exposure and its DQ."""
    flat, dq = stack_mean(stack, robust=robust)
    if stack[0].meta.get("dark_subtracted"):
        return flat, dq, np.zeros_like(flat)
    e = find_exposure(darks_by_exposure, exposure)
    if e is None:
        raise ValueError(f"no dark frames at the flat exposure {exposure:g} ms; add darks at "
                         "that exposure or put a dark stage before this one")
    dark, ddq = stack_mean(darks_by_exposure[e], robust=robust)
    return flat - dark, dq | ddq, dark


class TwoPointFFC(Stage):
    """Two-point flat-field correction (the paper's eq. 5) trained at the exposure alpha selects.

    Parameters
    ----------
    exposure_ms : float, optional
        Train at this flat exposure for every band. Default: per band, the longest flat exposure
        whose median alpha stays under ``threshold_percent`` (the paper's improved method);
        that needs ``calibration``.
    calibration : path or Calibration, optional
    threshold_percent : float
    normalisation : "paper" or "mean_gain"
        ``"paper"``: ``Avg(L3) (R3 - R1) / (R2 - R1)`` per band (Avg over the test image's
        good pixels); ``"mean_gain"``: ``(R3 - R1) mean(R2 - R1) / (R2 - R1)`` (DN).
    average : "median" or "mean" (for the flat and dark stacks)
    """

    name = "two_point_ffc"

    def __init__(self, *, exposure_ms: float | None = None, calibration=None,
                 threshold_percent: float = 12.0, normalisation: str = "paper",
                 average: str = "median"):
        self.exposure_ms = exposure_ms
        self.calibration = calibration
        self.threshold_percent = threshold_percent
        self.normalisation = normalisation
        self.average = average

    def fit(self, frames):
        if self.normalisation not in ("paper", "mean_gain"):
            raise ValueError(f"normalisation must be 'paper' or 'mean_gain', got "
                             f"{self.normalisation!r}")
        flats = group_by_exposure(frames, "light")
        darks = group_by_exposure(frames, "dark")
        if not flats:
            raise ValueError("no flat (light) frames among the training frames")
        first = next(iter(flats.values()))[0]
        band_map = first.band_map()
        n_bands = int(band_map.max()) + 1
        robust = self.average == "median"
        if self.exposure_ms is not None:
            e = find_exposure(flats, float(self.exposure_ms))
            if e is None:
                raise ValueError(f"no flat frames at exposure_ms={self.exposure_ms:g}; "
                                 f"available: {list(flats)}")
            selected = [e] * n_bands
            table = None
        else:
            cal = load_calibration(self.calibration)
            if cal is None:
                raise ValueError("give exposure_ms= or calibration= (to select the training "
                                 "exposure per band by the leakage percentage)")
            table = self._alpha_table(flats, cal, band_map, n_bands)
            sel = table.select(self.threshold_percent).selected_ms
            fallback = min(flats)
            if np.isnan(sel).any():
                warnings.warn(f"no flat exposure has alpha under {self.threshold_percent:g} % "
                              f"in band(s) {list(np.flatnonzero(np.isnan(sel)) + 1)}; using the "
                              f"shortest, {fallback:g} ms", HsiffcWarning, stacklevel=2)
            selected = [fallback if np.isnan(s) else float(s) for s in sel]
        gain = np.ones(band_map.shape, np.float32)
        flat_mean = np.zeros(band_map.shape, np.float32)
        dark_used = np.zeros(band_map.shape, np.float32)
        dq = np.zeros(band_map.shape, DQ_DTYPE)
        for e in sorted(set(selected)):
            signal, sdq, dark = _signal(flats[e], darks, e, robust)
            bands = [i for i, s in enumerate(selected) if s == e]
            mask = np.isin(band_map, bands)
            g, gdq = two_point_gain(np.zeros_like(signal), signal, band_map=band_map)
            gain[mask] = g[mask]
            dq[mask] |= gdq[mask] | (sdq[mask] & DQ_DTYPE(DQ.SATURATED | DQ.DEAD | DQ.HOT))
            good = (gdq == 0)
            flat_mean[mask] = band_means(signal.astype(np.float64), band_map, good)[mask]
            dark_used[mask] = dark[mask]
        self.gain_ = gain
        self.flat_mean_ = flat_mean
        self.dark_ = dark_used
        self.dq_ = dq
        self.selected_ms_ = selected
        self.alpha_table_ = None if table is None else table.to_dict()
        self.fitted_ = True
        return self

    @staticmethod
    def _alpha_table(flats, cal, band_map, n_bands):
        exposures = np.array(list(flats))
        alpha = np.empty((n_bands, exposures.size))
        for j, e in enumerate(exposures):
            mean, _ = stack_mean(flats[e], robust=False)
            y = raw_response(flats[e][0].replace(data=mean), cal)
            a = model.leakage_percentage_paper(y, e, cal.a, cal.b, cal.dark + cal.dark_current * e)
            for b in range(n_bands):
                v = a[band_map == b]
                v = v[np.isfinite(v)]
                alpha[b, j] = np.median(v) if v.size else np.inf
        mosaic = flats[exposures[0]][0].mosaic
        return AlphaTable(exposures, alpha, mosaic.wavelengths_nm if mosaic else None, "median",
                          "paper")

    def transform(self, frame):
        self.check_is_fitted()
        if frame.data.shape != self.gain_.shape:
            raise ValueError(f"frame shape {frame.data.shape} differs from the flat's "
                             f"{self.gain_.shape}")
        signal = frame.data if frame.meta.get("dark_subtracted") else frame.data - self.dark_
        dq = frame.dq | self.dq_
        if self.normalisation == "mean_gain":
            out = signal * self.gain_
        else:
            band_map = frame.band_map()
            avg = band_means(frame.data.astype(np.float64), band_map, dq == 0)
            with np.errstate(invalid="ignore", divide="ignore"):
                out = avg * signal * self.gain_ / self.flat_mean_
            out = np.where(np.isfinite(out), out, 0.0)
        return frame.replace(data=out.astype(np.float32), dq=dq,
                             meta={"ffc": "two_point", "ffc_training_ms": self.selected_ms_})


class PolynomialFFC(Stage):
    """Per-pixel polynomial flat-field correction over several flat levels.

    For every pixel a polynomial of ``order`` maps its (dark-subtracted) response at each flat
    level to the band's mean response at that level (the response a uniform pixel would give),
    the family of the paper's reference [11]. Fitted by least squares for all pixels at once;
    applied to any level. Responses outside the pixel's trained range (with ``margin`` relative
    slack) are corrected by the polynomial's end tangent rather than extrapolated, and flagged
    OUT_OF_DOMAIN.

    Parameters
    ----------
    order : int (>= 1; needs order + 1 flat levels)
    margin : float
    average : "median" or "mean"
    """

    name = "polynomial_ffc"

    def __init__(self, *, order: int = 2, margin: float = 0.05, average: str = "median"):
        self.order = order
        self.margin = margin
        self.average = average

    def fit(self, frames):
        order = int(self.order)
        if order < 1:
            raise ValueError(f"order must be >= 1, got {self.order}")
        flats = group_by_exposure(frames, "light")
        darks = group_by_exposure(frames, "dark")
        # one level per (exposure, illumination)
        levels = {}
        for e, stack in flats.items():
            for f in stack:
                levels.setdefault((e, f.meta.get("illumination", "")), []).append(f)
        if len(levels) < order + 1:
            raise ValueError(f"a polynomial of order {order} needs at least {order + 1} flat "
                             f"levels; the training frames have {len(levels)}")
        band_map = next(iter(levels.values()))[0].band_map()
        xs, ys, dq = [], [], np.zeros(band_map.shape, DQ_DTYPE)
        for (e, _), stack in sorted(levels.items()):
            signal, sdq, _ = _signal(stack, darks, e, self.average == "median")
            xs.append(signal.astype(np.float64))
            ys.append(band_means(signal.astype(np.float64), band_map, sdq == 0))
            dq |= sdq & DQ_DTYPE(DQ.SATURATED)
        x = np.stack(xs)  # (L, H, W)
        y = np.stack(ys)
        scale = np.maximum(np.abs(x).max(axis=0), 1e-6)
        u = x / scale
        powers = np.stack([u ** j for j in range(order + 1)], axis=-1)  # (L, H, W, n)
        ata = np.einsum("lhwi,lhwj->hwij", powers, powers)
        atb = np.einsum("lhwi,lhw->hwi", powers, y)
        ata += 1e-12 * np.eye(order + 1)
        coef = np.linalg.solve(ata, atb[..., None])[..., 0]
        self.coef_ = np.moveaxis(coef, -1, 0).astype(np.float64)  # (n, H, W) in units of x/scale
        self.scale_ = scale.astype(np.float64)
        self.x_min_ = x.min(axis=0).astype(np.float32)
        self.x_max_ = x.max(axis=0).astype(np.float32)
        self.dq_ = dq
        self.n_levels_ = len(levels)
        # raw test frames get the master dark of their exposure subtracted first
        self.dark_exposures_ms_ = [float(e) for e in darks]
        if darks:
            self.dark_masters_ = np.stack([stack_mean(st, robust=self.average == "median")[0]
                                           for st in darks.values()])
        self.fitted_ = True
        return self

    def _poly(self, u):
        out = np.zeros_like(u)
        for c in self.coef_[::-1]:
            out = out * u + c
        return out

    def transform(self, frame):
        self.check_is_fitted()
        if frame.meta.get("dark_subtracted"):
            signal = frame.data
        else:
            e = find_exposure(self.dark_exposures_ms_, frame.exposure_ms)
            if e is None:
                raise ValueError(f"no training dark at {frame.exposure_ms:g} ms for this raw "
                                 "frame; put a dark stage before PolynomialFFC")
            signal = frame.data - self.dark_masters_[self.dark_exposures_ms_.index(e)]
        x = signal.astype(np.float64)
        span = self.x_max_ - self.x_min_
        lo = self.x_min_ - self.margin * span
        hi = self.x_max_ + self.margin * span
        outside = (x < lo) | (x > hi)
        xc = np.clip(x, lo, hi)
        u = xc / self.scale_
        out = self._poly(u)
        # beyond the domain continue along the end tangent (finite, monotone near the end)
        h = 1e-4
        slope = (self._poly(u + h) - self._poly(u - h)) / (2 * h) / self.scale_
        out = out + slope * (x - xc)
        dq = frame.dq | self.dq_
        dq[outside] |= DQ_DTYPE(DQ.OUT_OF_DOMAIN)
        out = np.where(np.isfinite(out), out, 0.0)
        return frame.replace(data=out.astype(np.float32), dq=dq,
                             meta={"ffc": f"polynomial order {int(self.order)}"})
