"""Fitting candidate effects jointly with a base model (see :mod:`hsiffc.diagnose.bases`).

An effect is linear in its parameters, ``Y += X @ theta``, with design columns ``X`` built from
the base model's prediction. It is fitted jointly with the base: its columns and the residual
are first cleared of what the base model's own parameters can absorb (per-pixel projection on
the base Jacobian, Frisch-Waugh-Lovell), then the base is refitted with the effect removed, and
the two alternate until the weighted cost stops falling. The columns are rebuilt from the
refitted base every round, so an effect far above its detection limit (which distorts the first
base fit) is found from the same start as a small one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg

from .effects import EFFECTS, Context

MAX_ROUNDS = 16
ROUND_TOL = 1e-4  # relative fall of the weighted cost that ends the alternation
BIG_EFFECT = 2.0  # RMS of a newly added effect, in noise sigmas, that calls for fresh base starts


@dataclass
class Data:
    """Everything a fit needs; arrays (P, S) unless stated.

    The fields (commented in the class body) are the fit-half and held-out step means (DN),
    exposures (ms), relative light rates, validity masks, weights (1/DN^2), acquisition order,
    previous step, light mask, full scale (DN) and the frame gap between the two halves.
    """

    y: np.ndarray  # fit-half step means, DN
    y_ho: np.ndarray  # held-out step means, DN
    t: np.ndarray  # (S,) exposure, ms
    r: np.ndarray  # (S,) relative light rate (0 for darks)
    valid: np.ndarray  # fit samples
    valid_ho: np.ndarray  # held-out samples
    w: np.ndarray  # fit weights, 1/DN^2
    order: np.ndarray  # (S,) acquisition order in [-1, 1]
    prev_index: np.ndarray  # (S,) previous step in acquisition order (-1: none)
    light: np.ndarray  # (S,) bool
    full_scale: float
    frame_gap: float  # mean frame index of the held-out half minus that of the fit half


class State:
    """Base-model parameters and fitted effects of one model.

    Parameters
    ----------
    base : LinearBase or LeakageBase
        The base model.
    theta : ndarray, (P, n)
        Its parameters per pixel.
    effects : dict, optional
        Effect name -> (parameters, prediction (P, S) in DN).
    """

    def __init__(self, base, theta, effects=None):
        self.base = base
        self.theta = theta
        self.effects = dict(effects or {})  # name -> (params, prediction (P, S))
        self.prediction = None
        self.ho_extra = 0.0  # what within-step ("pair") effects add to the held-out half

    def sum_effects(self, shape, skip=None):
        """Sum of the predictions (DN) of the fitted effects, within-step ones excluded.

        Parameters
        ----------
        shape : (int, int)
            (P, S).
        skip : str, optional
            An effect to leave out.

        Returns
        -------
        ndarray, (P, S), DN
        """
        out = np.zeros(shape)
        for n, (_, p) in self.effects.items():
            if n != skip and EFFECTS[n].scope != "pair":
                out += p
        return out


def context(base, theta, data: Data):
    """The base model evaluated on the data, and the :class:`Context` effects are built from.

    Parameters
    ----------
    base : LinearBase or LeakageBase
        The base model.
    theta : ndarray, (P, n)
        Its parameters.
    data : Data
        The samples.

    Returns
    -------
    model : ndarray, (P, S), DN
    jac : ndarray, (P, S, n)
        Jacobian of the model with respect to ``theta``.
    ctx : Context
    """
    m, jac, k, dydt, dydlnk = base.evaluate(theta, data.t, data.r)
    signal = m - base.dark(theta)
    pi = data.prev_index
    prev = np.where(pi[None, :] >= 0, signal[:, np.maximum(pi, 0)], 0.0)
    ctx = Context(t=np.broadcast_to(data.t, m.shape), k=k, signal=signal, order=data.order,
                  prev_signal=prev, light=data.light, full_scale=data.full_scale, dydt=dydt,
                  dydlnk=np.where(data.light[None, :], dydlnk, 0.0))
    return m, jac, ctx


def gram(a, w, b):
    """Per pixel a^T W b: (P, S, i), (P, S), (P, S, j) -> (P, i, j), as batched matmuls.

    Parameters
    ----------
    a : ndarray, (P, S, i)
    w : ndarray, (P, S)
        Weights.
    b : ndarray, (P, S, j)

    Returns
    -------
    ndarray, (P, i, j)
    """
    return np.matmul((a * w[..., None]).transpose(0, 2, 1), b)


def projector(jac, w):
    """Per pixel, the map v -> v - J (J^T W J)^-1 J^T W v (what the base cannot absorb).

    Parameters
    ----------
    jac : ndarray, (P, S, n)
        Base-model Jacobian.
    w : ndarray, (P, S)
        Weights.

    Returns
    -------
    callable
        ``project(v)`` for v of shape (P, S) or (P, S, m).
    """
    normal = gram(jac, w, jac)
    normal += 1e-9 * (np.einsum("pii->p", normal)[:, None, None] + 1e-30) * np.eye(jac.shape[-1])
    inv = np.linalg.pinv(normal)
    jw_t = (jac * w[..., None]).transpose(0, 2, 1)  # (P, n, S)

    def project(v):  # v: (P, S) or (P, S, m)
        squeeze = v.ndim == 2
        vv = v[..., None] if squeeze else v
        out = vv - np.matmul(jac, np.matmul(inv, np.matmul(jw_t, vv)))
        return out[..., 0] if squeeze else out
    return project


def separable_fraction(effect, ctx, project, w) -> float:
    """Smallest fraction of the effect's weighted column energy, over directions in its
    parameter space, that the base model's parameters cannot absorb (1: fully separable,
    0: the design cannot tell the effect from the base).

    Parameters
    ----------
    effect : Effect
        The candidate.
    ctx : Context
        Base model on the data.
    project : callable
        From :func:`projector`.
    w : ndarray, (P, S)
        Weights.

    Returns
    -------
    float
        In [0, 1].
    """
    if effect.scope in ("step", "pair"):
        return 1.0
    X = effect.columns(ctx)
    Xp = project(X)
    if effect.scope == "global":
        g = gram(X, w, X).sum(axis=0)
        gp = gram(Xp, w, Xp).sum(axis=0)
        if not np.all(np.isfinite(g)) or np.trace(g) <= 0:
            return 0.0
        scale = np.sqrt(np.clip(np.diag(g), 1e-300, None))
        g, gp = g / np.outer(scale, scale), gp / np.outer(scale, scale)
        try:
            ev = linalg.eigh(gp, g + 1e-12 * np.eye(len(g)), eigvals_only=True)
        except (linalg.LinAlgError, ValueError):
            return 0.0
        return float(max(ev.min(), 0.0))
    num = (Xp * Xp * w[..., None]).sum(axis=(1, 2))
    den = (X * X * w[..., None]).sum(axis=(1, 2))
    ok = den > 0
    return float(np.median(num[ok] / den[ok])) if ok.any() else 0.0


def fit_effect(effect, ctx, res, w, project=None):
    """Least-squares parameters of one effect on a residual; returns (params, prediction).

    Parameters
    ----------
    effect : Effect
        The effect.
    ctx : Context
        Base model on the data.
    res : ndarray, (P, S), DN
        Residual to explain.
    w : ndarray, (P, S)
        Weights.
    project : callable, optional
        From :func:`projector`: fit jointly with the base (what the base cannot absorb).

    Returns
    -------
    params : ndarray
        (m,) for a global effect, (P, m) per pixel, (S,) per step.
    prediction : ndarray, (P, S), DN
    """
    X = effect.columns(ctx)  # (P, S, m)
    joint = project is not None and effect.scope in ("global", "pixel")
    Xp = project(X) if joint else X
    rp = project(res) if joint else res
    if effect.scope == "global":
        a = gram(Xp, w, Xp).sum(axis=0)
        b = gram(Xp, w, rp[..., None]).sum(axis=0)[:, 0]
        theta = np.linalg.lstsq(a + 1e-12 * np.trace(a) * np.eye(a.shape[0]), b, rcond=None)[0]
        return theta, X @ theta
    if effect.scope == "pixel":
        a = gram(Xp, w, Xp)
        b = gram(Xp, w, rp[..., None])
        a = a + 1e-9 * (np.einsum("pii->p", a)[:, None, None] + 1e-30) * np.eye(a.shape[1])
        theta = np.linalg.solve(a, b)[..., 0]
        return theta, np.matmul(X, theta[..., None])[..., 0]
    # step: one factor per light step, shared by the pixels
    x = X[..., 0]
    num = (w * x * res).sum(axis=0)
    den = (w * x * x).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.where((den > 0) & ctx.light, num / den, 0.0)
    return theta, x * theta[None, :]


def fit_pair_effect(effect, ctx, data: Data, prediction):
    """A within-step effect (the held-out frames differ from the fit frames of the same step),
    fitted on the frame differences by two-fold cross-fitting over pixels: the parameter applied
    to one half of the pixels is estimated on the other half, so the held-out error stays
    honest.

    Parameters
    ----------
    effect : Effect
        A within-step ("pair") effect.
    ctx : Context
        Base model on the data.
    data : Data
        The samples (fit and held-out halves).
    prediction : ndarray, (P, S), DN
        Current model prediction.

    Returns
    -------
    params : ndarray, (1,)
        Whole-sensor estimate.
    prediction : ndarray, (P, S), DN
        What the effect adds to the held-out half.
    """
    x = effect.columns(ctx)[..., 0] * data.frame_gap
    ok = data.valid & data.valid_ho & data.light[None, :]
    d = np.where(ok, data.y_ho - data.y, 0.0)
    wx = np.where(ok, data.w, 0.0)
    half = (np.arange(x.shape[0]) % 2).astype(bool)
    coef = np.zeros(x.shape[0])

    def estimate(sel):
        den = (wx[sel] * x[sel] ** 2).sum()
        return float((wx[sel] * x[sel] * d[sel]).sum() / den) if den > 0 else 0.0
    coef[half] = estimate(~half)
    coef[~half] = estimate(half)
    return np.array([estimate(np.ones_like(half))]), coef[:, None] * x


def cost(state, data: Data) -> float:
    """Weighted sum of squared fit residuals of a state with a prediction.

    Parameters
    ----------
    state : State
        With ``prediction`` set.
    data : Data
        The samples.

    Returns
    -------
    float
        Dimensionless (residuals in DN times weights in 1/DN^2).
    """
    res = np.where(data.valid, data.y - state.prediction, 0.0)
    return float((data.w * res * res).sum())


def fitpredict(names, data: Data, state0: State, rounds=MAX_ROUNDS, base_iter=40,
               quick=False) -> State:
    """Fit the base + the named effects jointly (see the module docstring).

    With ``quick``, effects small against the noise (RMS below ``BIG_EFFECT`` sigma) stop after
    the first joint step: the base model's response to them is its linearised least-squares
    update (exact to first order), with no nonlinear refit; ``state.theta`` is then that of
    ``state0``. Large effects are always iterated to convergence.

    Parameters
    ----------
    names : sequence of str
        Effects to fit with the base.
    data : Data
        The samples.
    state0 : State
        Start (the base alone).
    rounds : int
        Alternations between effects and base at most.
    base_iter : int
        Iterations of each base refit.
    quick : bool
        See above.

    Returns
    -------
    State
        With ``prediction`` (P, S) DN and the effects' parameters.
    """
    base = state0.base
    state = State(base, state0.theta.copy())
    plain = [n for n in names if EFFECTS[n].scope != "pair"]
    previous = np.inf
    first = True
    for _ in range(rounds if plain else 0):
        m, jac, ctx = context(base, state.theta, data)
        project = projector(jac, data.w)
        for name in plain:
            res = np.where(data.valid, data.y - m - state.sum_effects(m.shape, skip=name), 0.0)
            state.effects[name] = fit_effect(EFFECTS[name], ctx, res, data.w, project)
        total = state.sum_effects(m.shape)
        added = total - state0.sum_effects(m.shape) if first else 0.0
        # an effect that moves the data by more than its noise has distorted the base it was
        # first fitted against: refit the base from fresh starts too (per pixel the best)
        big = first and np.mean(data.w * added ** 2, where=data.valid) > BIG_EFFECT ** 2
        if quick and first and not big:  # linearised base update, no refit
            res = np.where(data.valid, data.y - m - total, 0.0)
            state.prediction = m + (res - project(res)) + total
            return _pair_effects(names, state, ctx, data)
        refit = base.restart if big else base.fit
        state.theta = refit(data.y - total, data.t, data.r, data.valid, data.w, state.theta,
                            max_iter=base_iter)
        first = False
        state.prediction = base.predict(state.theta, data.t, data.r) + total
        now = cost(state, data)
        if not np.isfinite(now) or previous - now < ROUND_TOL * now:
            break
        previous = now
    m, _, ctx = context(base, state.theta, data)
    for name in plain:  # final effect parameters against the final base model
        res = np.where(data.valid, data.y - m - state.sum_effects(m.shape, skip=name), 0.0)
        state.effects[name] = fit_effect(EFFECTS[name], ctx, res, data.w)
    state.prediction = m + state.sum_effects(m.shape)
    return _pair_effects(names, state, ctx, data)


def _pair_effects(names, state, ctx, data):
    for name in names:
        if EFFECTS[name].scope == "pair":
            state.effects[name] = fit_pair_effect(EFFECTS[name], ctx, data, state.prediction)
            state.ho_extra = state.ho_extra + state.effects[name][1]
    if state.prediction is None:
        state.prediction = state.base.predict(state.theta, data.t, data.r)
    return state


def refit_base(y, data: Data, state0: State) -> State:
    """The base model refitted to ``y`` near ``state0``, linearised (one Gauss-Newton step;
    used on data simulated from ``state0`` itself, where that step is the fit).

    Parameters
    ----------
    y : ndarray, (P, S), DN
        Data to fit.
    data : Data
        Masks, weights, exposures and rates.
    state0 : State
        Where to linearise.

    Returns
    -------
    State
    """
    m, jac, _ = context(state0.base, state0.theta, data)
    res = np.where(data.valid, y - m, 0.0)
    st = State(state0.base, state0.theta)
    st.prediction = m + (res - projector(jac, data.w)(res))
    return st


def describe_params(name, theta):
    """Figures of an effect's fitted parameters for the report.

    Parameters
    ----------
    name : str
        Effect name.
    theta : ndarray
        Its parameters (from :func:`fit_effect`).

    Returns
    -------
    dict
        Global: the parameters by name (plus derived figures in DN); per pixel: median and
        robust spread; per step: count, RMS, median and largest magnitude.
    """
    e = EFFECTS[name]
    if e.scope in ("global", "pair"):
        p = {k: float(v) for k, v in zip(e.param_names, theta)}
        if name == "offset_drift":
            order = np.linspace(-1, 1, 201)
            curve = sum(v * c for v, c in zip(theta, (order, 1.5 * order ** 2 - 0.5,
                                                       2.5 * order ** 3 - 1.5 * order)))
            p["peak_dn"] = float(np.abs(curve).max())
        if name == "readout_nonlinearity":
            p["deviation_at_full_scale_dn"] = float(theta[0] + theta[1])
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
