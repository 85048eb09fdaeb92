"""What a sweep's design allows diagnose to do: held-out split, dark model, noise, and which
candidate effects the design can identify.

Held-out design: with two or more frames in every step, the fit half is the first frame of each
step (frames 0, 2, ...) and the held-out half the other frames of the same step; with one frame
per step, alternate steps of each kind (light, dark) in acquisition order are held out, and the
model must predict steps it has not seen.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np

from ..calibrate.samples import collect_samples, photon_transfer, relative_light_rate
from ..errors import DataFormatError
from ..data.sweep import Sweep
from .bases import dark_current_from_darks

MIN_SEPARABLE = 0.02  # smallest fraction of an effect the base must leave separable


@dataclass
class Design:
    """Facts of a sweep's design that decide what can be fitted and identified.

    Made by :func:`describe`; the fields are commented in the class body: frame pairs in
    every step, how the held-out samples were made, counts of light and dark steps and of
    distinct exposures (ms) and light rates, whether light rates differ at equal signal (which
    separates leakage from a compressive readout), and notes.
    """

    pairs: bool  # two or more frames in every step
    held_out: str
    n_light_steps: int
    n_dark_steps: int
    light_exposures: int  # distinct exposures of usable light steps
    dark_exposures: int  # distinct exposures of dark steps
    light_rates: int  # distinct light rates (relative) of usable light steps
    exposures: int  # distinct exposures of all usable steps
    rate_at_equal_signal: bool  # light rates differ at equal signal (leakage vs compression)
    notes: list = field(default_factory=list)

    def as_dict(self) -> dict:
        """The fields as a plain dict (for the JSON result).

        Returns
        -------
        dict
        """
        return {k: v for k, v in self.__dict__.items()}


def subset(sweep: Sweep, max_pixels: int, seed: int):
    """A random subset of pixels as a (N, 1, P) sweep, with their rows, columns and band.

    Parameters
    ----------
    sweep : Sweep
        Frames (N, H, W).
    max_pixels : int
        Pixels to keep (all when the frame has fewer).
    seed : int
        Seed of the random choice.

    Returns
    -------
    sub : Sweep
        (N, 1, P), no mosaic.
    rows, cols, band : ndarray of int, (P,)
        Where each pixel was and its band (0 without a mosaic).
    """
    h, w = sweep.frame_shape
    n = h * w
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(n, size=min(n, max_pixels), replace=False))
    rr, cc = np.unravel_index(idx, (h, w))
    band = (sweep.mosaic.band_map((h, w))[rr, cc] if sweep.mosaic is not None
            else np.zeros(idx.size, int))
    sub = replace(sweep, data=np.ascontiguousarray(sweep.data[:, rr, cc])[:, None, :],
                  mosaic=None, meta={})
    return sub, rr, cc, band


CLIP_WIDTH_DN = 2  # values within this many DN of the highest count as one clip level
CLIP_BELOW_DN = 10  # ... against the values this many DN below them


def clip_level(sub: Sweep):
    """A hard clip below the ADC's full scale (a full well that fills before the ADC does):
    the lowest of the top ``CLIP_WIDTH_DN`` values of the light frames when the values pile up
    there (more of them than in the ``CLIP_BELOW_DN`` DN below, as a clip does and the smooth
    top of a response, dynamic saturation included, does not); None otherwise, for float data
    and where the highest value is the ADC's full scale (clipped there anyway).

    Parameters
    ----------
    sub : Sweep
        Raw frames (N, H, W) in DN.

    Returns
    -------
    float or None, DN
        Frame values at or above it are clipped.

    Examples
    --------
    >>> import numpy as np
    >>> from hsiffc.data.sweep import Sweep
    >>> rng = np.random.default_rng(0)
    >>> level = np.linspace(100, 4100, 20)[:, None, None]
    >>> frames = np.minimum(level + rng.normal(0, 5, (20, 1, 64)), 4001).round()
    >>> sweep = Sweep(frames.astype(np.uint16), exposure_ms=np.linspace(1, 20, 20),
    ...               kind=np.full(20, "light"), bit_depth=12, step=np.arange(20))
    >>> clip_level(sweep)
    4000.0
    """
    if not np.issubdtype(sub.data.dtype, np.integer):
        return None
    light = np.asarray(sub.kind) == "light"
    if not light.any():
        return None
    v = sub.data[light].reshape(-1)
    top = int(v.max())
    if top >= sub.full_scale_dn:
        return None
    near = int(np.count_nonzero(v > top - CLIP_WIDTH_DN))
    below = int(np.count_nonzero((v <= top - CLIP_WIDTH_DN)
                                 & (v > top - CLIP_WIDTH_DN - CLIP_BELOW_DN)))
    if near >= max(20, 0.001 * v.size) and near > below:
        return float(top - CLIP_WIDTH_DN + 1)
    return None


PLATEAU_SHOT_PART = 0.25  # a full well's frames hold at most this part of the shot variance
PLATEAU_MIN_SHOT = 2.0  # ... tested where the shot variance there is this many read variances
PLATEAU_MIN_PIXELS = 20  # pixels at the top that a plateau needs
PLATEAU_WIDTH = 0.02  # the top pixels: this fraction of the top level (+ 4 read noise) below it


def _step_stats(sub: Sweep, top_dn: float):
    """Per step: kind, pixel means and frame variances (S, P) in DN and DN^2, frames, and the
    pixels with a frame at ``top_dn``, at 0 DN of unsigned data or at a frame's highest code
    where more values sit there than in the 3 DN below (a clip, moved by an offset: their noise
    is cut off). The variance is that of each frame's deviations from the step's mean
    less a line in the pixels' means fitted across the pixels, frame by frame: a light or an
    offset that changes between the frames (flicker, lag, a clamp) moves every pixel by what
    follows its signal, and noise does not."""
    floor = 0.0 if np.issubdtype(sub.data.dtype, np.unsignedinteger) else -np.inf
    kind, mean, var, n, cut = [], [], [], [], []
    for s in sub.steps():
        x = sub.data[sub.step == s].reshape(np.count_nonzero(sub.step == s), -1)
        xf = x.astype(np.float64)
        m = xf.mean(axis=0)
        bad = np.any((xf >= top_dn) | (xf <= floor), axis=0)
        if np.issubdtype(x.dtype, np.integer):  # a clip of the frame, moved by an offset
            high = xf.max(axis=1, keepdims=True)
            at = xf == high
            under = (xf < high) & (xf >= high - 3)
            bad |= np.any(at & ((at.sum(axis=1) >= PLATEAU_MIN_PIXELS)
                                & (at.sum(axis=1) > under.sum(axis=1)))[:, None], axis=0)
        dev = xf - m
        a = np.stack([np.ones_like(m), m - m.mean()], axis=1)[~bad]
        if a.shape[0] > 2 and x.shape[0] > 1:
            coef = np.linalg.lstsq(a, dev[:, ~bad].T, rcond=None)[0]  # (2, frames)
            dev = dev - (coef[0][:, None] + coef[1][:, None] * (m - m.mean())[None, :])
        kind.append(sub.kind[np.flatnonzero(sub.step == s)[0]])
        mean.append(m)
        var.append((dev ** 2).sum(axis=0) / max(x.shape[0] - 1, 1))
        n.append(x.shape[0])
        cut.append(bad)
    return (np.array(kind), np.array(mean), np.array(var), np.array(n, float),
            np.array(cut))


def well_plateau(sub: Sweep, dose):
    """A full well that stops the response below the ADC's full scale with the read noise after
    it (so no pile-up at one code, :func:`clip_level`): the level that acts as full scale, or
    None.

    A full pixel drains the charge beyond its capacity, so its frames hold the read noise and
    no shot noise, and its level stays where it is as the light rises; a pixel that collects
    light (dynamic saturation of a leaky pixel included) keeps the shot noise of its signal.
    The pixels whose highest light sample (no frame cut off at full scale or 0 DN, 4 shot-noise
    sigma below full scale) lies within ``PLATEAU_WIDTH`` of the top level (its 99th percentile
    above each pixel's dark level; + 4 read-noise sigma) are tested together: where the shot
    noise there is ``PLATEAU_MIN_SHOT`` read variances or more and their pooled frame variance
    exceeds the read variance by less than ``PLATEAU_SHOT_PART`` of it, at least
    ``PLATEAU_MIN_PIXELS`` pixels, and where the pixels' two highest doses are both at the top,
    their level at the higher does not fall below that at the lower (by 4 standard errors of
    the mean over the pixels: a level that falls as the light rises is a clip moved by an
    offset, not a well), the plateau's level is their lowest sample less 3 read-noise sigma.
    Read variance and system gain come from the frame pairs (the darks, or the intercept of the
    photon-transfer line of the light steps below half the top level). Needs two frames in
    every step.

    Parameters
    ----------
    sub : Sweep
        Raw frames (N, H, W) in DN.
    dose : array_like, (S,)
        Light rate times exposure of each step (of ``sub.steps()``; any unit, NaN unknown).

    Returns
    -------
    dict or None
        ``level_dn`` (DN, with the dark level: samples at or above it count as clipped),
        ``read_dn2`` and ``shot_dn2`` (DN^2, the read and the shot variance at the level),
        ``plateau_dn2`` (the pooled frame variance of the top pixels) and ``pixels``.
    """
    fs = float(sub.full_scale_dn)
    kind, mean, var, n, cut = _step_stats(sub, fs)
    light = (kind == "light") & np.isfinite(np.asarray(dose, float))
    dark = kind == "dark"
    if light.sum() < 4 or n.min() < 2:
        return None
    ok = ~cut
    dark_dn = (np.median(mean[dark], axis=0) if dark.any() else mean[light].min(axis=0))
    level = np.where(ok, mean - dark_dn, np.nan)[light]  # (L, P) above dark
    step_level = np.array([np.mean(v[o]) if o.any() else np.nan
                           for v, o in zip(level, ok[light])])
    step_var = np.array([np.mean(v[o]) if o.any() else np.nan
                         for v, o in zip(var[light], ok[light])])
    if not np.isfinite(step_level).any():  # every light step cut off (clipped)
        return None
    low = np.isfinite(step_var) & (step_level < 0.5 * np.nanmax(step_level))
    if low.sum() < 3:
        return None
    gain, intercept = np.polyfit(step_level[low], step_var[low], 1)
    read = (float(np.median([np.mean(v[o]) for v, o in zip(var[dark], ok[dark]) if o.any()]))
            if dark.any() and ok[dark].any() else float(intercept))
    read = max(read, 1.0 / 12.0)
    if gain <= 0:
        return None
    shot_sd = np.sqrt(read + gain * np.maximum(np.nan_to_num(level), 0.0))
    usable = np.isfinite(level) & (mean[light] < fs - 4.0 * shot_sd)
    if not usable.any():
        return None
    cols = np.arange(level.shape[1])
    top_idx = np.argmax(np.where(usable, level, -np.inf), axis=0)  # (P,)
    has = usable.any(axis=0)
    top = level[top_idx, cols]
    band = float(np.percentile(top[has], 99)) * (1 - PLATEAU_WIDTH) - 4.0 * np.sqrt(read)
    group = has & (top >= band)
    if group.sum() < PLATEAU_MIN_PIXELS:
        return None
    n_l = n[light]
    dof = (n_l[top_idx] - 1.0)[group]
    pooled = float(np.sum(dof * var[light][top_idx, cols][group]) / np.sum(dof))
    shot = float(gain * np.mean(top[group]))
    if shot < PLATEAU_MIN_SHOT * read or pooled > read + PLATEAU_SHOT_PART * shot:
        return None
    # the two highest doses of each pixel (usable samples), where both are at the top
    u = np.asarray(dose, float)[light]
    by_dose = np.argsort(-np.where(usable, u[:, None], -np.inf), axis=0, kind="stable")
    hi, nxt = by_dose[0], by_dose[1]
    both = (group & usable[hi, cols] & usable[nxt, cols] & (u[hi] > u[nxt])
            & (level[hi, cols] >= band) & (level[nxt, cols] >= band))
    if both.sum() >= PLATEAU_MIN_PIXELS:
        rise = level[hi, cols][both] - level[nxt, cols][both]
        se = np.sqrt(read * np.mean(1.0 / n_l[hi][both] + 1.0 / n_l[nxt][both]) / both.sum())
        if rise.mean() < -4.0 * se:
            return None
    # below the lowest of them by 3 read-noise sigma: a frame of every full pixel reaches it
    level_dn = float(np.min(mean[light][top_idx, cols][group])) - 3.0 * np.sqrt(read)
    return {"level_dn": level_dn, "read_dn2": read,
            "shot_dn2": shot, "plateau_dn2": pooled, "pixels": int(group.sum())}


def step_dose(sub: Sweep) -> np.ndarray:
    """Relative light rate times exposure (ms) of every step of ``sub.steps()``; NaN for darks
    and steps of unknown rate.

    Parameters
    ----------
    sub : Sweep

    Returns
    -------
    ndarray, (S,)
    """
    first = np.array([np.flatnonzero(sub.step == s)[0] for s in sub.steps()])
    info = {"kind": np.asarray(sub.kind)[first], "photons": np.asarray(sub.photons)[first],
            "exposure_ms": np.asarray(sub.exposure_ms)[first],
            "illumination": np.asarray(sub.illumination).astype(str)[first]}
    rate, _ = relative_light_rate(info)
    dose = rate * info["exposure_ms"]
    return np.where((info["kind"] == "light") & (dose > 0), dose, np.nan)


def _pair_split(sweep: Sweep):
    fit_idx, ho_idx, gap = [], [], []
    for s in sweep.steps():
        sel = np.flatnonzero(sweep.step == s)
        fit_idx += sel[0::2].tolist()
        ho_idx += sel[1::2].tolist()
        gap.append(np.mean(np.arange(sel.size)[1::2]) - np.mean(np.arange(sel.size)[0::2]))
    return sweep.select(np.array(fit_idx)), sweep.select(np.array(ho_idx)), float(np.mean(gap))


def samples(sub: Sweep, full_well_dn=None):
    """Fit and held-out samples of a (pixel-subset) sweep.

    Parameters
    ----------
    sub : Sweep
        A pixel subset from :func:`subset`, (N, 1, P).
    full_well_dn : float, optional, DN
        Step means at or above it are not valid.

    Returns
    -------
    dict
        y, y_ho (P, S) DN, valid, valid_ho (P, S), t (ms), r, kind, step (S,), n_fit, n_ho
        (S,) frames per sample, pairs (bool), frame_gap, held_out (description), usable (S,),
        clip_dn (:func:`clip_level`, or the level of a full well's plateau, DN, or None),
        plateau (:func:`well_plateau`'s figures, or None).
    """
    counts = np.array([(sub.step == s).sum() for s in sub.steps()])
    pairs = bool(np.all(counts >= 2))
    clip = clip_level(sub)  # a step with a frame at the clip is not a valid sample
    # a full well below full scale with the read noise after it: its level acts as the clip
    plateau = well_plateau(sub, step_dose(sub)) if pairs and clip is None else None
    if plateau is not None:
        clip = plateau["level_dn"]
    # nor one with a frame at the ADC's lowest code: the noise below it is cut off
    floor = 0.0 if np.issubdtype(sub.data.dtype, np.unsignedinteger) else None
    if pairs:
        fit_sw, ho_sw, gap = _pair_split(sub)
        sf = collect_samples(fit_sw, full_well_dn=full_well_dn, clip_dn=clip, floor_dn=floor)
        sh = collect_samples(ho_sw, full_well_dn=full_well_dn, clip_dn=clip, floor_dn=floor)
        valid = (sf.valid & sh.valid).T
        out = dict(y=sf.y.T.astype(np.float64), y_ho=sh.y.T.astype(np.float64), valid=valid,
                   valid_ho=valid.copy(), n_fit=sf.n_frames, n_ho=sh.n_frames, frame_gap=gap,
                   held_out="second frame of every step (the first fits the model)")
    else:
        sf = collect_samples(sub, full_well_dn=full_well_dn, clip_dn=clip, floor_dn=floor)
        fit_col = np.zeros(len(sf.step), bool)
        for kind in ("light", "dark"):
            cols = np.flatnonzero((sf.kind == kind) & sf.usable_step)
            fit_col[cols[0::2]] = True
        valid = sf.valid.T
        y = sf.y.T.astype(np.float64)
        out = dict(y=y, y_ho=y, valid=valid & fit_col[None, :], valid_ho=valid & ~fit_col[None, :],
                   n_fit=sf.n_frames, n_ho=sf.n_frames, frame_gap=0.0,
                   held_out=("alternate steps of each kind in acquisition order (some steps have "
                             "one frame, so frame pairs cannot be held out)"))
    usable = sf.usable_step
    out.update(t=np.where(usable, sf.exposure_ms, 1.0),
               r=np.where(usable, np.nan_to_num(sf.rate), 0.0),
               kind=sf.kind, step=sf.step, usable=usable, pairs=pairs, clip_dn=clip,
               plateau=plateau)
    out["valid"] &= usable[None, :]
    out["valid_ho"] &= usable[None, :]
    return out


def describe(smp) -> Design:
    """The :class:`Design` of the samples from :func:`samples`.

    Parameters
    ----------
    smp : dict
        From :func:`samples`.

    Returns
    -------
    Design
    """
    light = (smp["kind"] == "light") & smp["usable"]
    dark = (smp["kind"] == "dark") & smp["usable"]
    t, r = smp["t"], smp["r"]
    # light rates that differ at equal signal: two light steps with about equal dose r t
    # (within 30 %) whose rates differ by more than 30 %
    u = r * t
    li = np.flatnonzero(light)
    equal = False
    for i in li:
        close = li[(np.abs(u[li] / u[i] - 1) < 0.3) & (u[li] > 0)]
        if close.size and np.any(np.abs(r[close] / r[i] - 1) > 0.3):
            equal = True
            break
    return Design(pairs=smp["pairs"], held_out=smp["held_out"], n_light_steps=int(light.sum()),
                  n_dark_steps=int(dark.sum()),
                  light_exposures=int(np.unique(t[light]).size),
                  dark_exposures=int(np.unique(t[dark]).size),
                  light_rates=int(np.unique(np.round(r[light], 12)).size),
                  exposures=int(np.unique(t[light | dark]).size),
                  rate_at_equal_signal=bool(equal))


def dark_model(y, t, r, valid, w, design: Design):
    """Whether the dark current is part of the base model, and why: only when the dark samples
    of the fit half span two exposures and the pixels as a whole show a dark current above the
    noise.

    Parameters
    ----------
    y : ndarray, (P, S), DN
        Fit samples.
    t : ndarray, (S,), ms
        Exposures.
    r : ndarray, (S,)
        Relative light rates (0 for darks).
    valid : ndarray of bool, (P, S)
        Samples to use.
    w : ndarray, (P, S)
        Weights.
    design : Design
        The sweep's design.

    Returns
    -------
    use : bool
        Whether the dark current is fitted.
    description : dict
        ``model`` and ``reason`` (and figures when measured).
    """
    if design.dark_exposures < 2:
        why = ("no dark frames" if design.n_dark_steps == 0 else
               "dark frames at one exposure only")
        return False, {"model": "constant dark level per pixel", "reason": why + ": a dark "
                       "current cannot be measured from them"}
    dc = dark_current_from_darks(y, t, r, valid, w)
    med = float(np.median(dc))
    se = float(1.4826 * np.median(np.abs(dc - med)) / np.sqrt(dc.size))
    if not med > 3 * se:
        return False, {"model": "constant dark level per pixel", "reason": (
            f"the dark frames at {design.dark_exposures} exposures show no dark current above "
            f"the noise (median {med:.3g} DN/ms, standard error {se:.2g})")}
    return True, {
        "model": "dark level + dark current per pixel (measured from the dark frames)",
        "n_dark_exposures": design.dark_exposures,
        "reason": (f"the dark frames at {design.dark_exposures} exposures grow with exposure "
                   f"({med / max(se, 1e-300):.0f} standard errors): the dark current is part of "
                   "the base model, added to the light rate and measured from the dark samples "
                   "less the selected effects")}


def describe_dark_current(dc, desc: dict) -> dict:
    """The dark-current figures of the final model added to the dark model's description.

    Parameters
    ----------
    dc : ndarray, (P,), DN/ms
        Fitted dark current per pixel.
    desc : dict
        From :func:`dark_model`.

    Returns
    -------
    dict
        ``desc`` plus median and robust spread of the dark current (DN/ms) when it is fitted
        (``..._dark_signal_...`` where the dark signal is collected outside the photodiode).
    """
    if "n_dark_exposures" not in desc:
        return desc
    med = float(np.median(dc))
    what = "current" if desc.get("leaks", True) else "signal"
    return {**desc, f"median_dark_{what}_dn_per_ms": med,
            f"spread_dark_{what}_dn_per_ms": float(1.4826 * np.median(np.abs(dc - med)))}


def structural_skip(name, design: Design, dark) -> str | None:
    """Why the design cannot identify effect ``name`` (None when it can, as far as the design
    alone tells; see also :func:`hsiffc.diagnose.fitting.separable_fraction`): the rules of its
    scope, then the effect's own (:attr:`hsiffc.diagnose.effects.Effect.skip`).

    Parameters
    ----------
    name : str
        Effect name (a key of :data:`hsiffc.diagnose.EFFECTS`).
    design : Design
        The sweep's design.
    dark : dict
        The dark model's description (:func:`dark_model`).

    Returns
    -------
    str or None
        The reason, in words.
    """
    from .effects import EFFECTS

    effect = EFFECTS[name]
    scope = effect.scope
    if scope in ("step", "frame") and not design.pairs:
        return ("one frame per step: a per-step error cannot be predicted for a held-out step "
                "(it needs two frames per step)")
    if scope == "pair" and not design.pairs:
        return "one frame per step: a change between the frames of a step cannot be seen"
    if scope in ("step", "frame") and design.n_light_steps < 3:
        return "fewer than 3 light steps"
    return effect.skip(design, dark)


WITHIN_STEP_P = 1e-6  # frame differences that follow the signal across pixels beyond this


def noise_pairs(smp, valid, with_test=False):
    """Temporal variance of one frame per step (S,), from the frame pairs, mean over pixels,
    after the differences are tested against the noise model and cleared of what is not noise.

    The differences between the halves of a step are noise only where the frames of a step are
    exchangeable. A light that changes from frame to frame (flicker, a drift within the step)
    moves every pixel of a step by an amount that follows its signal, and a lag from frame to
    frame by one that follows the signal of the step and of the step before: so per step the
    differences are regressed, across the pixels, on a constant, the pixel's mean over all the
    frames of the step and that of the step before (means over all frames are independent of
    the differences, so the regression takes no noise), and the variance is measured on the
    residual (corrected for the regressors' degrees of freedom). The regression's explained
    sums of squares, in units of that variance, are a chi-square under the noise model: their
    p-value over the steps is the test (``with_test``).

    Parameters
    ----------
    smp : dict
        From :func:`samples` (with frame pairs).
    valid : ndarray of bool, (P, S)
        Samples valid in both halves.
    with_test : bool
        Also return the test.

    Returns
    -------
    ndarray, (S,), DN^2
    dict, with ``with_test``
        ``raw_dn`` and ``clean_dn`` (RMS noise of one frame before and after the clearing,
        over the steps), ``chi2``, ``dof``, ``p_value`` and ``within_step`` (the differences
        hold more than noise).
    """
    y, y_ho = smp["y"], smp["y_ho"]
    nf, nh = smp["n_fit"][None, :], smp["n_ho"][None, :]
    scale = 1.0 / nf + 1.0 / nh
    d = y_ho - y
    m = (nf * y + nh * y_ho) / (nf + nh)
    by_order = np.argsort(smp["step"])
    prev = np.full(y.shape[1], -1)
    prev[by_order[1:]] = by_order[:-1]
    var = np.zeros(y.shape[1])
    raw = np.zeros(y.shape[1])
    chi2, dof = 0.0, 0
    for s in range(y.shape[1]):
        ok = valid[:, s]
        n = int(ok.sum())
        if n == 0:
            continue
        ds = d[ok, s]
        raw[s] = float(np.mean(ds ** 2)) / scale[0, s]
        cols = [np.ones(n), m[ok, s]]
        if prev[s] >= 0:
            cols.append(m[ok, prev[s]])
        a = np.column_stack([c for c in cols if np.ptp(c) > 0] or [np.ones(n)])
        if n < 4 * a.shape[1] + 10:  # too few pixels to clear: the raw differences
            var[s] = raw[s]
            continue
        a = (a - np.r_[0.0, a[:, 1:].mean(axis=0)]) if a.shape[1] > 1 else a
        coef, _, rank, _ = np.linalg.lstsq(a, ds, rcond=None)
        res = ds - a @ coef
        v = float(res @ res) / max(n - rank, 1)
        var[s] = v / scale[0, s]
        fitted = a @ coef
        chi2 += float(fitted @ fitted) / max(v, 1e-300)
        dof += int(rank)
    if not with_test:
        return var
    from scipy import stats

    used = valid.any(axis=0)
    p = float(stats.chi2.sf(chi2, dof)) if dof else 1.0
    return var, {"raw_dn": float(np.sqrt(np.mean(raw[used]))) if used.any() else 0.0,
                 "clean_dn": float(np.sqrt(np.mean(var[used]))) if used.any() else 0.0,
                 "chi2": chi2, "dof": dof, "p_value": p, "within_step": p < WITHIN_STEP_P}


def quantisation_bias(var_pair, quantum=1.0):
    """Variance (S,) in DN^2 that quantisation adds to a held-out sample but the frame pairs do
    not show: with a temporal noise much below the quantum, both frames of a step fall on the
    same code, and the rounding error is a bias of that pixel and step, not noise.

    For a Gaussian noise sigma and a level uniform within the quantum q, the bias
    ``E[Q(x)] - mu`` has the variance ``m(sigma) = q^2 sum_k exp(-4 pi^2 k^2 sigma^2 / q^2) /
    (2 pi^2 k^2)`` (q^2 / 12 at sigma = 0, nothing at sigma >~ 0.4 q), and the frame pairs
    measure ``sigma^2 + q^2 / 12 - m(sigma)``; sigma is solved from that per step.

    Parameters
    ----------
    var_pair : ndarray, (S,), DN^2
        From :func:`noise_pairs`.
    quantum : float, DN
        Step of the recorded values (1 for integer raw data; 0: not quantised).

    Returns
    -------
    ndarray, (S,), DN^2

    Examples
    --------
    >>> import numpy as np
    >>> quantisation_bias(np.array([0.0, 100.0])).round(3).tolist()
    [0.083, 0.0]
    """
    v = np.asarray(var_pair, float)
    if quantum <= 0:
        return np.zeros_like(v)
    pair, bias, _ = _quantisation_table()
    return quantum ** 2 * np.interp(np.maximum(v, 0.0) / quantum ** 2, pair, bias)


def noise_before_rounding(var_pair, quantum=1.0):
    """Variance (S,) in DN^2 of the temporal noise before the ADC rounds it: the sigma^2 that
    :func:`quantisation_bias` solves from the frame pairs (``var_pair`` itself when the data
    are not quantised). Simulating a frame as ``round(level + sigma * N(0, 1))`` reproduces
    both the pairs' variance and the rounding bias of a quiet pixel.

    Parameters
    ----------
    var_pair : ndarray, (S,), DN^2
        From :func:`noise_pairs`.
    quantum : float, DN
        Step of the recorded values (0: not quantised).

    Returns
    -------
    ndarray, (S,), DN^2

    Examples
    --------
    >>> import numpy as np
    >>> noise_before_rounding(np.array([0.0, 1 / 12, 100.0])).round(3).tolist()
    [0.0, 0.022, 99.917]
    """
    v = np.asarray(var_pair, float)
    if quantum <= 0:
        return v.copy()
    pair, _, s2 = _quantisation_table()
    q2 = quantum ** 2
    x = np.maximum(v, 0.0) / q2
    return q2 * np.where(x <= pair[-1], np.interp(x, pair, s2), x - 1.0 / 12)


@functools.lru_cache(maxsize=1)
def _quantisation_table():
    """(pair variance, bias variance, sigma^2) in units of the quantum squared, sigma from 0
    to 2."""
    s2 = np.concatenate([[0.0], np.geomspace(1e-6, 4.0, 400)])
    k = np.arange(1, 401)[:, None]
    bias = (np.exp(-4 * np.pi ** 2 * k ** 2 * s2[None, :]) / (2 * np.pi ** 2 * k ** 2)).sum(0)
    return s2 + 1.0 / 12 - bias, bias, s2  # the pair variance grows with sigma


def noise_from_spread(res_ho, valid_ho, signal, pred_var, n_frames):
    """Temporal variance of one frame per step (S,) without frame pairs: per held-out step, the
    robust spread across pixels of the held-out residual (a linear trend in signal removed; a
    common error of the step does not enter), minus the prediction's own variance, then a
    photon-transfer line ``var = K signal + R`` through the steps. Systematic errors that differ
    from pixel to pixel at equal signal inflate it (conservative).

    Parameters
    ----------
    res_ho : ndarray, (P, S), DN
        Held-out residuals.
    valid_ho : ndarray of bool, (P, S)
        Valid held-out samples.
    signal : ndarray, (P, S), DN
        Model signal above dark.
    pred_var : ndarray, (P, S), DN^2
        Variance of the prediction itself.
    n_frames : ndarray, (S,)
        Frames averaged in each held-out sample.

    Returns
    -------
    callable
        ``variance(signal_dn)`` of one frame in DN^2.

    Raises
    ------
    DataFormatError
        No held-out step has 20 valid pixels (the message says how to get more).
    """
    rows = []
    for s in range(res_ho.shape[1]):
        ok = valid_ho[:, s]
        if ok.sum() < 20:
            continue
        x, v = signal[ok, s], res_ho[ok, s]
        a = np.column_stack([np.ones_like(x), x - x.mean()])
        v = v - a @ np.linalg.lstsq(a, v, rcond=None)[0]
        var = (1.4826 * np.median(np.abs(v - np.median(v)))) ** 2 - np.mean(pred_var[ok, s])
        rows.append((float(np.median(x)), max(var, 0.0) * n_frames[s]))
    if not rows:
        raise DataFormatError("no held-out step has 20 valid pixels, so the noise cannot be "
                              "measured; analyse more pixels (--pixels) or record two frames "
                              "per step")
    sig, var = np.array(rows).T
    if len(rows) >= 3 and np.ptp(sig) > 0:
        k, r0 = np.polyfit(np.maximum(sig, 0), var, 1)
    else:
        k, r0 = 0.0, float(np.median(var))
    k, r0 = max(k, 0.0), max(r0, 1.0 / 12.0)
    return lambda s_dn: k * np.maximum(s_dn, 0.0) + r0


def frame_variance(sub, smp):
    """Per-frame variance model (callable on signal above dark) from the photon transfer curve
    where the design has frame pairs; None otherwise.

    Parameters
    ----------
    sub : Sweep
        The pixel subset.
    smp : dict
        From :func:`samples`.

    Returns
    -------
    callable or None
        ``variance(signal_dn)`` in DN^2 (:meth:`hsiffc.calibrate.PhotonTransfer.variance`,
        plus :func:`quantisation_bias` for integer raw data).
    """
    below = 0.7  # of full scale; of a full well's plateau below it (the line stays under it)
    if smp.get("plateau") is not None:
        below *= smp["clip_dn"] / sub.full_scale_dn
    ptc = photon_transfer(sub, max_fraction_of_full_scale=below) if smp["pairs"] else None
    if ptc is None:
        return None
    if not np.issubdtype(sub.data.dtype, np.integer):
        return ptc.variance

    def variance(signal):  # integer data: the rounding bias of quiet samples too
        v = np.asarray(ptc.variance(signal), float)
        return v + quantisation_bias(v.ravel()).reshape(v.shape)
    return variance
