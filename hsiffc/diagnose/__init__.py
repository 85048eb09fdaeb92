"""Close the loop with measured data: where does the model miss, why, and how much better is
it once the missing effect is modelled?

``diagnose(sweep)`` fits the base model (the paper's leakage model with a constant dark level)
per pixel on one frame of every step and measures every error on the other frame (held out).
It then fits each candidate effect of :mod:`hsiffc.diagnose.effects` on top of the base model
(alternating with a refit of the base), compares them on the held-out error and the Bayesian
information criterion, and adds effects greedily while one beats the current model by more than
the noise allows. Structure left in the held-out residual that no candidate explains is reported
as ``unexplained``.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy import stats

from ..calibrate import fit_pixels, initial_guess, model_and_jacobian, predict
from ..calibrate.samples import collect_samples, photon_transfer
from ..errors import DataFormatError
from ..sweep import Sweep
from .effects import EFFECTS, OUTSIDE, Context, inject

__all__ = ["diagnose", "EFFECTS", "OUTSIDE", "inject", "list_effects"]

BASE_MODEL = "leakage model dY/dt = k - a exp(bY), constant dark level, per pixel (k, a, b, d)"
SELECT_SIGMAS = 5.0  # held-out improvement needed, in standard errors of the paired difference
MIN_GAIN_OF_NOISE = 0.08  # ... and at least this fraction of the noise floor, as an RMS
MIN_EXPLAINED = 0.5  # ... and at least this fraction of the current systematic error
UNEXPLAINED_P = 1e-6
UNEXPLAINED_OF_NOISE = 0.2  # structure counts when its RMS exceeds this fraction of the noise


def list_effects() -> list[dict]:
    return [{"name": e.name, "scope": e.scope, "params": list(e.param_names),
             "summary": e.summary} for e in EFFECTS.values()]


def _split(sweep: Sweep):
    """Fit and held-out frame sets: alternate frames within every step."""
    fit_idx, ho_idx = [], []
    for s in sweep.steps():
        sel = np.flatnonzero(sweep.step == s)
        if sel.size < 2:
            raise DataFormatError(
                f"step {s} has {sel.size} frame; diagnose needs at least 2 frames per step (one "
                "to fit, one held out). Record two frames per step (as EMVA 1288 does)",
                path=sweep.source or None)
        fit_idx += sel[0::2].tolist()
        ho_idx += sel[1::2].tolist()
    return sweep.select(np.array(fit_idx)), sweep.select(np.array(ho_idx))


def _subset(sweep: Sweep, max_pixels: int, seed: int):
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


class _State:
    """Base-model parameters and fitted effects of the current model."""

    def __init__(self, theta, effects=None):
        self.theta = theta
        self.effects = dict(effects or {})  # name -> (params, prediction (P, S))


def _context(theta, t, r, order, prev_index, light, fs):
    m, jac = model_and_jacobian(theta, t, r)
    signal = m - theta[:, 3:4]
    k = np.broadcast_to(np.exp(theta[:, 0:1]) * r, m.shape)
    dydt = k - np.exp(theta[:, 1:2] + np.exp(theta[:, 2:3]) * m)
    prev = np.where(prev_index[None, :] >= 0, signal[:, np.maximum(prev_index, 0)], 0.0)
    return m, Context(t=np.broadcast_to(t, m.shape), k=k, signal=signal, order=order,
                      prev_signal=prev, light=light, full_scale=fs, dydt=dydt,
                      dydlnk=jac[..., 0])


def _projector(jac, w):
    """Per pixel, the map v -> v - J (J^T W J)^-1 J^T W v that removes what the base model's
    own parameters can absorb (Frisch-Waugh-Lovell): effects are fitted jointly with the base
    model, to first order, in one linear solve."""
    normal = np.einsum("psi,ps,psj->pij", jac, w, jac)
    normal += 1e-9 * (np.einsum("pii->p", normal)[:, None, None] + 1e-30) * np.eye(jac.shape[-1])
    inv = np.linalg.pinv(normal)

    def project(v):  # v: (P, S) or (P, S, m)
        squeeze = v.ndim == 2
        vv = v[..., None] if squeeze else v
        coef = np.einsum("pij,psj,ps,psm->pim", inv, jac, w, vv)
        out = vv - np.einsum("psi,pim->psm", jac, coef)
        return out[..., 0] if squeeze else out
    return project


def _fit_effect(effect, ctx, res, w, project=None):
    """Least-squares parameters of one effect on a residual; returns (params, prediction).

    With ``project`` (see :func:`_projector`) the columns and the residual are first cleared of
    what the base model's parameters explain, so the parameters are those of the joint fit."""
    X = effect.columns(ctx)  # (P, S, m)
    Xp = X if project is None or effect.scope == "step" else project(X)
    rp = res if project is None or effect.scope == "step" else project(res)
    if effect.scope == "global":
        a = np.einsum("psi,ps,psj->ij", Xp, w, Xp)
        b = np.einsum("psi,ps,ps->i", Xp, w, rp)
        theta = np.linalg.lstsq(a + 1e-12 * np.trace(a) * np.eye(a.shape[0]), b, rcond=None)[0]
        return theta, np.einsum("psi,i->ps", X, theta)
    if effect.scope == "pixel":
        a = np.einsum("psi,ps,psj->pij", Xp, w, Xp)
        b = np.einsum("psi,ps,ps->pi", Xp, w, rp)
        a = a + 1e-9 * (np.einsum("pii->p", a)[:, None, None] + 1e-30) * np.eye(a.shape[1])
        theta = np.linalg.solve(a, b[..., None])[..., 0]
        return theta, np.einsum("psi,pi->ps", X, theta)
    # step: one factor per light step, shared by the pixels
    x = X[..., 0]
    num = (w * x * res).sum(axis=0)
    den = (w * x * x).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.where((den > 0) & ctx.light, num / den, 0.0)
    return theta, x * theta[None, :]


def _fitpredict(names, data, state0, rounds=2, base_iter=15):
    """Fit base + the named effects, alternating effect fits and base refits."""
    y, t, r, valid, w, order, prev_index, light, fs = data
    state = _State(state0.theta.copy())
    for _ in range(rounds):
        m, ctx = _context(state.theta, t, r, order, prev_index, light, fs)
        _, jac = model_and_jacobian(state.theta, t, r)
        project = _projector(jac, w)
        for name in names:
            others = sum((p for n, (_, p) in state.effects.items() if n != name),
                         np.zeros_like(m))
            res = np.where(valid, y - m - others, 0.0)
            state.effects[name] = _fit_effect(EFFECTS[name], ctx, res, w, project)
        total = sum((p for _, p in state.effects.values()), np.zeros_like(m))
        fit = fit_pixels(y - total, t, r, valid, w, state.theta, max_iter=base_iter)
        with np.errstate(divide="ignore", invalid="ignore"):
            new = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark])
        good = np.all(np.isfinite(new), axis=1)
        state.theta = np.where(good[:, None], new, state.theta)
    m, ctx = _context(state.theta, t, r, order, prev_index, light, fs)
    for name in names:  # final effect parameters against the final base model
        others = sum((p for n, (_, p) in state.effects.items() if n != name), np.zeros_like(m))
        state.effects[name] = _fit_effect(EFFECTS[name], ctx, np.where(valid, y - m - others, 0),
                                          w)
    state.prediction = m + sum((p for _, p in state.effects.values()), np.zeros_like(m))
    return state


def _describe_params(name, theta):
    e = EFFECTS[name]
    if e.scope == "global":
        p = {k: float(v) for k, v in zip(e.param_names, theta)}
        if name == "offset_drift":
            order = np.linspace(-1, 1, 201)
            curve = sum(v * c for v, c in zip(theta, (order, 1.5 * order ** 2 - 0.5,
                                                       2.5 * order ** 3 - 1.5 * order)))
            p["peak_dn"] = float(np.abs(curve).max())
        return p
    if e.scope == "pixel":
        v = theta[:, 0]
        return {f"median_{e.param_names[0]}": float(np.median(v)),
                f"spread_{e.param_names[0]}": float(1.4826 * np.median(np.abs(v - np.median(v)))),
                "n_pixels": int(v.size)}
    v = theta[theta != 0]
    return {"n_steps": int(v.size), "rms": float(np.sqrt(np.mean(v ** 2))) if v.size else 0.0,
            "median_abs": float(np.median(np.abs(v))) if v.size else 0.0,
            "max_abs": float(np.abs(v).max()) if v.size else 0.0}


def _refit_base(y, data, state0):
    _, t, r, valid, w, *_ = data
    fit = fit_pixels(y, t, r, valid, w, state0.theta, max_iter=15)
    with np.errstate(divide="ignore", invalid="ignore"):
        theta = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark])
    st = _State(np.where(np.isfinite(theta), theta, state0.theta))
    st.prediction = predict(st.theta, t, r)
    return st


def _structure(res, valid, t, signal, light, noise, rows, cols, band, null=None):
    """Binned held-out residual: is there structure beyond noise? Returns (findings, flag)."""
    groups = {}
    step_id = np.broadcast_to(np.arange(res.shape[1]), res.shape)
    groups["step (exposure, acquisition order)"] = step_id
    sig = np.where(light[None, :], signal, np.nan)
    if np.any(valid & light[None, :]):
        edges = np.nanpercentile(sig[valid & light[None, :]], np.linspace(0, 100, 51))
        groups["signal level (50 quantile bins)"] = np.where(
            light[None, :], np.clip(np.searchsorted(edges[1:-1], sig), 0, 49), -1)
    groups["row"] = np.broadcast_to((rows * 8 // max(rows.max() + 1, 1))[:, None], res.shape)
    groups["column"] = np.broadcast_to((cols * 8 // max(cols.max() + 1, 1))[:, None], res.shape)
    if band.max() > 0:
        groups["mosaic phase (band)"] = np.broadcast_to(band[:, None], res.shape)
    findings, flag = [], False
    for name, g in groups.items():
        ok = valid & (g >= 0)
        gv, rv = g[ok].astype(int), res[ok]
        n = np.bincount(gv)
        keep = n >= 10
        s1 = np.bincount(gv, weights=rv)
        s2 = np.bincount(gv, weights=rv * rv)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / n
            var = s2 / n - mean ** 2
            se = np.sqrt(var / np.maximum(n - 1, 1))
        mean, se = mean[keep], se[keep]
        chi2 = float(np.sum((mean / se) ** 2))
        dof = int(keep.sum())
        p = float(stats.chi2.sf(chi2, dof)) if dof else 1.0
        structured_rms = float(np.sqrt(np.mean(np.maximum(mean ** 2 - se ** 2, 0.0))))
        floor = 1.5 * null.get(name, 0.0) if null else 0.0
        significant = (p < UNEXPLAINED_P and structured_rms > UNEXPLAINED_OF_NOISE * noise
                       and structured_rms > floor)
        flag |= significant
        findings.append({"grouping": name, "bins": dof, "chi2": chi2, "p_value": p,
                         "structured_rms_dn": structured_rms,
                         "null_structured_rms_dn": (null or {}).get(name),
                         "significant": significant})
    return findings, flag


def diagnose(sweep: Sweep, *, max_pixels: int = 2048, seed: int = 0, effects=None,
             full_well_dn: float | None = None) -> dict:
    """Diagnose where the base model misses a sweep; see the module docstring.

    Parameters
    ----------
    sweep : Sweep
        Two or more frames per step (one fits, the other is held out).
    max_pixels : int
        Pixels analysed (a random subset when the sensor has more; sensor-wide effects are
        well determined by a few thousand pixels).
    effects : list of str, optional
        Candidate effects (default: the whole library).

    Returns
    -------
    dict with the fields of ``hsiffc diagnose --json`` plus the arrays needed for the report
    (under ``"_arrays"``).
    """
    t0 = time.perf_counter()
    names = list(EFFECTS) if effects is None else list(effects)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effects {unknown}; the library has {list(EFFECTS)}")
    if "sweep_steps" in sweep.meta:  # EMVA 1288: the sweep, not the spatial set
        sweep = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    sub, rows, cols, band = _subset(sweep, max_pixels, seed)
    fit_sw, ho_sw = _split(sub)
    sf = collect_samples(fit_sw, full_well_dn=full_well_dn)
    sh = collect_samples(ho_sw, full_well_dn=full_well_dn)
    fs = float(sweep.full_scale_dn)
    ptc = photon_transfer(sub)
    valid = (sf.valid & sh.valid).T
    y = sf.y.T.astype(np.float64)
    y_ho = sh.y.T.astype(np.float64)
    usable = sf.usable_step  # zero exposure or unknown light rate: left out
    t = np.where(usable, sf.exposure_ms, 1.0)
    r = np.where(usable, np.nan_to_num(sf.rate), 0.0)
    valid &= usable[None, :]
    dark0 = np.median(y[:, sf.kind == "dark"], axis=1) if (sf.kind == "dark").any() else y.min(1)
    var_frame = (ptc.variance(y - dark0[:, None]) if ptc is not None
                 else np.ones_like(y))
    # samples within 4 sigma of full scale are left out too: frames there are sometimes clipped,
    # and keeping only the unclipped ones would bias the sample low
    near_fs = 0.5 * (y + y_ho) > fs - 4.0 * np.sqrt(var_frame)
    valid &= ~near_fs
    w = np.where(valid, sf.n_frames[None, :] / var_frame, 0.0)
    # temporal noise of a held-out sample, measured from the frame pairs themselves (per step,
    # averaged over pixels), plus the variance the base fit's own noise adds to a prediction
    # (4 parameters from the pixel's fit samples): the error a correct model would show
    pair = (y - y_ho) ** 2 / (1.0 / sf.n_frames[None, :] + 1.0 / sh.n_frames[None, :])
    var_step = np.where(valid, pair, 0).sum(0) / np.maximum(valid.sum(0), 1)  # one frame
    noise2 = var_step[None, :] / sh.n_frames[None, :]
    noise_floor = None  # set once the base model is fitted (it adds its prediction variance)
    light = sf.kind == "light"
    order_rank = np.argsort(np.argsort(sf.step))
    order = (order_rank / max(len(order_rank) - 1, 1)) * 2 - 1
    by_order = np.argsort(sf.step)
    prev_index = np.full(len(order), -1)
    prev_index[by_order[1:]] = by_order[:-1]

    theta0 = initial_guess(y, t, r, valid, w)
    base_fit = fit_pixels(y, t, r, valid, w, theta0)
    # Selecting samples by their observed value near full scale keeps those with low noise
    # and biases them; select instead by the model's prediction (independent of the held-out
    # noise), leaving out everything the model puts within 5 sigma of full scale, and refit.
    with np.errstate(divide="ignore", invalid="ignore"):
        theta_b = np.column_stack([np.log(base_fit.g), np.log(base_fit.a), np.log(base_fit.b),
                                   base_fit.dark])
    theta_b = np.where(np.isfinite(theta_b), theta_b, theta0)
    pred = predict(theta_b, t, r)
    sd_pred = np.sqrt(ptc.variance(pred - dark0[:, None])) if ptc is not None else 1.0
    valid = (sf.valid & sh.valid).T & usable[None, :] & (pred < fs - 5.0 * sd_pred)
    w = np.where(valid, sf.n_frames[None, :] / var_frame, 0.0)
    base_fit = fit_pixels(y, t, r, valid, w, theta_b)
    data = (y, t, r, valid, w, order, prev_index, light, fs)
    with np.errstate(divide="ignore", invalid="ignore"):
        theta_b = np.column_stack([np.log(base_fit.g), np.log(base_fit.a), np.log(base_fit.b),
                                   base_fit.dark])
    base = _State(np.where(np.isfinite(theta_b), theta_b, theta0))
    base.prediction = predict(base.theta, t, r)
    # variance the base fit's own noise adds to each prediction (linearised: j C j^T)
    _, jac = model_and_jacobian(base.theta, t, r)
    normal = np.einsum("psi,ps,psj->pij", jac, w, jac)
    normal += 1e-9 * np.einsum("pii->p", normal)[:, None, None] * np.eye(4)
    pred_var = np.einsum("psi,pij,psj->ps", jac, np.linalg.pinv(normal), jac)
    noise_floor = float(np.sqrt(np.mean((noise2 + np.clip(pred_var, 0, None))[valid])))
    n_fit = int(valid.sum())
    n_pix = y.shape[0]

    def metrics(state, n_params):
        res_ho = np.where(valid, y_ho - state.prediction, 0.0)
        res_fit = np.where(valid, y - state.prediction, 0.0)
        mse = float((res_ho ** 2).sum() / n_fit)
        rss_w = float((w * res_fit ** 2).sum())
        bic = n_fit * np.log(rss_w / n_fit) + n_params * np.log(n_fit)
        return res_ho, mse, bic

    n_light_steps = int(light.sum())
    base_params = 4 * n_pix
    res_base, mse_base, _ = metrics(base, base_params)
    current, cur_res, cur_mse, cur_params = base, res_base, mse_base, base_params
    selected: list[str] = []
    candidates = []
    for round_ in range(len(names)):
        best = None
        for name in names:
            if name in selected:
                continue
            state = _fitpredict(selected + [name], data, current)
            k = cur_params + EFFECTS[name].n_params(n_pix, n_light_steps)
            res, mse, bic = metrics(state, k)
            d = cur_res[valid] ** 2 - res[valid] ** 2
            se = float(d.std() / np.sqrt(d.size))
            gain = float(d.mean())
            entry = {"name": name, "heldout_rms_dn": float(np.sqrt(mse)), "criterion": float(bic),
                     "criterion_name": "BIC (fit half, weighted)", "round": round_ + 1,
                     "heldout_mse_gain_dn2": gain, "gain_standard_error_dn2": se,
                     "params": _describe_params(name, state.effects[name][0])}
            candidates.append(entry)
            systematic2 = max(cur_mse - noise_floor ** 2, 1e-12)
            ok = np.isfinite(mse) and np.isfinite(bic)
            # nothing to explain when the current model is already at the noise floor
            beats = ok and cur_mse - noise_floor ** 2 > (MIN_GAIN_OF_NOISE * noise_floor) ** 2 \
                and (gain > SELECT_SIGMAS * se
                            and gain > (MIN_GAIN_OF_NOISE * noise_floor) ** 2
                            and gain > MIN_EXPLAINED * systematic2)
            entry["selected_in_round"] = False
            entry["explained_fraction_of_systematic"] = float(gain / systematic2)
            # among the effects that pass, the most parsimonious (lowest BIC)
            if beats and (best is None or bic < best[3]):
                best = (name, state, mse, bic, res, k, entry)
        if best is None:
            break
        name, state, mse, bic, res, k, entry = best
        entry["selected_in_round"] = True
        selected.append(name)
        current, cur_mse, cur_res, cur_params = state, mse, res, k

    m_final, ctx = _context(current.theta, t, r, order, prev_index, light, fs)
    # what a correct model leaves: simulate the final model with the measured noise, refit the
    # base model, and measure the same residual structure (parametric bootstrap, 2 draws)
    rng = np.random.default_rng(seed + 1)
    null = {}
    for _ in range(2):
        sd_fit = np.sqrt(var_step[None, :] / sf.n_frames[None, :])
        sd_ho = np.sqrt(var_step[None, :] / sh.n_frames[None, :])
        y_sim = current.prediction + sd_fit * rng.standard_normal(y.shape)
        y_sim_ho = current.prediction + sd_ho * rng.standard_normal(y.shape)
        sim_state = _fitpredict(selected, (y_sim,) + data[1:], current, rounds=1) if selected \
            else _refit_base(y_sim, data, current)
        sim_res = np.where(valid, y_sim_ho - sim_state.prediction, 0.0)
        for f in _structure(sim_res, valid, t, ctx.signal, light, noise_floor, rows, cols, band,
                            null=None)[0]:
            null[f["grouping"]] = max(null.get(f["grouping"], 0.0), f["structured_rms_dn"])
    findings, unexplained = _structure(cur_res, valid, t, ctx.signal, light, noise_floor,
                                       rows, cols, band, null=null)
    findings_before, _ = _structure(res_base, valid, t, ctx.signal, light, noise_floor,
                                    rows, cols, band, null=null)

    def figs(mse):
        rms = float(np.sqrt(mse))
        return {"rms_dn": rms, "systematic_rms_dn": float(np.sqrt(max(rms ** 2 - noise_floor ** 2,
                                                                      0.0)))}

    chosen = []
    for name in selected:
        params = _describe_params(name, current.effects[name][0])
        chosen.append({"name": name, "params": params,
                       "interpretation": EFFECTS[name].interpret(params)})
    n_total_samples = int(sf.usable_step.sum() * n_pix)
    return {
        "dataset": str(sweep.source or "in-memory sweep"),
        "base_model": BASE_MODEL,
        "n_pixels": int(n_pix), "n_pixels_sensor": int(np.prod(sweep.frame_shape)),
        "n_samples": int(valid.sum()), "n_invalid_samples": int(n_total_samples - valid.sum()),
        "noise_floor_dn": noise_floor,
        "before": figs(mse_base), "after": figs(cur_mse),
        "selected_effects": selected, "effects": chosen,
        "candidates": candidates, "unexplained": bool(unexplained),
        "residual_structure_after": findings, "residual_structure_before": findings_before,
        "held_out": "second frame of every step (the first fits the model)",
        "selection_rule": (f"held-out mean squared error lower by more than {SELECT_SIGMAS:g} "
                           "standard errors of the paired difference, by more than "
                           f"({MIN_GAIN_OF_NOISE:g} x noise floor)^2 and by more than "
                           f"{MIN_EXPLAINED:g} of the current systematic error (which must itself "
                           f"exceed ({MIN_GAIN_OF_NOISE:g} x noise floor)^2); among those the "
                           "lowest BIC"),
        "runtime_s": time.perf_counter() - t0,
        "_arrays": {"res_before": res_base, "res_after": cur_res, "valid": valid, "t": t,
                    "signal": ctx.signal, "light": light, "order": order, "rows": rows,
                    "cols": cols, "band": band, "step": sf.step},
    }
