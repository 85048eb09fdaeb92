"""Which response model a sensor keeps: chosen by held-out prediction inside the calibration.

A per-pixel fit has as many chances to follow noise as it has parameters. The leakage model
has four per pixel (responsivity g, leakage a and b, the dark level); on a sensor whose
response does not bend, or bends the same way in every pixel, a and b are not determined by
one pixel's samples, and a correction built on them adds a fixed pattern of their noise. So
the calibration compares candidate models on light steps their fit did not see, on every band
at once (each band's figures are recorded too), and keeps the simplest one that the held-out
steps do not show to be worse:

``two_point_stack``
    a linear response, each pixel's gain from the flat stack alone (the EMVA 1288 two-point
    correction; only where the calibration is given a flat stack);
``linear``
    a linear response through the dark frames' dark, each pixel's responsivity from its light
    steps (combined with the flat stack by inverse variance when there is one);
``pixel_leakage``
    the leakage model per pixel where the pixel's own samples earn it (the leakage fit's
    chi-square below the linear one's by more than the Bayesian information criterion's price
    of its two parameters, ``2 ln n``), the linear response elsewhere. A bend that the samples
    show earns it even where b alone is poorly determined (``sigma_ln_b``; a and b are
    strongly correlated, the dynamic saturation level they set is not): such pixels are
    flagged LEAK_UNCONSTRAINED.

Every candidate shares the dark (each pixel's dark frames) and the sensor's exposure offset.
The held-out score of a candidate is its corrected frames' fixed-pattern non-uniformity
(EMVA 1288: temporal noise removed; squared and relative to the signal) on each held-out
light step. A richer candidate replaces a simpler one where its mean over the held-out steps
is lower and it is higher in no range of signal (darkest 40 %, middle, brightest 20 % of the
held-out steps) beyond twice the standard error of the relative difference
``(new - old) / (new + old)``: what it adds must pay on steps it did not see, and must not
buy the top with the bottom. A sensor whose leakage is not measurable keeps a linear model
(the stack two-point, or the light steps combined with it: equal within noise); within the
leakage model, each pixel's a and b must also be earned by its own samples (below).

The comparison runs on a block of whole mosaic rows (up to :data:`MAX_PIXELS` pixels, the
middle of the sensor) with the sweep's light steps split in two by dose (every other step
held out); the kept model is then fitted on every step and every pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..data.dq import DQ
from ..data.mosaic import single_band_map
from ..flatfield.model_based import model_ffc_apply
from ..flatfield.model_based import FlatStack, model_flat_fit
from .flats import MIN_FLAT_FRAMES, flat_stack_steps
from .joint import B_GRID, MARGIN_GRID, run_kernel
from ..kernels.pixelfit import LEAKAGE, LINEAR_NOT_CONVERGED, LINEAR_WORSE, NO_FIT, TOO_FEW
from .samples import collect_samples, dark_level, dark_sigma, kernel_samples, linear_fit

__all__ = ["CANDIDATES", "CODES", "MAX_PIXELS", "FitSettings", "calibration_flags",
           "candidate_parameters", "choose_models", "held_out_split",
           "kept_codes"]

#: the candidate models, simplest first (code = position)
CANDIDATES = {
    "two_point_stack": "linear response, each pixel's gain from the flat stack alone",
    "linear": "linear response through the dark frames' dark, responsivity from the light "
              "steps (and the flat stack)",
    "pixel_leakage": "leakage model per pixel where the sweep determines a and b, linear "
                     "elsewhere",
}
#: pixels of the block the candidates are compared on
MAX_PIXELS = 16384
#: light steps the comparison needs (half of them held out)
MIN_LIGHT_STEPS = 6
#: a leakage pixel whose ln b has a larger 1-sigma error is not determined by the sweep
MAX_SIGMA_LN_B = 0.5
#: Levenberg-Marquardt iterations per pixel: with its dark held at the dark frames' a
#: strongly bent pixel can need more than the fit's default 200
MAX_ITER = 600
#: the chi-square a pixel's leakage fit must gain over its linear one, per ln(samples) (the
#: Bayesian information criterion's price of the two leakage parameters)
EARN_PER_LN_N = 2.0


@dataclass(frozen=True)
class FitSettings:
    """The sensor-wide choices of the joint fit, as the candidates are fitted with them."""

    ptc: object  #: PhotonTransfer or None
    full_well_dn: float | None
    use_dc: bool  #: per-pixel dark current from the dark frames
    dark_model: str  #: "in_well" or "additive"
    starts: tuple | None  #: (b start, margin) or None (grids)
    exposure_offset_ms: float
    fix_dark: bool  #: each pixel's dark level held at its dark frames' line

    def fit(self, smp):
        """The joint fit of a chunk of samples and their kernel arguments."""
        ks = kernel_samples(smp, self.ptc, exposure_offset_ms=self.exposure_offset_ms)
        fit = run_kernel(**ks, dark_current="estimate" if self.use_dc else None,
                         dark_model=self.dark_model,
                         b_start=self.starts[0] if self.starts else B_GRID,
                         margins=(self.starts[1],) if self.starts else MARGIN_GRID,
                         max_iter=MAX_ITER, fix_dark=self.fix_dark)
        return fit, ks


def fit_dark(fit, ks, settings: FitSettings) -> np.ndarray:
    """Each pixel's dark level (P,), DN: the dark frames'
    (:func:`~hsiffc.calibrate.samples.dark_level`) where the fit held it at them. The kernel
    holds it at that line (to 1e-13 DN) and returns it, so the line is computed here only for
    the pixels the kernel fitted nothing to (no light sample, no signal); the fit's own
    elsewhere."""
    if not settings.fix_dark:
        return fit.dark
    dark = fit.dark.copy()
    miss = np.flatnonzero(~np.isfinite(dark))
    if miss.size:
        frames = dark_level({**ks, "y": ks["y"][:, miss], "valid": ks["valid"][:, miss]},
                            np.asarray(fit.dark_current)[miss])
        dark[miss] = np.where(np.isfinite(frames), frames, dark[miss])
    return dark


def candidate_parameters(fit, ks, settings: FitSettings, code, *, earn: bool = True) -> dict:
    """Per-pixel parameters (P,) of the kept model ``code`` (P,) of :data:`CANDIDATES`: a, b,
    the dark level (:func:`fit_dark`), responsivity and its sigma, and which pixels use the
    linear response (``earn=False``: the leakage model wherever its fit converged, earned or
    not)."""
    dark = fit_dark(fit, ks, settings)
    code = np.broadcast_to(np.asarray(code), fit.g.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        earned = fit.chi2_linear - fit.chi2 > EARN_PER_LN_N * np.log(np.maximum(fit.n_valid, 2))
    leak = (code == _code("pixel_leakage")) & (fit.status == LEAKAGE) & (earned | (not earn))
    # the linear response, fitted where it is used (every pixel of a linear sensor, the
    # pixels of a leaky one that do not earn their leakage)
    need = np.flatnonzero(~leak)
    g_lin = np.full(fit.g.shape, np.nan)
    s_lin = np.full(fit.g.shape, np.inf)
    if need.size:
        sub = {**ks, "y": ks["y"][:, need], "valid": ks["valid"][:, need]}
        g_lin[need], s_lin[need] = linear_fit(sub, dark[need], fit.dark_current[need],
                                              exposure_offset_ms=settings.exposure_offset_ms)
    sigma_lin = np.where(code == _code("two_point_stack"), np.inf, s_lin)
    return {"a": np.where(leak, fit.a, 0.0), "b": fit.b, "linear": ~leak, "dark": dark,
            "responsivity": np.where(leak, fit.g, np.where(np.isfinite(g_lin), g_lin, fit.g)),
            "sigma_ln_g": np.where(leak, fit.sigma[:, 0], sigma_lin)}


#: candidate name -> its code in ``model_kept``
CODES = {name: i for i, name in enumerate(CANDIDATES)}


def calibration_flags(status, sigma_ln_b, leak_band) -> np.ndarray:
    """Calibration DQ. In a band that keeps the leakage model, NOT_CONVERGED marks a pixel
    whose leakage fit did not converge (its factor is not used: NO_FLAT downstream) and
    LEAK_UNCONSTRAINED one whose a and b the sweep does not pin (it is corrected as linear);
    a band that keeps a linear model has no leakage parameter to flag."""
    flags = np.zeros(status.shape, np.uint32)
    linear = (status == LINEAR_WORSE) | (status == LINEAR_NOT_CONVERGED)
    flags[leak_band & (status == LINEAR_NOT_CONVERGED)] |= np.uint32(DQ.NOT_CONVERGED)
    flags[leak_band & (linear | ~(sigma_ln_b < MAX_SIGMA_LN_B))] |= np.uint32(DQ.LEAK_UNCONSTRAINED)
    flags[np.isin(status, (TOO_FEW,) + NO_FIT)] |= np.uint32(DQ.DO_NOT_USE)
    return flags


def _code(name: str) -> int:
    return CODES[name]


def kept_codes(choice: dict | None, band_map) -> np.ndarray:
    """Per pixel, the code of the model its band keeps (``pixel_leakage`` without a choice)."""
    if not choice:
        return np.full(np.shape(band_map), _code("pixel_leakage"), np.int64)
    per_band = np.array([_code(b["kept"]) for b in choice["bands"]], np.int64)
    return per_band[np.asarray(band_map)]


def held_out_split(sweep) -> tuple[list, list, list]:
    """(fit light steps, held-out light steps, dark steps): the light steps with two or more
    frames ordered by dose (relative light rate x exposure), every other one held out."""
    steps = sweep.steps()
    first = np.array([np.flatnonzero(sweep.step == s)[0] for s in steps])
    n = np.array([(sweep.step == s).sum() for s in steps])
    kind = sweep.kind[first]
    photons = sweep.photons[first]
    dose = np.where(np.isfinite(photons), photons, sweep.exposure_ms[first])
    light = np.flatnonzero((kind == "light") & (n >= 2) & (sweep.exposure_ms[first] > 0))
    light = light[np.argsort(dose[light], kind="stable")]
    darks = [int(s) for s in steps[kind == "dark"]]
    return ([int(steps[i]) for i in light[0::2]], [int(steps[i]) for i in light[1::2]], darks)


def _block_rows(shape, tile_rows: int, max_pixels: int) -> slice:
    h, w = shape
    n = max(tile_rows, (max(max_pixels // w, 1) // tile_rows) * tile_rows)
    n = min(n, h - h % tile_rows if h >= tile_rows else h)
    r0 = ((h - n) // 2 // tile_rows) * tile_rows
    return slice(r0, r0 + n)


def _flat_stack(flats, rows, settings, dark, dark_current, fs):
    """The first flat stack of ``flats`` on ``rows`` (FlatStack), its dark the dark frames
    of its exposure where there are two or more, else the pixels' dark line."""
    if flats is None:
        return None
    for s in flat_stack_steps(flats, MIN_FLAT_FRAMES):
        sel = flats.step == s
        t = float(flats.exposure_ms[sel][0])
        frames = flats.data[sel][:, rows].astype(np.float64)
        darks = flats.data[(flats.kind == "dark")
                           & np.isclose(flats.exposure_ms, t, rtol=1e-6, atol=0.0)][:, rows]
        d = (darks.mean(axis=0) if len(darks) >= 2 else
             (dark + dark_current * t).reshape(frames.shape[1:]))
        return FlatStack.from_arrays(frames, t + settings.exposure_offset_ms, d,
                                     usable=(frames < fs).all(axis=0))
    return None


def _fpn2(corrected, good, band_map, n_bands):
    """Per band: relative fixed-pattern variance (temporal noise removed) of frames (N, H, W)
    over the ``good`` pixels, NaN where fewer than half of the band's pixels are good."""
    n = corrected.shape[0]
    m = corrected.mean(axis=0)
    v = corrected.var(axis=0, ddof=1)
    out = np.full(n_bands, np.nan)
    for band in range(n_bands):
        sel = band_map == band
        ok = good & sel
        if ok.sum() < max(10, 0.5 * sel.sum()):
            continue
        level = m[ok].mean()
        if not level > 0:
            continue
        out[band] = (m[ok].var(ddof=1) - v[ok].mean() / n) / level ** 2
    return out


def choose_models(sweep, settings: FitSettings, *, flats=None, max_pixels: int = MAX_PIXELS,
                  light_rate=None) -> dict | None:
    """Compare :data:`CANDIDATES` on held-out light steps; return the kept model per band.

    Parameters
    ----------
    sweep : Sweep
        The calibration sweep (light and dark steps).
    settings : FitSettings
        The joint fit's sensor-wide choices.
    flats : Sweep, optional
        Flat stacks (a light step of :data:`MIN_FLAT_FRAMES` or more frames) and dark frames
        at their exposure: ``two_point_stack`` is a candidate only with one.
    max_pixels : int
        Pixels of the block of whole mosaic rows the comparison runs on.
    light_rate : array_like, optional
        Given light rates: no comparison (their steps cannot be split here).

    Returns
    -------
    dict or None
        ``kept``: the sensor's model, chosen on every band's held-out steps at once, with its
        ``held_out_fpn_percent`` (every candidate) and ``predicted_fpn_percent``; ``bands``:
        per band the same ``kept`` model, ``held_out_fpn_percent`` of every candidate
        (root of the mean relative fixed-pattern variance over the held-out steps) and
        ``n_steps``, ``predicted_fpn_percent``: what the kept model's own errors (its
        factor's and its dark's) predict for the same steps, and ``held_out_over_predicted``
        (the median over the steps of the ratio of the two, see :func:`_figures`); ``rows``, ``fit_steps``,
        ``held_out_steps``, ``candidates``. None where the sweep has fewer than
        :data:`MIN_LIGHT_STEPS` light steps of two or more frames (every band then keeps
        ``pixel_leakage``).
    """
    fit_steps, held, darks = held_out_split(sweep)
    if light_rate is not None or len(fit_steps) + len(held) < MIN_LIGHT_STEPS or not darks:
        return None
    mosaic = sweep.mosaic
    tile_rows = mosaic.tile_shape[0] if mosaic is not None else 1
    rows = _block_rows(sweep.frame_shape, tile_rows, max_pixels)
    full_map = (mosaic.band_map(sweep.frame_shape) if mosaic is not None
                else single_band_map(sweep.frame_shape))
    band_map = np.asarray(full_map[rows])
    n_bands = int(band_map.max()) + 1
    # the block's rows first (a view), then the fit steps' frames: copies the block only
    sub = replace(sweep, data=sweep.data[:, rows], mosaic=None, meta={}).select(
        np.isin(sweep.step, fit_steps + darks))
    fit, ks = settings.fit(collect_samples(sub, full_well_dn=settings.full_well_dn,
                                           dtype=np.float64))
    fs = sweep.full_scale_dn
    dark0 = fit_dark(fit, ks, settings)
    stack = _flat_stack(flats, rows, settings, dark0, fit.dark_current, fs)
    names = [c for c in CANDIDATES if stack is not None or c != "two_point_stack"]
    shape = band_map.shape
    params, gains = {}, {}
    for name in names:
        p = candidate_parameters(fit, ks, settings, _code(name))
        flags = calibration_flags(fit.status, fit.sigma[:, 2], np.full(fit.g.shape,
                                                                       name == "pixel_leakage"))
        flags[~np.isfinite(p["responsivity"])] |= np.uint32(DQ.DO_NOT_USE)
        mf = model_flat_fit(p["responsivity"].reshape(shape), p["sigma_ln_g"].reshape(shape),
                            p["a"].reshape(shape), p["b"].reshape(shape), band_map,
                            flags=flags.reshape(shape), flats=[stack] if stack else ())
        params[name], gains[name] = p, mf
    scores = {name: [] for name in names}
    predicted = {name: [] for name in names}
    levels = []  # per held-out step, each band's mean signal above dark (DN)
    sigma_dark = (fit.sigma[:, 3] if settings.fix_dark  # the kernel's: the dark frames'
                  else dark_sigma(ks, dark_current=settings.use_dc)).reshape(shape)
    dark0 = dark0.reshape(shape)
    dc = fit.dark_current.reshape(shape)
    for s in held:
        sel = sweep.step == s
        t = float(sweep.exposure_ms[sel][0])
        raw = sweep.data[sel][:, rows]
        good = (raw < fs).all(axis=0)
        for mf in gains.values():
            good &= mf.dq == 0
        dark_t = dark0 + dc * t
        above = raw.mean(axis=0) - dark_t
        levels.append([float(above[band_map == band].mean()) for band in range(n_bands)])
        out = {}
        for name in names:
            p, mf = params[name], gains[name]
            frames = []
            for frame in raw:
                corrected, dq, _ = model_ffc_apply(
                    frame, t + settings.exposure_offset_ms, p["a"].reshape(shape),
                    p["b"].reshape(shape), dark_t, mf.gain, gain_sweep=mf.gain_sweep,
                    full_scale_dn=fs)
                good &= dq == 0
                frames.append(corrected)
            out[name] = np.asarray(frames, np.float64)
        for name in names:
            scores[name].append(_fpn2(out[name], good, band_map, n_bands))
            predicted[name].append(_predicted2(gains[name], sigma_dark, out[name], good,
                                               band_map, n_bands))
    # the sensor's choice, on every band's steps at once (more steps than one band has: a
    # near tie in one band does not flip it); each band's own figures beside it
    scores = {n: np.asarray(v) for n, v in scores.items()}  # (held-out steps, bands)
    predicted = {n: np.asarray(v) for n, v in predicted.items()}
    levels = np.asarray(levels)
    kept = _choose(names, {n: v.ravel() for n, v in scores.items()},
                   (levels / np.nanmax(levels, axis=0, keepdims=True)).ravel())
    sensor = _figures({n: v.ravel() for n, v in scores.items()},
                      {n: v.ravel() for n, v in predicted.items()}, kept)
    bands = [{"band": band, **_figures({n: v[:, band] for n, v in scores.items()},
                                       {n: v[:, band] for n, v in predicted.items()}, kept)}
             for band in range(n_bands)]
    return {"kept": kept, "held_out_fpn_percent": sensor["held_out_fpn_percent"],
            "predicted_fpn_percent": sensor["predicted_fpn_percent"],
            "held_out_over_predicted": sensor["held_out_over_predicted"], "bands": bands,
            "rows": [rows.start, rows.stop], "fit_steps": fit_steps, "held_out_steps": held,
            "candidates": names}


def _predicted2(mf, sigma_dark, corrected, good, band_map, n_bands):
    """Per band: the relative fixed-pattern variance the calibration's own errors predict for
    frames (N, H, W) corrected by ``mf``: each pixel's factor error (``sigma_ln_gain``) and
    its dark's error through the factor, over its signal, averaged over the ``good`` pixels
    (leakage a and b add where they bend the response: not included)."""
    m = corrected.mean(axis=0)
    out = np.full(n_bands, np.nan)
    for band in range(n_bands):
        ok = good & (band_map == band)
        if ok.sum() < 10:
            continue
        level = m[ok].mean()
        if not level > 0:
            continue
        var = (mf.sigma_ln_gain[ok].astype(np.float64) ** 2
               + (sigma_dark[ok] * mf.gain[ok] / level) ** 2)
        out[band] = var[np.isfinite(var)].mean()
    return out


#: the held-out steps' ranges of signal, as fractions of the band's brightest held-out step
RANGES = (0.0, 0.4, 0.8)


def _choose(names, per, level) -> str:
    """The kept candidate: the simplest of ``names``, replaced by a richer one that predicts
    the held-out steps better and nowhere worse (:func:`_better`; the ranges of signal are
    :data:`RANGES` of ``level``, each step's signal relative to its band's brightest).
    ``per``: each candidate's relative fixed-pattern variance per step (NaN: not measured);
    with no step measured, ``pixel_leakage``."""
    ok = np.all([np.isfinite(v) for v in per.values()], axis=0)
    if not ok.any():
        return "pixel_leakage"
    kept = names[0]
    if ok.sum() >= 2:
        which = np.searchsorted(np.asarray(RANGES) * level[ok].max(), level[ok],
                                side="right") - 1
        for n in names[1:]:
            if _better(per[n][ok], per[kept][ok], which):
                kept = n
    return kept


def _figures(per, predicted, kept) -> dict:
    """The held-out figures of the steps every candidate measured: their number, each
    candidate's root mean relative fixed-pattern variance (percent), the ``kept`` one, what
    its own errors predict, and the median over the steps of the kept model's held-out
    fixed pattern over its prediction (``held_out_over_predicted``: near 1 where the
    calibration's errors explain what the correction leaves, well above 1 where the data
    show a pattern the model misses)."""
    ok = np.all([np.isfinite(v) for v in per.values()], axis=0)
    pred = predicted[kept][ok]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(np.maximum(per[kept][ok], 0.0) / pred)
    ratio = ratio[np.isfinite(ratio)]
    return {"n_steps": int(ok.sum()),
            "held_out_over_predicted": float(np.median(ratio)) if ratio.size else float("nan"),
            "held_out_fpn_percent": {n: float(100 * np.sqrt(max(v[ok].mean(), 0.0)))
                                     if ok.any() else float("nan") for n, v in per.items()},
            "kept": kept,
            "predicted_fpn_percent": (float(100 * np.sqrt(np.nanmean(pred)))
                                      if np.isfinite(pred).any() else float("nan"))}


def _better(new, old, which) -> bool:
    """Whether the held-out fixed-pattern variances ``new`` show a candidate better than the
    one with ``old`` (per step; ``which``: each step's range of signal): lower in their mean
    over the steps, and higher in no range beyond twice the standard error of the relative
    difference (:func:`_relative_difference`)."""
    if not (old.mean() > 0 and new.mean() < old.mean()):
        return False  # (below the noise on average: no pattern to improve on)
    rel = _relative_difference(new, old)
    for r in np.unique(which):
        x = rel[which == r]
        if x.size >= 2 and x.mean() > 2.0 * x.std(ddof=1) / np.sqrt(x.size):
            return False
    return True


def _relative_difference(new, old) -> np.ndarray:
    """Per step, ``(new - old) / (new + old)`` of two fixed-pattern variances (in [-1, 1]:
    each step counts alike, whatever its level; 0 where neither is above the noise)."""
    new, old = np.maximum(new, 0.0), np.maximum(old, 0.0)
    total = new + old
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(total > 0, (new - old) / np.where(total > 0, total, 1.0), 0.0)
