"""Flat stacks of a calibration sweep folded into the calibration: the best responsivity map.

A sweep fit estimates each pixel's responsivity from a few frames per step; a flat stack (many
frames of one uniform light, e.g. the EMVA 1288 spatial set) estimates it from many. The
model-based flat field (:func:`hsiffc.flatfield.model_based.model_flat_fit`) combines both per pixel by
inverse variance. :func:`add_flat_stacks` runs that combination at calibration time and stores
its result in the calibration, so that the calibration alone (what ``hsiffc correct`` applies by
default, with no training frames) already carries it:

* ``flat_gain``: the combined factor ``mean_band(g) / g``;
* ``flat_gain_sweep``: the sweep's own factor (``model_ffc`` moves to it where leakage bends the
  response: the flat's g does not share the errors of the fitted a and b);
* ``sigma_ln_flat_gain``: 1-sigma relative error of ``flat_gain``;
* ``flat_weight``: the flat stacks' share in it;
* ``flat_dq``: NO_FLAT where no responsivity could be estimated (factor 1).

Each stack's dark is the dark frames of its exposure where the sweep has two or more (the
EMVA 1288 dark stack), combined per pixel with the calibration's dark at that exposure by
inverse variance (the temporal variance of the dark frames over their number, against the
calibration's ``sigma_dark_dn``), else the calibration's dark alone.

The stacks are not samples of the joint fit: a 100-frame step weighs as much as 50 two-frame
steps there and pulls every pixel's fit to its one level.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..flatfield.model_based import FlatStack, model_flat_fit
from ..data.sweep import Sweep
from .product import Calibration

__all__ = ["FLAT_ARRAYS", "MIN_FLAT_FRAMES", "add_flat_stacks", "flat_stack_steps",
           "combined_dark"]

#: the arrays :func:`add_flat_stacks` adds
FLAT_ARRAYS = ("flat_gain", "flat_gain_sweep", "sigma_ln_flat_gain", "flat_weight", "flat_dq")
#: light frames of one step needed to count as a flat stack (as the model_ffc stage)
MIN_FLAT_FRAMES = 8


def flat_stack_steps(sweep: Sweep, min_frames: int = MIN_FLAT_FRAMES) -> list:
    """Step ids of the light steps with at least ``min_frames`` frames."""
    out = []
    for s in sweep.steps():
        sel = sweep.step == s
        if sweep.kind[sel][0] == "light" and sel.sum() >= min_frames:
            out.append(int(s))
    return out


def combined_dark(cal: Calibration, exposure_ms: float, dark_frames=None) -> np.ndarray:
    """The dark at ``exposure_ms`` (DN, float64): the calibration's, combined per pixel by
    inverse variance with the mean of ``dark_frames`` (frames of that exposure, >= 2) when
    given. The dark frames' variance is their temporal variance (median over the pixels, so a
    2-frame estimate does not make single pixels' weights noisy) over their number."""
    d_cal = np.asarray(cal.dark_at(exposure_ms), np.float64)
    if dark_frames is None or len(dark_frames) < 2:
        return d_cal
    frames = np.asarray(dark_frames, np.float64)
    master = frames.mean(axis=0)
    var_master = float(np.median(frames.var(axis=0, ddof=1))) / frames.shape[0]
    var_cal = np.asarray(cal.arrays.get("sigma_dark_dn", np.inf), np.float64) ** 2
    var_cal = np.where(np.isfinite(var_cal) & (var_cal > 0), var_cal, np.inf)
    if not var_master > 0:
        return master
    w_master = 1.0 / var_master
    w_cal = np.where(np.isfinite(var_cal), 1.0 / var_cal, 0.0)
    return (w_master * master + w_cal * d_cal) / (w_master + w_cal)


def add_flat_stacks(cal: Calibration, sweep: Sweep, *, steps=None,
                    min_frames: int = MIN_FLAT_FRAMES) -> Calibration:
    """The calibration with the sweep's flat stacks folded into its responsivity map.

    Parameters
    ----------
    cal : Calibration
        Fitted on the sweep's other steps (needs ``responsivity``).
    sweep : Sweep
        Holds the flat stacks (and, ideally, dark frames at their exposures).
    steps : list of int, optional
        The flat stacks' step ids (default: every light step with ``min_frames`` or more).

    Returns
    -------
    Calibration
        A new calibration with the arrays :data:`FLAT_ARRAYS` and, in ``fitted_on``,
        ``flat_stacks`` (step, frames, exposure, level above dark, dark used) and
        ``flat_summary`` (per band uncertainties); ``cal`` itself when the sweep has no flat
        stack.
    """
    if "responsivity" not in cal.arrays:
        return cal
    cal.check_compatible(frame_shape=sweep.frame_shape, what="the sweep with the flat stacks")
    steps = flat_stack_steps(sweep, min_frames) if steps is None else list(steps)
    if not steps:
        return cal
    full = 2 ** sweep.bit_depth - 1
    stacks, info = [], []
    for s in steps:
        sel = sweep.step == s
        t = float(sweep.exposure_ms[sel][0])
        darks = sweep.data[(sweep.kind == "dark") & np.isclose(sweep.exposure_ms, t,
                                                               rtol=1e-6, atol=0.0)]
        dark = combined_dark(cal, t, darks if len(darks) >= 2 else None)
        frames = sweep.data[sel]
        usable = (frames < full).all(axis=0)
        stacks.append(FlatStack.from_arrays(frames, t, dark, usable=usable))
        info.append({"step": int(s), "n_frames": int(sel.sum()), "exposure_ms": t,
                     "level_dn": float(np.median(frames.mean(axis=0) - dark)),
                     "dark": (f"calibration's, combined with {len(darks)} dark frames"
                              if len(darks) >= 2 else "calibration's")})
    band_map = (sweep.mosaic.band_map(sweep.frame_shape) if sweep.mosaic is not None
                else np.zeros(sweep.frame_shape, np.int64))
    mf = model_flat_fit(cal["responsivity"], cal.arrays.get("sigma_ln_g"), cal.a, cal.b,
                        band_map, flags=cal.arrays.get("flags"), flats=stacks)
    arrays = dict(cal.arrays)
    arrays.update(flat_gain=mf.gain, flat_gain_sweep=mf.gain_sweep,
                  sigma_ln_flat_gain=mf.sigma_ln_gain, flat_weight=mf.flat_weight,
                  flat_dq=mf.dq.astype(np.uint32))
    fitted = dict(cal.fitted_on)
    fitted.update(flat_stacks=info, flat_summary=mf.summary)
    return replace(cal, arrays=arrays, fitted_on=fitted, created="")
