"""Close the loop with measured data: where does the model miss, why, and how much better is
it once the missing effect is modelled?

``diagnose(sweep)`` fits the base model per pixel (the paper's leakage model; with the dark
current measured from the dark frames when they show one) on the fit half of the sweep and
measures every error on the held-out half (see :mod:`hsiffc.diagnose.design`). It fits each
candidate effect of :mod:`hsiffc.diagnose.effects` jointly with the base model
(:mod:`hsiffc.diagnose.fitting`), skips with a stated reason each effect the design cannot
identify, and adds effects greedily while one beats the current model by more than the noise
allows, then drops any that no longer beats the model of the others by that rule
(:mod:`hsiffc.diagnose.select`); once a light change between the frames of a step is selected,
the noise floor is measured on the frame differences less what it predicts. The search starts
from the leakage model with one shape for the sensor
(:class:`~hsiffc.diagnose.bases.SharedLeakageBase`) where the per-pixel one predicts the
held-out data measurably worse, and is run from both then; otherwise it refits the selected
model with one shape and keeps it where it is as good with fewer parameters. It then asks
whether the bending of the response is leakage at all or a readout nonlinearity, and reports
structure left in the held-out residual that no candidate explains as ``unexplained`` (binned,
and as a pattern over the pixels times one over the steps, against what the model leaves on
data simulated from itself). Frames that clip below the ADC's full scale
(:func:`~hsiffc.diagnose.design.clip_level`) or sit at its lowest code are left out.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import DataFormatError
from ..data.sweep import Sweep
from . import design as ds
from .bases import LeakageBase, LinearBase, SharedLeakageBase
from .effects import ALIASES, EFFECTS, OUTSIDE, inject
from .fitting import (Data, State, context, describe_params, fitpredict, gram, projector,
                      refit_base, separable_fraction)
from .select import RULE, UNEXPLAINED_OF_FLOOR, equally_good, evaluate, greedy, leakage_check
from .structure import groupings, structure

__all__ = ["diagnose", "EFFECTS", "OUTSIDE", "inject", "list_effects"]

MIN_LIGHT_STEPS = 4


def _unexplained_reason(structured, too_big, after, floor):
    parts = []
    if too_big:
        parts.append(f"the systematic error left ({after['systematic_rms_dn']:.3g} DN RMS) is "
                     f"more than {UNEXPLAINED_OF_FLOOR:g} of the noise floor ({floor:.3g} DN)")
    if structured:
        parts.append("the held-out residual shows structure beyond the noise in a grouping "
                     "(see residual_structure_after)")
    return "; ".join(parts) if parts else (
        f"the systematic error left ({after['systematic_rms_dn']:.3g} DN RMS) is within "
        f"{UNEXPLAINED_OF_FLOOR:g} of the noise floor ({floor:.3g} DN) and no grouping shows "
        "structure beyond the noise")


def list_effects() -> list[dict]:
    """The effect library: one dict per effect with ``name``, ``scope``, ``params`` and
    ``summary`` (what ``hsiffc diagnose --list-effects`` prints).

    Returns
    -------
    list of dict

    Examples
    --------
    >>> effects = list_effects()
    >>> "dark_current" in [e["name"] for e in effects], sorted(effects[0])
    (True, ['name', 'params', 'scope', 'summary'])
    """
    return [{"name": e.name, "scope": e.scope, "params": list(e.param_names),
             "summary": e.summary} for e in EFFECTS.values()]


def _prediction_variance(base, theta, data, state=None):
    """Variance the fit's own noise adds to each prediction (linearised: j C j^T), of the base
    model or (with ``state``) of the base with the per-pixel effects of a fitted model."""
    _, jac, ctx = context(base, theta, data)
    if state is not None:
        cols = [EFFECTS[n].columns(ctx) for n in state.effects if EFFECTS[n].scope == "pixel"]
        jac = np.concatenate([jac] + cols, axis=-1)
    normal = gram(jac, data.w, jac)
    normal += 1e-9 * (np.einsum("pii->p", normal)[:, None, None] + 1e-30) * np.eye(jac.shape[-1])
    return np.clip((np.matmul(jac, np.linalg.pinv(normal)) * jac).sum(axis=-1), 0, None)


def _identifiable(names, base, theta, data, des, dark_desc):
    """(skipped [{name, reason}], testable names, weak {name: reason}) next to a base model.

    Only the design skips a candidate: one that the base model's parameters mostly absorb
    (less than ``MIN_SEPARABLE`` of it separable) is still fitted in full and kept when that
    fit improves the held-out error (a pre-check never silences it); ``weak`` holds the reason
    reported when it does not."""
    _, jac, ctx = context(base, theta, data)
    project = projector(jac, data.w)
    skipped, testable, weak = [], [], {}
    for name in names:
        why = ds.structural_skip(name, des, dark_desc)
        if why is None:
            frac = separable_fraction(EFFECTS[name], ctx, project, data.w)
            if frac < ds.MIN_SEPARABLE:
                weak[name] = (f"the {base.name} base model's own parameters absorb most of it "
                              f"on this design (only {100 * frac:.2g} % of it is separable); "
                              "its full fit was tried and did not improve the held-out error")
        (skipped.append({"name": name, "reason": why}) if why else testable.append(name))
    return skipped, testable, weak


def _with_weak(skipped, weak, selected):
    return skipped + [{"name": n, "reason": r} for n, r in weak.items() if n not in selected]


def _refuse(msg, sweep):
    raise DataFormatError(msg, path=sweep.source or None)


def diagnose(sweep: Sweep, *, max_pixels: int = 2048, seed: int = 0, effects=None,
             full_well_dn: float | None = None) -> dict:
    """Diagnose where the base model misses a sweep; see the module docstring.

    Parameters
    ----------
    sweep : Sweep
        Any sweep design: exposure sweeps, light sweeps at a fixed exposure, mixed; with or
        without dark frames; two frames per step (frame pairs held out) or one (alternate steps
        held out).
    max_pixels : int
        Pixels analysed (a random subset when the sensor has more).
    seed : int
        Seed of the pixel subset.
    effects : list of str, optional
        Candidate effects (default: the whole library, :func:`list_effects`).
    full_well_dn : float, optional, DN
        Step means at or above it are not used.

    Returns
    -------
    dict
        The fields of ``hsiffc diagnose --json`` (design, base model, noise floor in DN,
        RMS before and after in DN, selected effects with their sizes, what stays unexplained)
        plus the arrays the report plots (under ``"_arrays"``). Run time: seconds (measured
        by ``benchmarks/bench_diagnose.py``).

    Raises
    ------
    ValueError
        Unknown effect names (the message lists the library).
    DataFormatError
        A design nothing can be learned from (fewer than 4 usable light steps, no valid sample).
    """
    t0 = time.perf_counter()
    names = list(EFFECTS) if effects is None else [ALIASES.get(n, n) for n in effects]
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effects {unknown}; the library has {list(EFFECTS)}")
    if "sweep_steps" in sweep.meta:  # EMVA 1288: the sweep, not the spatial set
        sweep = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    sub, rows, cols, band = ds.subset(sweep, max_pixels, seed)
    smp = ds.samples(sub, full_well_dn)
    des = ds.describe(smp)
    if des.n_light_steps < MIN_LIGHT_STEPS:
        _refuse(f"{des.n_light_steps} usable light steps (exposure > 0, known light rate); "
                f"diagnose needs at least {MIN_LIGHT_STEPS} to fit a response and test it on "
                "held-out data. Record more light steps", sweep)
    y, y_ho, t, r = smp["y"], smp["y_ho"], smp["t"], smp["r"]
    fs = float(sweep.full_scale_dn)
    if smp["clip_dn"] is not None:  # the data clip below the ADC's full scale
        fs = smp["clip_dn"]
        des.notes.append(f"the frames clip at {fs:g} DN, below the ADC's full scale "
                         f"({sweep.full_scale_dn} DN): a full well that fills first; steps with "
                         "a frame there are left out and the clip acts as full scale")
    kind = smp["kind"]
    light = kind == "light"
    n_fit = smp["n_fit"]
    dark0 = (np.median(y[:, kind == "dark"], axis=1) if (kind == "dark").any()
             else y.min(axis=1))
    var_fn = ds.frame_variance(sub, smp)
    var_frame = var_fn(y - dark0[:, None]) if var_fn is not None else np.ones_like(y)
    # samples within 4 sigma of full scale are left out: frames there are sometimes clipped
    near_fs = 0.5 * (y + y_ho) > fs - 4.0 * np.sqrt(var_frame)
    valid, valid_ho = smp["valid"] & ~near_fs, smp["valid_ho"] & ~near_fs
    if valid.sum(axis=1).max(initial=0) < 3 or not valid_ho.any():
        _refuse("no pixel has enough valid samples (clipped, at full scale or unusable); check "
                "the exposure and light levels of the sweep", sweep)
    n_light = int((valid & light[None, :]).sum(axis=1).max(initial=0))
    if n_light < MIN_LIGHT_STEPS:  # darks alone would be fitted as a flat "response"
        _refuse(f"no pixel has {MIN_LIGHT_STEPS} light samples below full scale (at most "
                f"{n_light}): the light steps are clipped or within the noise of full scale "
                f"({fs:g} DN); record the sweep with less light or shorter exposures", sweep)
    w = np.where(valid, n_fit[None, :] / var_frame, 0.0)
    use_dc, dark_desc = ds.dark_model(y, t, r, valid, w, des)
    n_fit_samples = float(np.median(valid.sum(axis=1)))
    base = (LeakageBase(use_dc) if n_fit_samples >= LeakageBase.n_core + use_dc + 3
            else LinearBase(use_dc))
    base.full_scale = fs
    if base.name == "linear":
        des.notes.append(f"{n_fit_samples:.0f} fit samples per pixel (median): too few for the "
                         "leakage model (4 parameters), the base is a linear response")
    theta = base.start(y, t, r, valid, w)
    # Select samples near full scale by the model's prediction (independent of the held-out
    # noise), leaving out everything the model puts within 5 sigma of full scale, and refit.
    pred = base.predict(theta, t, r)
    sd_pred = np.sqrt(var_fn(pred - dark0[:, None])) if var_fn is not None else 0.0
    keep = pred < fs - 5.0 * sd_pred
    valid, valid_ho = valid & keep, valid_ho & keep
    w = np.where(valid, w, 0.0)
    theta = base.fit(y, t, r, valid, w, theta, max_iter=40)
    order_rank = np.argsort(np.argsort(smp["step"]))
    order = (order_rank / max(len(order_rank) - 1, 1)) * 2 - 1
    by_order = np.argsort(smp["step"])
    prev_index = np.full(len(order), -1)
    prev_index[by_order[1:]] = by_order[:-1]
    data = Data(y=y, y_ho=y_ho, t=t, r=r, valid=valid, valid_ho=valid_ho, w=w, order=order,
                prev_index=prev_index, light=light, full_scale=fs, frame_gap=smp["frame_gap"])
    quantum = 1.0 if np.issubdtype(sub.data.dtype, np.integer) else 0.0  # DN
    if smp["pairs"]:
        var_step = ds.noise_pairs(smp, valid & valid_ho)  # one frame, per step
        # integer raw data: the rounding bias of a quiet pixel is in the held-out error but
        # not in the frame pairs
        noise2 = np.broadcast_to((var_step / smp["n_ho"] + ds.quantisation_bias(
            var_step, quantum))[None, :], y.shape)
    else:  # no frame pairs: the noise from the spread of the held-out residual across pixels
        m = base.predict(theta, t, r)
        pv = _prediction_variance(base, theta, data)
        var_fn = ds.noise_from_spread(np.where(valid_ho, y_ho - m, 0.0), valid_ho,
                                      m - base.dark(theta), pv, smp["n_ho"])
        var1 = var_fn(m - base.dark(theta))
        data.w = w = np.where(valid, n_fit[None, :] / var1, 0.0)
        theta = base.fit(y, t, r, valid, w, theta, max_iter=40)
        noise2 = var1 / smp["n_ho"][None, :]
        var_step = np.median(var1, axis=0)

    def var_step_of(state):
        """The noise of one frame per step (S,) for a model: the frame differences it is
        measured on hold a within-step effect too (a light that changes between the frames of
        a step), so with one in the model it is measured on them less what it predicts."""
        extra = state.ho_extra
        if not smp["pairs"] or np.ndim(extra) == 0:
            return var_step
        return ds.noise_pairs({**smp, "y_ho": smp["y_ho"] - extra}, valid & valid_ho)

    def noise2_of(state, vs=None):
        """The noise variance (P, S) of each held-out sample for a model (see above);
        ``vs``: its :func:`var_step_of`, where already measured."""
        vs = var_step_of(state) if vs is None else vs
        if vs is var_step:
            return noise2
        return np.broadcast_to((vs / smp["n_ho"] + ds.quantisation_bias(vs, quantum))[None, :],
                               y.shape)

    def refloor(fitted, floor):
        """The noise floor ``floor`` of the start model, for ``fitted`` (see above)."""
        if np.ndim(fitted.state.ho_extra) == 0:
            return floor
        less = float(np.mean((noise2 - noise2_of(fitted.state))[valid_ho]))
        return float(np.sqrt(max(floor ** 2 - less, 1e-12 * floor ** 2)))
    # the base alone gets the linearised (Gauss-Newton) step every candidate's trial fit makes,
    # so a base fit short of its optimum does not credit that step to whichever effect is tried
    start = refit_base(y, data, State(base, theta))
    pred_var = _prediction_variance(base, theta, data)
    noise_floor = float(np.sqrt(np.mean((noise2 + pred_var)[valid_ho])))
    if not np.isfinite(noise_floor) or noise_floor <= 0:
        _refuse("the temporal noise cannot be measured on this sweep (no valid held-out "
                "sample with a finite noise); record two frames per step", sweep)
    n_pix, n_light = y.shape[0], int(light.sum())
    base_fit = evaluate(start, [], data, n_pix, n_light)
    per_pixel_start = None
    if base.name == "leakage":
        # the same model with one leakage shape for the sensor (a and b shared: two parameters
        # a pixel fewer); the search starts from it where the per-pixel model predicts the
        # held-out data measurably worse (it follows the noise of the fit half: a base worse
        # than a simpler one would let any effect that makes up part of the difference look
        # like a find)
        shared = SharedLeakageBase(use_dc)
        shared.full_scale = fs
        sh_state = State(shared, shared.start(y, t, r, valid, w, per_pixel=theta))
        sh_fit = evaluate(refit_base(y, data, sh_state), [], data, n_pix, n_light)
        if not equally_good(sh_fit, base_fit, valid_ho, noise_floor):
            per_pixel_start = (base, theta, base_fit, noise_floor)
            base, theta, base_fit = shared, sh_state.theta, sh_fit
            pred_var = _prediction_variance(base, theta, data)
            noise_floor = float(np.sqrt(np.mean((noise2 + pred_var)[valid_ho])))

    # which candidates can this design identify at all (next to this base)?
    skipped, testable, weak = _identifiable(names, base, theta, data, des, dark_desc)
    candidates: list = []
    ambiguous: list = []
    final = greedy(base_fit, testable, data, noise_floor, n_pix, n_light, candidates,
                   label=base.name, ambiguous=ambiguous, refloor=refloor)
    leakage = {"verdict": "not tested", "reason": "the base model is linear"}
    per_pixel = None  # the per-pixel leakage model, where one shape for the sensor replaced it
    if per_pixel_start is not None:
        # the search from the per-pixel model too, whole model against whole model: its
        # result is kept where it predicts the held-out data measurably better
        pp_base, pp_theta, pp_fit, pp_floor = per_pixel_start
        pp_skipped, pp_testable, pp_weak = _identifiable(names, pp_base, pp_theta, data, des,
                                                         dark_desc)
        pp_ambiguous: list = []
        pp_final = greedy(pp_fit, pp_testable, data, pp_floor, n_pix, n_light, candidates,
                          label=pp_base.name, ambiguous=pp_ambiguous, refloor=refloor)
        if not equally_good(pp_final, final, valid_ho, pp_floor):
            final, base_fit, noise_floor = pp_final, pp_fit, pp_floor
            skipped, weak, ambiguous = pp_skipped, pp_weak, pp_ambiguous
        else:
            per_pixel = (pp_final, pp_fit)
    if final.state.base.name == "leakage" and "pixel_nonlinearity" not in final.names:
        # the selected model with one leakage shape, kept when it explains the sweep as well
        # with fewer parameters. Not tried next to a per-pixel nonlinearity, which says that
        # the bend differs from pixel to pixel
        sh_final = (evaluate(fitpredict(final.names, data, sh_state), final.names, data, n_pix,
                             n_light) if final.names else sh_fit)
        if sh_final.bic < final.bic and equally_good(final, sh_final, valid_ho, noise_floor):
            per_pixel = (final, base_fit)
            final, base_fit = sh_final, sh_fit
    if base.name in ("leakage", "shared leakage"):
        lin = LinearBase(use_dc)
        lin_state = State(lin, lin.start(y, t, r, valid, w))
        # the same linearised base step as the leakage bases and every trial fit get
        lin_fit = evaluate(refit_base(y, data, lin_state), [], data, n_pix, n_light)
        skipped_lin, testable_lin, weak_lin = _identifiable(names, lin, lin_state.theta, data,
                                                            des, dark_desc)
        ambiguous_lin: list = []
        final, leakage = leakage_check(final, lin_fit, testable_lin, data, noise_floor, n_pix,
                                       n_light, des, candidates, ambiguous_lin,
                                       refloor=refloor)
        if final.state.base.name == "linear":
            skipped, weak, ambiguous = skipped_lin, weak_lin, ambiguous_lin
        if leakage["verdict"] == "cannot tell":
            ambiguous.append({"effects": leakage["models"], "reason": leakage["reason"]})
    # the frames' noise before rounding: integer data with frame pairs are simulated as the
    # ADC records them, so the rounding bias of quiet pixels (common to the pixels of a step)
    # is in the null
    sim_quantum = quantum if smp["pairs"] else 0.0

    def simulate_frames(level, n_frames, rng, sigma_step):
        """The mean of ``n_frames`` simulated frames per step around ``level`` (P, S)."""
        if sim_quantum <= 0:
            return level + sigma_step / np.sqrt(n_frames) * rng.standard_normal(level.shape)
        total = np.zeros(level.shape)
        for k in range(int(n_frames.max())):
            frame = np.round((level + sigma_step * rng.standard_normal(level.shape))
                             / sim_quantum)
            total += np.where(k < n_frames, frame * sim_quantum, 0.0)
        return total / np.maximum(n_frames, 1)

    def residual_check(fitted):
        """Structure left in the held-out residual of a fitted model, against what the model
        itself leaves: simulate it with the measured noise, refit, and measure the same
        residual structure (parametric bootstrap, 2 draws)."""
        cur = fitted.state
        ctx = context(cur.base, cur.theta, data)[2]
        groups = groupings(valid_ho, ctx.signal, light, rows, cols, band)
        # the model's own fit noise (its base may be less well determined next to an effect)
        pv = _prediction_variance(cur.base, cur.theta, data, cur)
        vs = var_step_of(cur)
        var_sample = noise2_of(cur, vs) + pv
        sd_sample = np.sqrt(var_sample)  # noise of each held-out sample, DN
        sigma_step = np.sqrt(ds.noise_before_rounding(vs, sim_quantum))
        rng = np.random.default_rng(seed + 1)
        null = {}
        for _ in range(2):
            y_sim = simulate_frames(cur.prediction, n_fit, rng, sigma_step)
            y_sim_ho = simulate_frames(cur.prediction + cur.ho_extra, smp["n_ho"], rng,
                                       sigma_step)
            if not smp["pairs"]:
                y_sim_ho = y_sim
            sim_data = Data(**{**data.__dict__, "y": y_sim, "y_ho": y_sim_ho})
            sim = (fitpredict(fitted.names, sim_data, cur, quick=True) if fitted.names
                   else refit_base(y_sim, sim_data, cur))
            sim_res = np.where(valid_ho, y_sim_ho - sim.prediction - sim.ho_extra, 0.0)
            for f in structure(sim_res, valid_ho, groups, noise_floor, sd=sd_sample)[0]:
                null[f["grouping"]] = max(null.get(f["grouping"], 0.0), f["null_statistic"])
        findings, structured = structure(fitted.res, valid_ho, groups, noise_floor, null=null,
                                         sd=sd_sample)
        return ctx, groups, var_sample, sd_sample, null, findings, structured

    ctx, groups, var_sample, sd_sample, null, findings, structured = residual_check(final)
    if structured and per_pixel is not None and final.state.base.name == "shared leakage":
        # one leakage shape is as good on the held-out error, but leaves a pattern over the
        # pixels: the per-pixel model is kept where it leaves none
        alt = residual_check(per_pixel[0])
        if not alt[-1]:
            final, base_fit = per_pixel
            ctx, groups, var_sample, sd_sample, null, findings, structured = alt
            leakage["shape"] = (
                "per pixel: one leakage shape for the sensor fits the held-out error as well "
                "with fewer parameters, but leaves a pattern over the pixels in the residual "
                "that the per-pixel model does not")
    current = final.state
    selected = final.names
    skipped = _with_weak(skipped, weak, selected)
    findings_before, _ = structure(base_fit.res, valid_ho, groups, noise_floor, null=null,
                                   sd=sd_sample)

    def figs(mse, floor):
        rms = float(np.sqrt(mse))
        return {"rms_dn": rms, "noise_floor_dn": floor,
                "systematic_rms_dn": float(np.sqrt(max(rms ** 2 - floor ** 2, 0.0)))}

    floor_after = float(np.sqrt(np.mean(var_sample[valid_ho])))

    after = figs(final.mse, floor_after)
    # honest verdict: systematic error left above half the noise floor is unexplained, whatever
    # the binned structure tests say (the figure printed and the sentence agree)
    too_big = after["systematic_rms_dn"] > UNEXPLAINED_OF_FLOOR * floor_after
    unexplained = bool(structured or too_big)
    chosen = []
    for name in selected:
        p = describe_params(name, current.effects[name][0])
        chosen.append({"name": name, "params": p, "interpretation": EFFECTS[name].interpret(p)})
    n_total = int(smp["usable"].sum() * n_pix)
    return {
        "dataset": str(sweep.source or "in-memory sweep"),
        "base_model": current.base.describe + ("; dark current from the dark frames" if use_dc
                                               else ", constant dark level"),
        "design": des.as_dict(), "leakage": leakage,
        "dark_model": ds.describe_dark_current(current.base.dc(current.theta), dark_desc),
        "n_pixels": int(n_pix), "n_pixels_sensor": int(np.prod(sweep.frame_shape)),
        "n_samples": int(valid_ho.sum()),
        "n_invalid_samples": int(n_total - (valid | valid_ho).sum()),
        "noise_floor_dn": noise_floor,
        "noise_source": ("frame pairs (second minus first frame of every step)" if smp["pairs"]
                         else "spread of the held-out residual across pixels within a step"),
        "before": figs(base_fit.mse, noise_floor), "after": after,
        "selected_effects": selected, "effects": chosen, "skipped": skipped,
        "candidates": candidates, "unexplained": unexplained,
        "unexplained_reason": _unexplained_reason(structured, too_big, after, floor_after),
        "ambiguous": ambiguous,
        "residual_structure_after": findings, "residual_structure_before": findings_before,
        "held_out": smp["held_out"], "selection_rule": RULE,
        "runtime_s": time.perf_counter() - t0,
        "_arrays": {"res_before": base_fit.res, "res_after": final.res, "valid": valid_ho,
                    "t": t, "signal": ctx.signal, "light": light, "order": order, "rows": rows,
                    "cols": cols, "band": band, "step": smp["step"]},
    }
