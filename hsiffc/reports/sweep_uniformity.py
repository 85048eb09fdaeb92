"""Fixed-pattern non-uniformity of every step of a sweep, raw and after corrections.

Used by ``hsiffc uniformity`` and the FFC study (:mod:`hsiffc.reports.ffc_study`). For every
light step with two or more frames: exposure, signal level (DN above dark), the fractions of
clipped and flagged pixels, and per correction eq. (6) and the fixed-pattern non-uniformity of
:mod:`hsiffc.flatfield.uniformity` (temporal noise removed). All methods of a step are measured over the
same pixels: those with no DQ bit set in any raw or corrected frame of the step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..data.dq import DQ
from ..flatfield.uniformity import FixedPattern, fixed_pattern_nonuniformity

__all__ = ["SIGNAL_RANGES_DN", "signal_ranges_dn", "StepUniformity", "step_uniformity",
           "dark_frames_by_exposure",
           "sweep_uniformity", "summarise", "to_json", "plot_uniformity"]

log = logging.getLogger(__name__)

#: signal ranges (DN above dark) of the summary for an 8-bit sensor (full scale 255 DN): low
#: light, linear range, upper range, top. Other bit depths scale them to their full scale
#: (:func:`signal_ranges_dn`).
SIGNAL_RANGES_DN = ((5.0, 30.0), (30.0, 100.0), (100.0, 200.0), (200.0, 255.0))


def signal_ranges_dn(bit_depth: int = 8) -> tuple:
    """The summary's signal ranges (DN above dark) for a sensor of ``bit_depth`` bits: the same
    fractions of full scale (``2**bit_depth - 1`` DN) as :data:`SIGNAL_RANGES_DN` of 255 DN,
    rounded to whole DN (a 10-bit sensor: 20-120, 120-401, 401-802, 802-1023 DN).

    Examples
    --------
    >>> signal_ranges_dn(8) == SIGNAL_RANGES_DN
    True
    >>> signal_ranges_dn(10)[0]
    (20.0, 120.0)
    """
    scale = (2 ** int(bit_depth) - 1) / 255.0
    return tuple((float(round(lo * scale)), float(round(hi * scale)))
                 for lo, hi in SIGNAL_RANGES_DN)
#: steps with more clipped pixels than this are listed but left out of the summary
MAX_CLIPPED_FRACTION = 0.01


@dataclass
class StepUniformity:
    """Uniformity of one sweep step, raw and per correction (pooled over bands)."""

    step: int
    exposure_ms: float
    signal_dn: float
    clipped_fraction: float
    flagged_fraction: float
    raw: FixedPattern
    corrected: dict = field(default_factory=dict)  # name -> FixedPattern

    def figures(self, name: str | None = None) -> dict:
        """``{"eq6_percent", "fpn_percent", "fpn_se_percent"}`` of the raw frames (name None)
        or a correction (pooled over bands; ``fpn_se_percent`` is the standard error of
        ``fpn_percent``)."""
        fp = self.raw if name is None else self.corrected[name]
        return {"eq6_percent": fp.pooled_eq6_percent, "fpn_percent": fp.pooled_fpn_percent,
                "fpn_se_percent": fp.pooled_fpn_se_percent,
                "fpn_var_rel": fp.pooled_fpn_var_rel, "below_noise": fp.below_noise}


def step_uniformity(frames, corrections: dict, *, dark=None,
                    dark_frames=None) -> StepUniformity:
    """Fixed-pattern non-uniformity of one step's frames, raw and after each correction.

    Parameters
    ----------
    frames : list of Frame
        >= 2 raw frames of one step.
    corrections : dict of name -> object with ``transform(frame)``
        Fitted pipelines or stages (may be empty).
    dark : (H, W) array or float, optional, DN
        Subtracted from the raw frames (default: the dark the first correction removed, else
        none).
    dark_frames : (L, H, W) array, optional, DN
        Dark frames of the step's exposure (L >= 2): the raw figure subtracts their mean and
        removes their temporal variance (EMVA 1288), so neither a dark's noise nor a modelled
        dark's error counts as the raw pattern; ``dark`` then only sets the signal level.
    """
    frames = list(frames)
    raw = np.stack([f.data for f in frames])
    outs = {name: [c.transform(f) for f in frames] for name, c in corrections.items()}
    clipped = np.any([(f.dq & int(DQ.SATURATED)) != 0 for f in frames], axis=0)
    bad = np.any([f.dq != 0 for f in frames], axis=0)
    for out in outs.values():
        bad |= np.any([o.dq != 0 for o in out], axis=0)
    if dark is None:
        dark = next((o[0].dark_removed for o in outs.values()
                     if o[0].dark_removed is not None), None)
    band_map = frames[0].band_map()
    good = ~bad
    if dark_frames is not None and len(dark_frames) >= 2:
        dark_frames = np.asarray(dark_frames)
        raw_fp = fixed_pattern_nonuniformity(raw, band_map, dark_stack=dark_frames, mask=good)
        if dark is None:
            dark = dark_frames.mean(axis=0)
    else:
        raw_fp = fixed_pattern_nonuniformity(raw, band_map, dark=dark, mask=good)
    corrected = {name: fixed_pattern_nonuniformity(np.stack([o.data for o in out]), band_map,
                                                   mask=good) for name, out in outs.items()}
    signal = raw.mean(axis=0) - (0.0 if dark is None else dark)
    return StepUniformity(step=int(frames[0].meta.get("step", -1)),
                          exposure_ms=frames[0].exposure_ms,
                          signal_dn=float(np.mean(signal[good] if good.any() else signal)),
                          clipped_fraction=float(clipped.mean()),
                          flagged_fraction=float(bad.mean()), raw=raw_fp, corrected=corrected)


def sweep_uniformity(frames, corrections: dict, *, dark_for=None, steps=None,
                     dark_frames_for=None) -> list:
    """:func:`step_uniformity` for every light step with two or more frames.

    Parameters
    ----------
    frames : list of Frame
        The sweep's frames (``meta["step"]`` groups them; else exposure and illumination).
    corrections : dict of name -> fitted pipeline or stage
    dark_for : callable, optional
        ``dark_for(exposure_ms) -> (H, W)`` dark for the raw figures (default: the dark the
        first correction removed).
    steps : iterable of int, optional
        Only these steps.
    dark_frames_for : callable, optional
        ``dark_frames_for(exposure_ms) -> (L, H, W) or None``: dark frames of that exposure for
        the raw figures (see :func:`step_uniformity`); :func:`dark_frames_by_exposure` makes one.
    """
    groups: dict = {}
    for f in frames:
        if f.kind != "light" or f.is_cube:
            continue
        key = f.meta.get("step", (f.exposure_ms, f.meta.get("illumination", "")))
        groups.setdefault(key, []).append(f)
    wanted = None if steps is None else set(int(s) for s in steps)
    out = []
    for key, group in groups.items():
        if len(group) < 2 or (wanted is not None and key not in wanted):
            continue
        dark = None if dark_for is None else dark_for(group[0].exposure_ms)
        dframes = None if dark_frames_for is None else dark_frames_for(group[0].exposure_ms)
        out.append(step_uniformity(group, corrections, dark=dark, dark_frames=dframes))
        log.debug("step %s: %.1f DN", key, out[-1].signal_dn)
    return sorted(out, key=lambda s: s.signal_dn)


def dark_frames_by_exposure(frames):
    """``dark_frames_for(exposure_ms)`` for :func:`sweep_uniformity`: every dark frame of that
    exposure (within 1e-6 relative), stacked, or None where fewer than two."""
    darks: dict = {}
    for f in frames:
        if f.kind == "dark" and not f.is_cube:
            darks.setdefault(float(f.exposure_ms), []).append(f.raw)

    def dark_frames_for(exposure_ms):
        for t, group in darks.items():
            if abs(t - exposure_ms) <= 1e-6 * max(abs(t), 1e-9) and len(group) >= 2:
                return np.stack(group)
        return None
    return dark_frames_for


def summarise(steps, methods, *, ranges=SIGNAL_RANGES_DN,
              max_clipped_fraction: float = MAX_CLIPPED_FRACTION) -> list:
    """Per signal range and method: the median and the worst step's fixed-pattern percent.

    Steps with more than ``max_clipped_fraction`` of their pixels clipped are left out.
    ``methods`` are correction names; "raw" is always included first.
    """
    rows = []
    for lo, hi in ranges:
        sel = [s for s in steps if lo <= s.signal_dn < hi
               and s.clipped_fraction <= max_clipped_fraction]
        row = {"signal_range_dn": [lo, hi], "n_steps": len(sel), "methods": {}}
        for name in ("raw", *methods) if sel else ():
            figs = [s.figures(None if name == "raw" else name) for s in sel]
            vals, eq6, se = (np.array([f[k] for f in figs], float)
                             for k in ("fpn_percent", "eq6_percent", "fpn_se_percent"))
            var_rel = np.array([f.get("fpn_var_rel", np.nan) for f in figs], float)
            med_var = _nanmedian_or_nan(var_rel)
            # no finite figure (every pixel of the range's steps flagged): no worst step
            worst = int(np.nanargmax(vals)) if np.isfinite(vals).any() else None
            row["methods"][name] = {
                # the median of the signed variance: below the noise when it is not positive
                "fpn_percent_median": (100 * float(np.sqrt(max(med_var, 0.0)))
                                       if np.isfinite(med_var) else _nanmedian_or_nan(vals)),
                "below_noise": bool(np.isfinite(med_var) and med_var <= 0),
                "fpn_percent_max": float("nan") if worst is None else float(vals[worst]),
                "worst_step": None if worst is None else sel[worst].step,
                "worst_signal_dn": None if worst is None else sel[worst].signal_dn,
                "fpn_se_percent_median": _nanmedian_or_nan(se),
                "eq6_percent_median": _nanmedian_or_nan(eq6)}
        rows.append(row)
    return rows


def _nanmedian_or_nan(values) -> float:
    values = np.asarray(values, dtype=float)
    return float(np.median(values[np.isfinite(values)])) if np.isfinite(values).any() \
        else float("nan")


def to_json(steps, methods, summary) -> dict:
    """The document ``hsiffc uniformity`` writes: ``{"steps": [...], "summary": [...]}``."""
    out = []
    for s in steps:
        row = {"step": s.step, "exposure_ms": s.exposure_ms, "signal_dn": s.signal_dn,
               "clipped_fraction": s.clipped_fraction, "flagged_fraction": s.flagged_fraction,
               "raw": s.figures()}
        row["corrected"] = {name: s.figures(name) for name in methods}
        out.append(row)
    return {"steps": out, "summary": summary}


def plot_uniformity(steps, methods, *, title: str = "", ranges=SIGNAL_RANGES_DN):
    """Fixed-pattern non-uniformity (percent) against signal level, one line per method
    (steps from the lower end of ``ranges``, 5 DN for 8 bits; a step whose fixed pattern is
    below what its frames can measure, 0 %, is left as a gap).

    Returns a new :class:`matplotlib.figure.Figure` (object API; no backend is switched).
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 4.2), layout="constrained")
    ax = fig.add_subplot()
    steps = [s for s in steps if s.signal_dn >= ranges[0][0]]
    sig = np.array([s.signal_dn for s in steps])
    for name in ("raw", *methods):
        fpn = np.array([s.figures(None if name == "raw" else name)["fpn_percent"]
                        for s in steps])
        # a fixed pattern below what two frames can measure has no place on a log axis
        ax.plot(sig, np.where(fpn > 0, fpn, np.nan), marker="o", ms=3, lw=1, label=name)
    clipped = [s.signal_dn for s in steps if s.clipped_fraction > MAX_CLIPPED_FRACTION]
    if clipped:
        ax.axvspan(min(clipped), max(sig), color="0.9", zorder=0,
                   label=f"> {100 * MAX_CLIPPED_FRACTION:g} % pixels clipped")
    ax.set_xlabel(f"signal level: mean DN above dark (steps from {ranges[0][0]:g} DN)")
    ax.set_ylabel("fixed-pattern non-uniformity (%)\n(temporal noise removed, EMVA 1288)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    return fig
