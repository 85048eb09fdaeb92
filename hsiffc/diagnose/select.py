"""Greedy selection of candidate effects on the held-out error, and the leakage check (is the
bending of the response leakage, or a readout nonlinearity that depends on the signal only?)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy import stats

from .effects import EFFECTS, FRAME_SIGNAL_OFFSET, OFFSET_PROBES, SMOOTH_PROBES
from .effectfit import fit_effect, frame_regression, gram, projector
from .fitting import Data, State, context, describe_params, fitpredict, pair_regression

SELECT_SIGMAS = 5.0  # held-out improvement needed, in standard errors of the paired difference
MIN_GAIN_OF_NOISE = 0.08  # ... and at least this fraction of the noise floor, as an RMS
MIN_EXPLAINED = 0.5  # ... and at least this fraction of the current systematic error
TIE_SIGMAS = 2.0  # two models whose held-out errors differ by less are equally good
LEFT_OFFSET_OF_FLOOR = 0.135  # an offset per step left counts above this RMS (of the noise)
#: effects a black-level clamp is taken for (an offset common to the pixels of a frame), whose
#: part that differs between the pixels of a frame the pixels must show
#: (:func:`frame_constant_stand_in`)
WITHIN_FRAME_TESTED = ("readout_nonlinearity", "illumination_error", "lamp_drift",
                       "frame_flicker")
WITHIN_FRAME_SIGMAS = 3.0  # the pixels of a frame refute that part by this many standard errors
WITHIN_FRAME_MAX_BETA = 0.25  # ... and show at most this fraction of it
PROBE_OF_DISTINCT = 0.75  # an offset probe must beat its effect by this fraction of the part
# of the effect that differs between the pixels of a frame (about 1 where the offset is true,
# about -1 where the effect is)
TREND_P = 5e-3  # per-step factors that trend with exposure, signal or order (F-test p below)
MIN_TREND_STEPS = 8  # fewer light steps: the trend test is not made
N_PERMUTATIONS = 8000  # random orders of the step factors in the trend test
LAG_STEPS = 3.0  # decay (steps) of the trend test's regressor for a lag over several frames
UNEXPLAINED_OF_FLOOR = 0.5  # systematic RMS left above this fraction of the noise: unexplained

RULE = (f"held-out mean squared error lower by more than {SELECT_SIGMAS:g} standard errors of the "
        f"paired difference, by more than ({MIN_GAIN_OF_NOISE:g} x noise floor)^2 and by more than "
        f"{MIN_EXPLAINED:g} of the current systematic error (which must itself exceed "
        f"({MIN_GAIN_OF_NOISE:g} x noise floor)^2, except for an effect between the halves of a "
        f"step where the frame differences, on which the floor is measured, fail the noise "
        f"model's test); a per-step effect only when its step factors "
        f"show no trend with exposure, signal, light rate, acquisition order or the signal of "
        f"the steps before, and their product with the signal no drift (p >= "
        f"{TREND_P:g}); a within-step effect only when the frame differences show its "
        f"coefficient at {SELECT_SIGMAS:g} standard errors; among those the lowest BIC, except a "
        f"within-step effect whose held-out error is lower than the BIC choice's by more than "
        f"{TIE_SIGMAS:g} standard errors (the fit-half BIC does not see it), and a sensor-wide "
        f"effect that passes the rule and predicts the held-out data as well as a per-step "
        f"effect that won (both fitted to convergence); then each selected "
        f"effect must still pass that rule next to the others (backward step)")


@dataclass
class Fitted:
    """A model with its held-out residual and figures.

    Parameters
    ----------
    state : State
        The fitted model.
    names : list of str
        Its effects.
    res : ndarray, (P, S), DN
        Held-out residual (0 outside the valid held-out samples).
    mse : float, DN^2
        Mean squared held-out residual.
    bic : float
        Bayesian information criterion of the fit half.
    n_params : int
        Free parameters.
    """

    state: State
    names: list
    res: np.ndarray  # held-out residual (P, S), 0 outside valid_ho
    mse: float
    bic: float
    n_params: int


def fitted_n_params(name: str, state: State, n_pix: int, n_light: int) -> int:
    """Free parameters effect ``name`` has in ``state`` (for the information criterion): those
    of its record (:meth:`~hsiffc.diagnose.effects.Effect.n_params`), except that a pooled
    per-pixel effect whose pixels all took the sensor's value
    (:func:`~hsiffc.diagnose.effectfit.pool_pixels`) has one value for the sensor: counted
    as ``P`` parameters it lost every comparison of the BIC to a sensor-wide effect (a readout
    nonlinearity or an offset drift beside a dark signal outside the photodiode).

    Parameters
    ----------
    name : str
        The effect.
    state : State
        A fitted model that holds it.
    n_pix, n_light : int
        Pixels and light steps.

    Returns
    -------
    int
    """
    effect = EFFECTS[name]
    fitted = state.effects.get(name)
    if effect.pooled and fitted is not None:
        theta = np.asarray(fitted[0])
        if theta.ndim == 2 and theta.shape[0] > 1 and np.ptp(theta, axis=0).max() == 0.0:
            return theta.shape[1]
    return effect.n_params(n_pix, n_light)


def evaluate(state: State, names, data: Data, n_pix: int, n_light: int) -> Fitted:
    """The held-out residual, MSE and BIC of a fitted state.

    Parameters
    ----------
    state : State
        With ``prediction`` set.
    names : sequence of str
        Its effects.
    data : Data
        The samples.
    n_pix : int
        Pixels analysed.
    n_light : int
        Light steps.

    Returns
    -------
    Fitted
    """
    vh, vf = data.valid_ho, data.valid
    res = np.where(vh, data.y_ho - state.prediction - state.ho_extra, 0.0)
    res_fit = np.where(vf, data.y - state.prediction, 0.0)
    n_ho, n_fit = max(int(vh.sum()), 1), max(int(vf.sum()), 1)
    k = (state.base.n_params * n_pix + state.base.n_shared
         + sum(fitted_n_params(n, state, n_pix, n_light) for n in names))
    rss_w = float((data.w * res_fit ** 2).sum())
    bic = n_fit * np.log(max(rss_w, 1e-300) / n_fit) + k * np.log(n_fit)
    mse = float((res ** 2).sum() / n_ho)
    return Fitted(state, list(names), res, mse if np.isfinite(mse) else np.inf, float(bic), k)


def refit(names, data: Data, state: State, n_pix: int, n_light: int, quick=False) -> Fitted:
    """The model with effects ``names`` fitted from ``state``
    (:func:`~hsiffc.diagnose.fitting.fitpredict`) and scored on the held-out half
    (:func:`evaluate`): what every comparison of two models fits.

    Parameters
    ----------
    names : sequence of str
        The effects.
    data : Data
        The samples.
    state : State
        Where the fit starts.
    n_pix, n_light : int
        Pixels analysed and light steps (for the BIC).
    quick : bool
        A trial fit (fewer rounds).

    Returns
    -------
    Fitted
    """
    return evaluate(fitpredict(names, data, state, quick=quick), names, data, n_pix, n_light)


def paired(a: Fitted, b: Fitted, valid_ho):
    """Mean and standard error of the held-out squared-error gain of b over a.

    Parameters
    ----------
    a, b : Fitted
        Two models of the same data.
    valid_ho : ndarray of bool, (P, S)
        Held-out samples.

    Returns
    -------
    gain, standard_error : float, DN^2
        Positive when b is better.
    """
    d = a.res[valid_ho] ** 2 - b.res[valid_ho] ** 2
    return float(d.mean()), float(d.std() / np.sqrt(max(d.size, 1)))


def _gauge(trial: Fitted, x, steps, data: Data):
    """Step-factor patterns the base model absorbs: for each base parameter, its Jacobian
    column over the effect's column, per step (median over the pixels). The factors of a
    per-step effect fitted jointly with the base are free along these (a constant is taken by
    the gain, one over the signal by the dark level, smooth bends by the leakage), so they
    are nuisance regressors of the trend test, not a trend."""
    _, jac, _ = context(trial.state.base, trial.state.theta, data)
    ok = data.valid[:, steps] & (np.abs(x[:, steps]) > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(ok[..., None], jac[:, steps, :] / x[:, steps, None], np.nan)
        g = np.nanmedian(ratio, axis=0)  # (n_steps, n_params)
    g = g[:, np.all(np.isfinite(g), axis=0) & (np.ptp(np.nan_to_num(g), axis=0) > 0)]
    return g


def _earlier_signal(signal, prev_index, n_back: int = 10):
    """Signal of the steps before each step (acquisition order), weighted ``exp(-(j - 1) /
    LAG_STEPS)`` for the ``j``-th step back: what a lag over several frames carries in."""
    out = np.zeros_like(signal)
    idx = np.asarray(prev_index).copy()
    for j in range(n_back):
        ok = idx >= 0
        if not ok.any():
            break
        out[:, ok] += np.exp(-j / LAG_STEPS) * signal[:, idx[ok]]
        idx = np.where(ok, prev_index[np.maximum(idx, 0)], -1)
    return out


def step_trend(trial: Fitted, name: str, data: Data):
    """Do the fitted per-step factors of effect ``name`` trend with exposure, signal, light
    rate, acquisition order, the previous step's signal or that of the steps before (a lag
    over several frames), or do the factors times the step's signal drift with acquisition
    order (an offset drift, whose factors look random where the signal jumps from step to
    step)? A per-step light error is random from step to step; factors that follow a smooth
    function of the step are the signature of a smooth misfit of the model (or of a lag longer
    than one step), which one free factor per step absorbs. The patterns the base model's own
    parameters absorb (:func:`_gauge`) are taken out of the factors first: they are not
    determined by the data.

    Parameters
    ----------
    trial : Fitted
        A model with the per-step effect.
    name : str
        The per-step effect.
    data : Data
        The samples.

    Returns
    -------
    str or None
        What the factors trend with (and the p-value), or None.
    """
    theta = np.asarray(trial.state.effects[name][0], float)
    if theta.ndim == 2:  # a frame effect: the factors of the fit half
        theta = theta[0]
    _, _, ctx = context(trial.state.base, trial.state.theta, data)
    x = EFFECTS[name].columns(ctx)[..., 0]
    den = (np.where(data.valid, data.w, 0.0) * x * x).sum(axis=0)
    steps = np.flatnonzero(data.light & (den > 0) & (theta != 0))
    if steps.size < MIN_TREND_STEPS:
        return None
    f = theta[steps]
    se2 = 1.0 / den[steps]

    def step_median(v):
        return np.array([np.median(v[data.valid[:, s], s]) if data.valid[:, s].any() else 0.0
                         for s in steps])
    sig = step_median(ctx.signal) / data.full_scale
    earlier = _earlier_signal(ctx.signal, data.prev_index)
    with np.errstate(invalid="ignore", divide="ignore"):
        prev = step_median(np.where(ctx.signal > 0, ctx.prev_signal / ctx.signal, 0.0))
        several = step_median(np.where(ctx.signal > 0, earlier / ctx.signal, 0.0))
    regs = {"exposure": np.log(data.t[steps]), "signal": sig, "signal^2": sig ** 2,
            "light rate": np.log(np.maximum(data.r[steps], 1e-12)),
            "acquisition order": data.order[steps],
            "the previous step's signal (a lag)": prev,
            f"the signal of the steps before (a lag decaying over {LAG_STEPS:g} steps)":
                several}
    regs = {k: v for k, v in regs.items() if np.ptp(v) > 1e-9 * (np.abs(v).max() + 1e-300)}
    if not regs:
        return None
    gauge = _gauge(trial, x, steps, data)
    scatter2 = max(float(np.var(f)) - float(np.mean(se2)), 0.0)
    wt = 1.0 / (se2 + scatter2 + 1e-300)
    sw = np.sqrt(wt)

    def std(c):
        return (c - c.mean()) / c.std()
    G = np.column_stack([np.ones(steps.size)] + [std(c) for c in gauge.T])
    n_g = np.linalg.matrix_rank(G * sw[:, None])
    if steps.size - n_g < MIN_TREND_STEPS // 2:  # the base absorbs nearly every pattern
        G = G[:, :1]
        n_g = 1
    # factors less what the base absorbs (weighted least squares on the gauge patterns)
    fg = f - G @ np.linalg.lstsq(G * sw[:, None], f * sw, rcond=None)[0]
    X = np.column_stack([G] + [std(c) for c in regs.values()])
    q = np.linalg.matrix_rank(X * sw[:, None]) - n_g
    if steps.size - n_g - q < 4:
        X = X[:, :n_g + 2]
        q = np.linalg.matrix_rank(X * sw[:, None]) - n_g
    dof = steps.size - n_g - q
    if q < 1 or dof < 1:
        return None
    full = np.linalg.lstsq(X * sw[:, None], f * sw, rcond=None)
    rss1 = float(((f - X @ full[0]) ** 2 * wt).sum())
    rss0 = float((fg ** 2 * wt).sum())
    if rss1 <= 0:
        return None
    fstat = ((rss0 - rss1) / q) / (rss1 / dof)
    p_poly = float(stats.f.sf(fstat, q, dof))
    # a smooth function of any one of them, whatever its shape: the factors sorted by it change
    # little from one step to the next. Robust ratio of successive differences to the spread
    # (medians: one odd step does not hide a trend), against random orders of the same
    # factors (permutation test); Bonferroni over the orderings
    names = [k for k in regs if k != "signal^2"]
    n = steps.size
    fc = (fg - np.median(fg)) * sw
    perm = np.argsort(np.random.default_rng(0).random((N_PERMUTATIONS, n)), axis=1)

    def ratio(v):  # v: (..., n)
        return (np.median(np.diff(v, axis=-1) ** 2, axis=-1)
                / np.maximum(np.median((v - np.median(v, axis=-1, keepdims=True)) ** 2,
                                       axis=-1), 1e-300))
    # and the factors times the step's signal (DN) in acquisition order: an offset that
    # drifts is smooth there, its factors are not (drift over a signal that jumps from step to
    # step in a mixed design). The null permutes the factors, not the products: the signal
    # itself may be smooth in acquisition order. What the base absorbs is taken out of the
    # products (the gauge patterns times the signal: an offset goes into the dark level)
    gs = G * sig[:, None]
    off_gauge = np.eye(n) - gs @ np.linalg.pinv(gs)
    orderings = [(k, np.argsort(regs[k], kind="stable"), None) for k in names]
    if "acquisition order" in regs and "signal" in regs:
        orderings.append(("an offset drifting with acquisition order (the factors times the "
                          "signal)", np.argsort(regs["acquisition order"], kind="stable"),
                          ((fg * sig) @ off_gauge.T, (fg[perm] * sig) @ off_gauge.T)))
    null_fc = ratio(fc[perm])
    p_vn, by = 1.0, names[0] if names else "signal"
    for k, idx, v in orderings:
        r_k, null = ((ratio(fc[idx]), null_fc) if v is None else
                     (ratio(v[0][idx]), ratio(v[1][:, idx])))
        pk = (1 + np.sum(null <= r_k)) / (1 + N_PERMUTATIONS) * len(orderings)
        if pk < p_vn:
            p_vn, by = float(pk), k
    p = min(2 * p_poly, 2 * p_vn)
    if p >= TREND_P:
        return None
    if p_poly < p_vn:  # which single regressor follows the factors best (for the report)
        r2 = [abs(np.corrcoef(regs[k], fg)[0, 1]) if np.ptp(fg) > 0 else 0.0 for k in names]
        by = names[int(np.argmax(r2))]
    return (f"its step factors follow {by} smoothly (p = {p:.2g} against factors independent "
            "from step to step, beyond what the base model absorbs): a smooth misfit of the "
            "model, not a random light error per step")


def between_halves(name: str) -> bool:
    """Does effect ``name`` predict a difference between the fit and held-out halves of a
    step (a within-step effect, a ``frame`` effect, or one with its own held-out columns)? Its
    evidence is then in the frame differences, which the fit-half BIC cannot see.

    Parameters
    ----------
    name : str

    Returns
    -------
    bool
    """
    e = EFFECTS[name]
    return e.scope in ("pair", "frame") or (e.ho_columns is not None
                                             and not e.steps_are_evidence)


def _pair_z(x, d, w):
    """Coefficient of ``d`` on ``x`` (weights ``w``, flat arrays) in standard errors (from
    the scatter of ``d`` about the fit); None where ``x`` is zero."""
    den = float((w * x * x).sum())
    if den <= 0:
        return None
    c = float((w * x * d).sum()) / den
    scale = float((w * (d - c * x) ** 2).sum()) / max(d.size - 1, 1)
    return abs(c) / np.sqrt(max(scale, 1e-300) / den)


def pair_evidence(trial: Fitted, name: str, data: Data):
    """Do the frame differences themselves show the effect ``name`` that acts between the
    halves of a step (:func:`between_halves`)? Its part between the halves is fitted on them
    (the held-out frames of a step minus the fit frames), so they are its only evidence: the
    held-out gain can also come from a coefficient that is noise times a misfit of the base
    model that follows the effect's column, which the paired standard error does not count.
    Accepted where the coefficient is ``SELECT_SIGMAS`` standard errors from zero (the
    standard error from the scatter of the frame differences about the fit); for a factor per
    step (``frame``), where the factors together are as unlikely under noise (chi-square).

    Parameters
    ----------
    trial : Fitted
        A model with the effect.
    name : str
        The effect.
    data : Data
        The samples.

    Returns
    -------
    str or None
        Why the effect is not shown (with the figure), or None.
    """
    effect = EFFECTS[name]
    _, _, ctx = context(trial.state.base, trial.state.theta, data)
    if effect.scope == "frame":
        x, ok, d = frame_regression(effect, ctx, data)
        chi2, dof = 0.0, 0
        for s in np.flatnonzero(ok.any(axis=0)):
            z = _pair_z(x[ok[:, s], s], d[ok[:, s], s], data.w[ok[:, s], s])
            if z is not None:
                chi2, dof = chi2 + z * z, dof + 1
        if dof == 0:
            return "no light step has both halves valid"
        p = float(stats.chi2.sf(chi2, dof))
        if p < 2 * stats.norm.sf(SELECT_SIGMAS):
            return None
        return (f"the frame differences show its factors at p = {p:.2g} only (chi-square "
                f"{chi2:.3g} on {dof} steps; needs the equivalent of {SELECT_SIGMAS:g} standard "
                "errors): the frames of a step agree")
    if effect.scope == "pair":
        x, ok, d = pair_regression(effect, ctx, data)
    else:  # its own held-out columns: the difference they predict between the halves
        x = (effect.ho_columns(ctx) - effect.columns(ctx))[..., 0]
        ok = data.valid & data.valid_ho
        d = np.where(ok, data.y_ho - data.y, 0.0)
    ok &= np.isfinite(x)
    if not ok.any():
        return "no step has both frames valid"
    z = _pair_z(x[ok], d[ok], data.w[ok])
    if z is None:
        return "its column is zero on every valid step"
    if z >= SELECT_SIGMAS:
        return None
    return (f"the frame differences show it at {z:.2g} standard errors only (needs "
            f"{SELECT_SIGMAS:g}): its held-out gain comes from a misfit of the model, not from a "
            "change within the step")


def greedy(start: Fitted, names, data: Data, noise_floor: float, n_pix: int, n_light: int,
           candidates: list, label: str, ambiguous: list | None = None,
           refloor=None) -> Fitted:
    """Add effects while one beats the current model by more than the noise allows.

    Parameters
    ----------
    start : Fitted
        The model to grow (the base alone, usually).
    names : sequence of str
        Candidate effects.
    data : Data
        The samples.
    noise_floor : float, DN
        Temporal noise of one held-out sample.
    n_pix, n_light : int
        Pixels and light steps.
    candidates : list
        Filled with one dict per candidate tried (the report's table).
    label : str
        Which selection this is (for the table).
    ambiguous : list, optional
        Filled with the ties between candidates of a round.
    refloor : callable, optional
        ``refloor(fitted, noise_floor)``: the noise floor for a model with a within-step
        effect, whose frame differences (where the noise is measured) hold that effect too.

    Returns
    -------
    Fitted
        The selected model.
    """
    floor0 = noise_floor
    current = start
    for round_ in range(len(names)):
        passed = []
        for name in names:
            if name in current.names:
                continue
            trial = refit(current.names + [name], data, current.state, n_pix, n_light, quick=True)
            entry, beats = _tried(current, trial, name, data, noise_floor, label, round_)
            candidates.append(entry)
            if beats:
                passed.append((trial, entry))
        if not passed:
            break
        # among those that pass, the most parsimonious (lowest BIC): a per-step effect predicts
        # the held-out frame of its own step and would otherwise absorb what is common to a step
        best = min(passed, key=lambda p: p[0].bic)
        # a within-step effect changes only the held-out half, which the fit-half BIC cannot
        # see: it is chosen instead when its held-out error is measurably lower
        for trial, entry in passed:
            if (between_halves(entry["name"]) and not between_halves(best[1]["name"])
                    and trial is not best[0]):
                gain, se = paired(best[0], trial, data.valid_ho)
                if gain > TIE_SIGMAS * se:
                    best = (trial, entry)
        full = None  # the round's choice fitted to convergence, where already fitted
        if EFFECTS[best[1]["name"]].scope in ("step", "frame"):
            best, full = _sensor_wide_rival(current, best, names, data, noise_floor, n_pix,
                                            n_light, candidates, label, round_, ambiguous)
        best[1]["selected_in_round"] = True
        if ambiguous is not None:
            for trial, entry in passed:
                if trial is best[0] or not equally_good(best[0], trial, data.valid_ho,
                                                        noise_floor):
                    continue
                if not equally_good(trial, best[0], data.valid_ho, noise_floor):
                    continue
                pair = {best[1]["name"], entry["name"]}
                if any(set(a["effects"]) == pair for a in ambiguous):
                    continue  # reported already (a sensor-wide rival's tie)
                ambiguous.append({
                    "effects": [best[1]["name"], entry["name"]],
                    "reason": (f"both fit the held-out data equally well (held-out RMS "
                               f"{np.sqrt(best[0].mse):.4g} and {np.sqrt(trial.mse):.4g} DN, "
                               f"within {TIE_SIGMAS:g} standard errors); "
                               f"{best[1]['name']} is kept as the more parsimonious (BIC "
                               f"{best[0].bic:.6g} against {trial.bic:.6g})")})
        chosen = best[0].names
        if full is None:
            full = fitpredict(chosen, data, current.state)
        # the next round's trials each get a linearised base step from this fit: so does the
        # model they are measured against (a base fit short of its optimum would credit that
        # step to whichever effect is tried next)
        current = refit(chosen, data, full, n_pix, n_light, quick=True)
        if refloor is not None:
            noise_floor = refloor(current, floor0)
    return backward(current, start, data, floor0, n_pix, n_light, candidates, label, refloor)


def _tried(current: Fitted, trial: Fitted, name: str, data: Data, noise_floor: float,
           label: str, round_: int) -> tuple[dict, bool]:
    """The report's entry for ``trial`` (``current`` + effect ``name``) and whether it beats
    ``current`` (:func:`_beats`)."""
    gain, se = paired(current, trial, data.valid_ho)
    entry = _entry(name, label, round_ + 1, trial, gain, se,
                   max(current.mse - noise_floor ** 2, 1e-12),
                   describe_params(name, trial.state.effects[name][0]))
    return entry, _beats(current, trial, name, gain, se, data, noise_floor, entry)


def _entry(name: str, label: str, round_, model: Fitted, gain: float, se: float,
           systematic2: float, params: dict) -> dict:
    """A row of the report's candidate table: effect ``name`` tried in ``round_`` of the
    search from base ``label`` gave ``model``, whose held-out mean squared error is ``gain``
    (standard error ``se``) below that of the model without it, whose systematic error
    (squared) was ``systematic2``."""
    return {"name": name, "base": label, "round": round_,
            "heldout_rms_dn": float(np.sqrt(model.mse)), "criterion": model.bic,
            "criterion_name": "BIC (fit half, weighted)",
            "heldout_mse_gain_dn2": gain, "gain_standard_error_dn2": se,
            "explained_fraction_of_systematic": float(gain / systematic2),
            "params": params, "selected_in_round": False}


def _sensor_wide_rival(current: Fitted, best: tuple, names, data: Data, noise_floor: float,
                       n_pix: int, n_light: int, candidates: list, label: str, round_: int,
                       ambiguous: list | None) -> tuple:
    """A per-step effect (one free factor a step) won the round: is there an effect shared by
    the sensor (a few parameters) that explains the held-out data as well, each fitted to
    convergence? One factor a step absorbs whatever the model misses smoothly (an exposure
    offset is a factor ``1 + t0 / t`` a step), and the quick trial fit, one linearised step of
    the base, can leave a nonlinear sensor-wide effect short of its fit (a leakage shape
    shared by the pixels moves with it). Such a rival, where it passes the selection rule
    itself, is the more parsimonious explanation and is chosen instead; where the per-step
    effect is as good too, the tie is reported.

    Returns
    -------
    choice : tuple
        ``(trial, entry)`` of the round's choice.
    state : State
        That choice fitted to convergence (for the next round to start from).
    """
    step_name = best[1]["name"]
    chosen = current.names + [step_name]
    step_full = refit(chosen, data, current.state, n_pix, n_light)
    rivals = []
    for name in names:
        if name in current.names or EFFECTS[name].scope != "global":
            continue
        trial = refit(current.names + [name], data, current.state, n_pix, n_light)
        entry, beats = _tried(current, trial, name, data, noise_floor, label, round_)
        entry["fit"] = f"to convergence, as a rival of {step_name}"
        candidates.append(entry)
        if beats and equally_good(step_full, trial, data.valid_ho, noise_floor):
            rivals.append((trial, entry))
    if not rivals:
        return best, step_full.state
    rival = min(rivals, key=lambda p: p[0].mse)
    if ambiguous is not None and equally_good(rival[0], step_full, data.valid_ho, noise_floor):
        k = rival[0].n_params - current.n_params
        ambiguous.append({
            "effects": [rival[1]["name"], step_name],
            "reason": (f"both fit the held-out data equally well (held-out RMS "
                       f"{np.sqrt(rival[0].mse):.4g} and {np.sqrt(step_full.mse):.4g} DN, each "
                       f"fitted to convergence); {rival[1]['name']} ({k} parameter"
                       f"{'s' if k > 1 else ''}) is kept as the more parsimonious than a factor "
                       f"for every step")})
    return rival, rival[0].state


def improves(current: Fitted, trial: Fitted, gain: float, se: float, noise_floor: float,
             floor_holds_it: bool = False) -> bool:
    """The held-out part of the selection rule: ``trial`` lowers ``current``'s held-out error
    by ``SELECT_SIGMAS`` paired standard errors, by more than ``(MIN_GAIN_OF_NOISE`` x floor)^2
    and by ``MIN_EXPLAINED`` of the systematic error left (which must exceed that square).

    Parameters
    ----------
    current, trial : Fitted
        Two models of the same data.
    gain, se : float, DN^2
        :func:`paired` (``current``, ``trial``).
    noise_floor : float, DN
        Temporal noise of one held-out sample.
    floor_holds_it : bool
        The floor was measured on frame differences that hold the effect tried (an effect
        between the halves of a step where the differences failed the noise model's test):
        the systematic error measured against that floor understates what is left, so it
        need not exceed the square above (the gain must, and its own evidence is asked of the
        frame differences, :func:`pair_evidence`).

    Returns
    -------
    bool
    """
    systematic2 = max(current.mse - noise_floor ** 2, 1e-12)
    floor2 = (MIN_GAIN_OF_NOISE * noise_floor) ** 2
    return bool(np.isfinite(trial.mse) and np.isfinite(trial.bic)
                and (floor_holds_it or current.mse - noise_floor ** 2 > floor2)
                and gain > SELECT_SIGMAS * se and gain > floor2
                and gain > MIN_EXPLAINED * systematic2)


def _beats(current: Fitted, trial: Fitted, name: str, gain: float, se: float, data: Data,
           noise_floor: float, entry: dict) -> bool:
    """Does ``trial`` (``current`` + effect ``name``) beat ``current`` by more than the noise
    allows: a held-out gain of ``SELECT_SIGMAS`` paired standard errors, above the floor and
    a fraction of the systematic error left, and (per step) factors without a trend or
    (within a step) the frame differences' own evidence? ``entry["rejected"]`` says why not,
    where one of the last two refuses it."""
    beats = improves(current, trial, gain, se, noise_floor,
                     floor_holds_it=data.frames_differ and between_halves(name))
    if beats and between_halves(name):
        weak_pair = pair_evidence(trial, name, data)
        if weak_pair:
            entry["rejected"] = weak_pair
            beats = False
    if beats and EFFECTS[name].scope in ("step", "frame"):
        trend = step_trend(trial, name, data)
        if trend:
            entry["rejected"] = trend
            beats = False
    return beats


def _with_effects(st: State, m, project, total, data: Data) -> Fitted:
    """``st``'s base (model ``m`` at its parameters, ``project`` its linearised fit) with the
    effect predictions ``total`` in place of its own, the base refitted (linearised) to what
    they leave, evaluated on the held-out data."""
    r = np.where(data.valid, data.y - m - total, 0.0)
    s = State(st.base, st.theta, st.effects)
    s.prediction = m + (r - project(r)) + total
    s.ho_extra = st.ho_extra
    return evaluate(s, [], data, 1, 1)


def offset_stand_in(fitted: Fitted, name: str, data: Data):
    """Does selected effect ``name`` stand in for an offset common to the pixels of a frame
    (:data:`~hsiffc.diagnose.effects.OFFSET_PROBES`: a black-level clamp that follows the
    frame's signal is one, outside the library)? The effect and its probe are each fitted on
    what the other effects and the base leave (jointly with the base, linearised), and their
    held-out errors compared: the probe predicts the held-out data better by more than
    ``TIE_SIGMAS`` paired standard errors and by more than ``PROBE_OF_DISTINCT`` of the part of
    the effect that differs between the pixels of a frame (its mean square about each step's
    mean over the pixels; of an effect fitted jointly with the base, the part of it the base
    cannot absorb): that part is what the two disagree on, so the probe gains about it
    where the offset is true and loses about it where the effect is. A light error scales each
    pixel's signal and a readout nonlinearity bends it by its own signal; pixels of different
    signal in one frame tell those from an offset the same for all of them.

    Where the pixels of a frame see nearly one signal that part is too small to tell, but a
    per-step effect (:data:`~hsiffc.diagnose.effects.SMOOTH_PROBES`) has one more test: an
    offset that follows the frame's mean signal (a few parameters) that predicts the held-out
    data as well as its factors (not worse by ``TIE_SIGMAS`` standard errors) says that the
    factors follow the signal level, as a misfit of the model does, not a light error, which
    is random from step to step.

    Parameters
    ----------
    fitted : Fitted
        The selected model.
    name : str
        One of its effects.
    data : Data
        The samples.

    Returns
    -------
    dict or None
        ``gain_dn2`` and ``standard_error_dn2`` of the probe over the effect, ``explained_dn2``
        by the effect, ``distinct_dn2`` (its part that differs between a frame's pixels), and
        ``reason``; None where the effect has no probe or the probe is not
        better.
    """
    probe, smooth = OFFSET_PROBES.get(name), SMOOTH_PROBES.get(name)
    st = fitted.state
    if (probe is None and smooth is None) or name not in st.effects:
        return None
    m, jac, ctx = context(st.base, st.theta, data)
    project = projector(jac, data.w)
    others = st.sum_effects(m.shape, skip=name)
    res0 = np.where(data.valid, data.y - m - others, 0.0)

    def with_(effect):
        pred = fit_effect(effect, ctx, res0, data.w, project)[1]
        return _with_effects(st, m, project, others + pred, data), pred
    without = _with_effects(st, m, project, others, data)
    with_effect, pred = with_(EFFECTS[name])
    # its part that differs between a frame's pixels (as it is fitted: jointly with the base,
    # less what the base absorbs, for a sensor-wide or per-pixel effect)
    vf, vh = data.valid, data.valid_ho
    apart = np.where(vf, pred - np.where(vf, pred, 0.0).sum(axis=0)
                     / np.maximum(vf.sum(axis=0), 1), 0.0)
    if EFFECTS[name].scope in ("global", "pixel"):
        apart = apart - project(apart)
    distinct = float((np.where(vh, apart, 0.0) ** 2).sum() / max(int(vh.sum()), 1))
    explained = paired(without, with_effect, vh)[0]
    out = {"explained_dn2": explained, "distinct_dn2": distinct}
    if probe is not None:
        gain, se = paired(with_effect, with_(probe)[0], vh)
        if gain > TIE_SIGMAS * se and gain > PROBE_OF_DISTINCT * distinct:
            return {**out, "gain_dn2": gain, "standard_error_dn2": se, "reason": (
                f"what it explains is better explained by {probe.summary} (held-out squared "
                f"error lower by {gain:.3g} +- {se:.2g} DN^2, where the two differ by "
                f"{distinct:.3g} DN^2 between the pixels of a frame; the effect explains "
                f"{explained:.3g} DN^2): an offset the same for every pixel of a frame, such as "
                "a black-level clamp that follows the frame's signal, which the library does "
                "not describe")}
    if smooth is not None:
        gain, se = paired(with_effect, with_(smooth)[0], vh)
        if gain > -TIE_SIGMAS * se:
            return {**out, "gain_dn2": gain, "standard_error_dn2": se, "reason": (
                f"its step factors follow the frame's signal: {smooth.summary} "
                f"({smooth.n_params(1, 1)} parameters) predicts the held-out data as well as "
                f"one factor per step (held-out squared error lower by {gain:.3g} +- {se:.2g} "
                f"DN^2; the effect explains {explained:.3g} DN^2): a misfit of the model that "
                "follows the signal level, such as a black-level clamp, not a light error, "
                "which is random from step to step")}
    return None


def _probe_added(st: State, probe, data: Data) -> Fitted:
    """``st`` with the offset ``probe`` fitted to what it leaves, jointly with the base
    (linearised), evaluated on the held-out data."""
    m, jac, ctx = context(st.base, st.theta, data)
    project = projector(jac, data.w)
    total = st.sum_effects(m.shape)
    res0 = np.where(data.valid, data.y - m - total, 0.0)
    total = total + fit_effect(probe, ctx, res0, data.w, project)[1]
    return _with_effects(st, m, project, total, data)


def offset_left(fitted: Fitted, data: Data, noise_floor: float):
    """Is an offset common to the pixels of each light step left in what ``fitted`` does not
    explain (an effect the library lacks, such as a black-level clamp that follows the frame's
    signal)? One offset per light step (DN, the same for every pixel,
    :data:`~hsiffc.diagnose.effects.OFFSET_PROBES` ``illumination_error``'s probe) is fitted
    to the residual, jointly with the base (linearised), and must pass the selection rule's
    held-out test against ``fitted`` (:func:`improves`) and explain more than
    ``LEFT_OFFSET_OF_FLOOR`` of the noise floor as an RMS (a real sweep's offset that wanders
    by a few hundredths of its noise from step to step is not a finding): a light error, a
    drift of the offset or a lamp drift the model holds leave nothing for it.

    Parameters
    ----------
    fitted : Fitted
        The selected model.
    data : Data
        The samples.
    noise_floor : float, DN
        Temporal noise of one held-out sample.

    Returns
    -------
    dict or None
        ``gain_dn2``, ``standard_error_dn2`` and ``reason``; None where nothing is left.
    """
    trial = _probe_added(fitted.state, OFFSET_PROBES["illumination_error"], data)
    gain, se = paired(fitted, trial, data.valid_ho)
    if not (improves(fitted, trial, gain, se, noise_floor)
            and gain > (LEFT_OFFSET_OF_FLOOR * noise_floor) ** 2):
        return None
    return {"gain_dn2": gain, "standard_error_dn2": se,
            "reason": (f"an offset common to the pixels of each light step is left (one per step "
                       f"lowers the held-out squared error by {gain:.3g} +- {se:.2g} DN^2, "
                       f"{np.sqrt(gain) / noise_floor:.2g} of the noise floor as an RMS, and "
                       "passes the selection rule): the library does not describe it (a "
                       "black-level clamp that follows the frame's signal is one such effect)")}


def _per_light_step(x, light):
    """(P, S, L): column ``i`` holds ``x`` (P, S) at the ``i``-th light step (indices
    ``light``) and zero elsewhere."""
    out = np.zeros(x.shape + (light.size,))
    out[:, light, np.arange(light.size)] = x[:, light]
    return out


def _step_columns(effect, ctx):
    """The columns of a sensor-wide effect (P, S, m), or of a per-step or per-frame one with
    one column for each light step (its factor there)."""
    x = effect.columns(ctx)
    if effect.scope == "global":
        return x
    return _per_light_step(x[..., 0], np.flatnonzero(ctx.light))


def frame_constant_stand_in(fitted: Fitted, names, data: Data):
    """Do the pixels of a frame show the part of effects ``names`` that differs between them?

    A black-level clamp moves every pixel of a frame by the same DN; a light error, a flicker
    or a lamp drift scales each pixel's own light signal, and a readout nonlinearity bends it
    by its own signal, so between the pixels of one frame (PRNU, the bands of a mosaic, a
    non-uniform light) these effects differ and a clamp does not. Their summed prediction
    ``u`` (fit half, DN) is fitted to what the other effects leave, beside one offset per
    light step common to the pixels and the base (linearised): the offsets take the part of
    ``u`` common to a frame, so its coefficient ``beta`` is measured on the part that differs
    between a frame's pixels alone. Where the effects are true ``beta`` is 1; where they stand
    in for an offset common to the pixels of a frame, 0. They are stand-ins where ``beta`` is
    below ``WITHIN_FRAME_MAX_BETA`` and ``WITHIN_FRAME_SIGMAS`` standard errors below 1 (the
    standard error from the scatter about the fit; the other selected effects are fitted
    jointly, free, as nuisances). Where the pixels of a frame see nearly one signal the standard
    error is large and nothing is decided, and so it is on the per-pixel leakage base: there
    the part of ``u`` that differs between the pixels follows each pixel's fitted leakage
    shape, whose noise pulls ``beta`` towards 0 (errors in the variables: development seed
    464, a true light error at 5x on a 16-bit sensor driven into its leakage, 0.11 +- 0.14);
    on the linear base and the one with one leakage shape for the sensor it follows each
    pixel's gain, which the sweep measures well. All of ``names`` are judged together: a light error
    beside a readout nonlinearity takes the part of the nonlinearity that a per-step slope in
    the pixel's signal can (development seeds 100976 and 102068, black clamps).

    Parameters
    ----------
    fitted : Fitted
        The selected model.
    names : sequence of str
        Its effects to judge (those of ``WITHIN_FRAME_TESTED`` are).
    data : Data
        The samples.

    Returns
    -------
    dict or None
        ``beta``, ``standard_error``, ``effects`` (those judged) and ``reason``; None where
        the pixels of a frame do not refute them.
    """
    names = [n for n in names if n in WITHIN_FRAME_TESTED and n in fitted.state.effects]
    light = np.flatnonzero(data.light)
    if not names or light.size == 0 or fitted.state.base.name == "leakage":
        return None
    st = fitted.state
    m, jac, ctx = context(st.base, st.theta, data)
    # the other effects are nuisances, fitted jointly: a per-pixel one with the base, the
    # others beside the offsets
    others = [EFFECTS[n] for n in fitted.names if n not in names and EFFECTS[n].scope != "pair"]
    jac = np.concatenate([jac] + [e.columns(ctx) for e in others if e.scope == "pixel"], axis=-1)
    extra = [_step_columns(e, ctx) for e in others if e.scope != "pixel"]
    # one weight a step (the median of its pixels'): a handful of pixels whose noise model
    # gives them a variance near zero held 95 % of the weight of a frame (development seed
    # 100088, a flicker, at 1.4 ms), and the comparison is between the pixels of a frame
    w = np.where(data.valid, [np.median(data.w[v, s]) if v.any() else 0.0
                              for s, v in enumerate(data.valid.T)], 0.0)
    project = projector(jac, w)
    u = sum(st.effects[n][1] for n in names)
    res = np.where(data.valid, data.y - m - st.sum_effects(m.shape) + u, 0.0)
    offsets = _per_light_step(np.ones(m.shape), light)  # one offset per light step
    z = project(np.concatenate([offsets] + extra + [u[..., None]], axis=-1))
    a = gram(z, w, z).sum(axis=0)
    a += 1e-12 * np.trace(a) / a.shape[0] * np.eye(a.shape[0])
    pres = project(res)
    coef = np.linalg.lstsq(a, gram(z, w, pres[..., None]).sum(axis=0)[:, 0], rcond=None)[0]
    left = pres - z @ coef
    dof = int(data.valid.sum()) - jac.shape[-1] * m.shape[0] - a.shape[0]
    if dof < 1:
        return None
    scale2 = float((w * left ** 2).sum()) / dof
    se = float(np.sqrt(max(np.linalg.pinv(a)[-1, -1] * scale2, 0.0)))
    beta = float(coef[-1])
    if not (np.isfinite(beta) and se > 0 and beta < WITHIN_FRAME_MAX_BETA
            and 1 - beta > WITHIN_FRAME_SIGMAS * se):
        return None
    what = " and ".join(names)
    return {"beta": beta, "standard_error": se, "effects": names, "reason": (
        f"the pixels of a frame do not show what {what} predict{'s' if len(names) == 1 else ''} "
        f"between them: fitted beside an offset per light step common to the pixels, the "
        f"data take {beta:.2f} +- {se:.2f} of that part where the effect needs 1 "
        f"({(1 - beta) / se:.1f} standard errors below): what it explains is an offset the same "
        "for every pixel of a frame, such as a black-level clamp that follows the frame's "
        "signal, which the library does not describe")}


def leakage_stand_in(final: Fitted, linear: Fitted, shared: Fitted | None, data: Data,
                     noise_floor: float):
    """Does the leakage base of ``final`` stand in for an offset common to the pixels of a
    frame? A black-level clamp that moves only the brightest steps of a linear sensor bends
    the top of every pixel's response, and a leakage model takes it up, leaving nothing for
    an effect. A linear response (``linear``, with ``final``'s effects) with an offset that
    follows the frame's mean signal (:data:`~hsiffc.diagnose.effects.FRAME_SIGNAL_OFFSET`,
    fitted jointly with the base, linearised) is compared with ``final`` and with the leakage
    model with one shape for the sensor (``shared``, with ``final``'s effects), which has as
    few parameters a pixel as the linear one (per-pixel leakage follows the noise of the fit
    half, so any simpler model predicts the held-out data a little better): where it predicts
    the held-out data better than both by the selection rule's margin (``SELECT_SIGMAS``
    paired standard errors and ``(MIN_GAIN_OF_NOISE`` x floor)^2; the systematic error left
    may be nil, as the leakage took it up), the bending is not shown to be leakage.

    Parameters
    ----------
    final : Fitted
        The selected model (a leakage base; None is returned for a linear one).
    linear : Fitted
        The linear base alone.
    shared : Fitted or None
        The leakage base with one shape for the sensor, alone (None: not fitted; the test is
        not made).
    data : Data
        The samples.
    noise_floor : float, DN
        Temporal noise of one held-out sample.

    Returns
    -------
    dict or None
        ``gain_dn2``, ``standard_error_dn2`` (over the better of the two leakage models) and
        ``reason``.
    """
    if final.state.base.name == "linear" or shared is None:
        return None

    def with_effects(start: Fitted) -> Fitted:
        if not final.names:
            return start
        return refit(final.names, data, start.state, data.y.shape[0], int(data.light.sum()),
                     quick=True)
    trial = _probe_added(with_effects(linear).state, FRAME_SIGNAL_OFFSET, data)
    leak = final if final.state.base.name != "leakage" else with_effects(shared)
    gain, se = min(paired(final, trial, data.valid_ho), paired(leak, trial, data.valid_ho),
                   key=lambda g: g[0] - SELECT_SIGMAS * g[1])
    if not (gain > SELECT_SIGMAS * se and gain > (MIN_GAIN_OF_NOISE * noise_floor) ** 2):
        return None
    return {"gain_dn2": gain, "standard_error_dn2": se, "reason": (
        f"the leakage model stands in for an offset common to the pixels of a frame: a linear "
        f"response with {FRAME_SIGNAL_OFFSET.summary} predicts the held-out data better than "
        f"the leakage model, per pixel and with one shape for the sensor (squared error lower "
        f"by {gain:.3g} +- {se:.2g} DN^2), so the bending it takes up is not shown to be "
        "leakage; such an offset (a black-level clamp that follows the frame's signal) is "
        "outside the library")}


def backward(current: Fitted, start: Fitted, data: Data, noise_floor: float, n_pix: int,
             n_light: int, candidates: list, label: str, refloor=None) -> Fitted:
    """The backward step of the search: each selected effect must still beat the model of the
    others by the rule that let it in (:func:`_beats`), now that they are all there. An effect
    chosen early can be made unnecessary by one chosen later (a per-step light error that
    absorbed part of a smooth misfit before the smooth effect was in). Of those that fail, one
    is dropped, and the rest checked again: first one refused for what it is (per-step factors
    that now follow a trend, a within-step effect the frame differences do not show), and of
    those the one whose removal leaves the lowest BIC: two effects that can stand in for each
    other each look unneeded next to the other, and the forward search too keeps the most
    parsimonious of the models that pass. Each effect is judged as the forward search judged
    it: added back to the model of the others by a quick fit. Where the effect to drop is a
    smooth one and a per-step effect of the model shows a trend without it, the per-step
    effect was standing in for it: the per-step effect is dropped instead where the model
    explains the data without it (systematic error within ``UNEXPLAINED_OF_FLOOR`` of the
    floor), and both are kept otherwise.

    Parameters
    ----------
    current : Fitted
        The model the forward search selected.
    start : Fitted
        The model it started from (the others are refitted from there, as the forward
        search fits each model).
    data, noise_floor, n_pix, n_light, candidates, label, refloor
        As for :func:`greedy` (``noise_floor`` that of its start); ``candidates`` gets an
        entry for each effect dropped.

    Returns
    -------
    Fitted
        The model with only effects that each beat the others.
    """
    while len(current.names) > 1:
        failing, reduced = [], {}
        for name in current.names:
            rest = [n for n in current.names if n != name]
            full = fitpredict(rest, data, start.state)
            without = refit(rest, data, full, n_pix, n_light, quick=True)
            # the effect added back as the forward search adds one (a quick fit from the model
            # without it), so that it is judged by the rule that let it in
            back = refit(current.names, data, without.state, n_pix, n_light, quick=True)
            reduced[name] = without
            gain, se = paired(without, back, data.valid_ho)
            floor = noise_floor if refloor is None else refloor(without, noise_floor)
            entry = _entry(name, label, "backward", back, gain, se,
                           max(without.mse - floor ** 2, 1e-12),
                           describe_params(name, current.state.effects[name][0]))
            if not _beats(without, back, name, gain, se, data, floor, entry):
                # refused for what it is (step factors with a trend, a within-step effect the
                # frame differences do not show) before refused for its size; then the one
                # whose removal leaves the most parsimonious model
                failing.append(((0 if "rejected" in entry else 1, without.bic), name, entry))
        drop = None
        for _, name, entry in sorted(failing, key=lambda f: f[0]):
            stand_in = None
            if EFFECTS[name].scope not in ("step", "frame"):
                stand_in = next((o for o in reduced[name].names
                                 if EFFECTS[o].scope in ("step", "frame")
                                 and step_trend(reduced[name], o, data)), None)
            if stand_in is None:
                drop = (reduced[name], {**entry, "rejected": entry.get("rejected", (
                    "the other selected effects leave it nothing to explain beyond the "
                    "noise (backward step)"))})
                break
            # a per-step effect follows any smooth misfit with its free factor per step, and
            # it does so here once the smooth effect is gone: the smooth effect is kept, and
            # the per-step one goes where the model explains the data without it
            without = reduced[stand_in]
            floor = noise_floor if refloor is None else refloor(without, noise_floor)
            if without.mse - floor ** 2 <= (UNEXPLAINED_OF_FLOOR * floor) ** 2:
                gain, se = paired(without, current, data.valid_ho)
                drop = (without, {**_entry(stand_in, label, "backward", current, gain, se,
                                           max(without.mse - floor ** 2, 1e-12),
                                           describe_params(
                                               stand_in, current.state.effects[stand_in][0])),
                                  "rejected": (f"it stands in for {name} only: without that, "
                                               "its step factors follow a trend (backward "
                                               "step)")})
                break
        if drop is None:
            break
        current = drop[0]
        candidates.append(drop[1])
    return current


def equally_good(a: Fitted, b: Fitted, valid_ho, noise_floor) -> bool:
    """b's held-out error is not measurably worse than a's.

    Parameters
    ----------
    a, b : Fitted
        Two models of the same data.
    valid_ho : ndarray of bool, (P, S)
        Held-out samples.
    noise_floor : float, DN
        Temporal noise of one held-out sample.

    Returns
    -------
    bool
    """
    gain, se = paired(a, b, valid_ho)  # > 0: b better
    return gain > -(TIE_SIGMAS * se + (0.5 * MIN_GAIN_OF_NOISE * noise_floor) ** 2)


def linear_with_offset(alt: Fitted, linear_start: Fitted, names, data: Data, n_pix: int,
                       n_light: int) -> Fitted:
    """The linear alternative of :func:`leakage_check` with an exposure offset added, where it
    predicts the held-out data better (``alt`` otherwise).

    Light collected for longer than the nominal exposure (a shutter or transfer offset) lifts
    the shortest exposures above the line through the dark level. A per-pixel leakage shape
    starts steep and bends, so it takes most of that lift (and a compression above it) for
    leakage, and the search from the leakage model then never needs the offset; a linear
    response needs the offset to be as good. Without it the linear alternative is measurably
    worse and leakage is called needed on a sensor that has none.

    Parameters
    ----------
    alt : Fitted
        The linear alternative (a linear response with a readout nonlinearity and the
        leakage model's other effects).
    linear_start : Fitted
        The linear base alone.
    names : sequence of str
        Candidate effects identifiable next to a linear response.
    data : Data
        The samples.
    n_pix, n_light : int
        Pixels and light steps.

    Returns
    -------
    Fitted
    """
    if "exposure_offset" not in names or "exposure_offset" in alt.names:
        return alt
    with_offset = alt.names + ["exposure_offset"]
    trial = refit(with_offset, data, linear_start.state, n_pix, n_light)
    return trial if trial.mse < alt.mse else alt


def refit_from_start(fitted: Fitted, start: Fitted, data: Data, n_pix: int,
                     n_light: int) -> Fitted:
    """``fitted``'s effects fitted again together from the base alone (``start``), kept where
    that predicts the held-out data better.

    The greedy search fits each round's effects from the model of the round before. Where two
    sensor-wide effects trade off (an exposure offset lifts the short exposures, a compression
    bends the long ones, and a line per pixel takes part of both), the alternation between
    effects and base can stop at a point that depends on which came first (development seed
    200006: an offset of 0.73 ms against 0.58 put in, and a compression with the wrong shape,
    leaving structure by signal level); fitted together from the base alone they reach the
    offset put in.

    Parameters
    ----------
    fitted : Fitted
        The model the search selected.
    start : Fitted
        Its base alone.
    data : Data
        The samples.
    n_pix, n_light : int
        Pixels and light steps.

    Returns
    -------
    Fitted
    """
    if len(fitted.names) < 2:
        return fitted
    fresh = refit(fitted.names, data, start.state, n_pix, n_light)
    return fresh if fresh.mse < fitted.mse else fitted


def one_rate_shape(leak: Fitted, alt: Fitted, gain: float, se: float, out: dict) -> dict:
    """The leakage check's verdict where the leakage model predicts the held-out data better
    than a linear response with a readout nonlinearity but the design reaches every signal at
    one light rate: ``cannot tell``.

    At one light rate the leakage model is one more shape of a compression that depends on the
    signal alone (its onset is exponential in the signal, a soft knee that a quadratic and
    cubic bend follow less well); only equal signals at different light rates show that the
    bending depends on the light rate. The leakage model is kept (it fits better), and the
    bending is not claimed as leakage (the shared set ``indep-ccd12-offset``, a linear sensor
    whose well compresses and fills, had leakage "needed").

    Parameters
    ----------
    leak, alt : Fitted
        The leakage model with its effects, and the linear alternative.
    gain, se : float, DN^2
        :func:`paired` (``alt``, ``leak``).
    out : dict
        The check's record so far (updated and returned).

    Returns
    -------
    dict
    """
    out["models"] = [" + ".join(["leakage base"] + leak.names),
                     " + ".join(["linear base"] + alt.names)]
    out.update(verdict="cannot tell", heldout_rms_leakage_dn=float(np.sqrt(leak.mse)),
               heldout_rms_without_dn=float(np.sqrt(alt.mse)), reason=(
                   f"the leakage model fits the held-out data better than a linear response with "
                   f"{', '.join(alt.names)} ({np.sqrt(leak.mse):.4g} against "
                   f"{np.sqrt(alt.mse):.4g} DN, {gain / max(se, 1e-300):.0f} standard errors), "
                   "but every signal level is reached at one light rate in this design, so that "
                   "shows the response bends with the leakage model's shape, not that the "
                   "bending depends on the light rate (leakage) rather than on the signal alone "
                   "(a compression of the well or the readout); the leakage model is kept and "
                   "the bending is not claimed as leakage"))
    return out


def leakage_check(leak: Fitted, linear_start: Fitted, names, data: Data, noise_floor, n_pix,
                  n_light, design, candidates, ambiguous=None,
                  refloor=None) -> tuple[Fitted, dict]:
    """Is the bending of the response leakage? Compare the leakage model (with its selected
    effects) to a linear response with a readout nonlinearity (signal only) and its own
    selected effects; keep the simpler one where both are equally good on held-out data.

    Parameters
    ----------
    leak : Fitted
        The leakage model with its selected effects.
    linear_start : Fitted
        The linear base alone.
    names : sequence of str
        Candidate effects.
    data : Data
        The samples.
    noise_floor : float, DN
        Temporal noise of one held-out sample.
    n_pix, n_light : int
        Pixels and light steps.
    design : Design
        The sweep's design.
    candidates : list
        Filled with the candidates tried.
    ambiguous : list, optional
        Filled with the ties of the linear model's own selection.
    refloor : callable, optional
        As for :func:`greedy`.

    Returns
    -------
    model : Fitted
        The model kept.
    check : dict
        What was compared and why the model was kept.
    """
    rn = "readout_nonlinearity"
    shape_only = ("every signal level is reached at one light rate in this design, so leakage "
                  "and a readout nonlinearity differ only in the shape of the response")
    by_rate = ("this design reaches equal signal at different light rates, where leakage (which "
               "depends on the light rate) and a readout nonlinearity (signal only) differ")
    why_design = by_rate if design.rate_at_equal_signal else shape_only
    out = {"design_separates_by_light_rate": design.rate_at_equal_signal}
    if rn not in names:
        out.update(verdict="not tested", reason=(
            f"{rn} is not a candidate, or not identifiable next to a linear response"))
        return leak, out
    alt_names = [n for n in leak.names if n in names and n != rn] + [rn]
    alt = refit(alt_names, data, linear_start.state, n_pix, n_light)
    if not equally_good(leak, alt, data.valid_ho, noise_floor):
        alt = linear_with_offset(alt, linear_start, names, data, n_pix, n_light)
    if not equally_good(leak, alt, data.valid_ho, noise_floor):
        gain, se = paired(alt, leak, data.valid_ho)
        if not design.rate_at_equal_signal:
            return leak, one_rate_shape(leak, alt, gain, se, out)
        out.update(verdict="needed", heldout_rms_leakage_dn=float(np.sqrt(leak.mse)),
                   heldout_rms_without_dn=float(np.sqrt(alt.mse)), reason=(
                       f"a linear response with a readout nonlinearity fits the held-out data "
                       f"worse ({np.sqrt(alt.mse):.4g} against {np.sqrt(leak.mse):.4g} DN, "
                       f"{gain / max(se, 1e-300):.0f} standard errors); {why_design}"))
        return leak, out
    linear = greedy(linear_start, names, data, noise_floor, n_pix, n_light, candidates,
                    label="linear", ambiguous=ambiguous, refloor=refloor)
    linear = refit_from_start(linear, linear_start, data, n_pix, n_light)
    if not equally_good(leak, linear, data.valid_ho, noise_floor):
        linear = alt  # the greedy search stopped short of a model known to be as good
    what = f"a linear response with {', '.join(linear.names) or 'no effect'}"
    out["models"] = [" + ".join(["leakage base"] + leak.names),
                     " + ".join(["linear base"] + linear.names)]
    out.update(heldout_rms_leakage_dn=float(np.sqrt(leak.mse)),
               heldout_rms_without_dn=float(np.sqrt(linear.mse)))
    # the held-out error first: where the linear model predicts better by the margin that
    # selects an effect, it is kept whatever the BIC says
    leak_worse = not equally_good(linear, leak, data.valid_ho, noise_floor)
    gain, se = paired(leak, linear, data.valid_ho)
    if linear.bic >= leak.bic and not gain > SELECT_SIGMAS * se:
        out.update(verdict="cannot tell", reason=(
            f"{what} fits the held-out data as well, but not more simply (BIC); {why_design}; "
            "the leakage model is kept"))
        return leak, out
    bends = rn in linear.names  # else there is no bending for leakage to explain
    verdict = ("not needed" if (leak_worse or design.rate_at_equal_signal or not bends)
               else "cannot tell")
    how = (f"better than the leakage model ({np.sqrt(linear.mse):.4g} against "
           f"{np.sqrt(leak.mse):.4g} DN, {gain / max(se, 1e-300):.0f} standard errors)"
           if linear.bic >= leak.bic else
           f"as well as the leakage model ({np.sqrt(linear.mse):.4g} against "
           f"{np.sqrt(leak.mse):.4g} DN) with fewer parameters (BIC {linear.bic:.6g} against "
           f"{leak.bic:.6g})")
    out.update(verdict=verdict, reason=(
        f"{what} fits the held-out data {how}; {why_design}"
        + ("" if verdict == "not needed" else
           "; the simpler model is kept and the bending is not blamed on leakage")))
    return linear, out
