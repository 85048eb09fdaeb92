"""Fitting candidate effects jointly with a base model (see :mod:`hsiffc.diagnose.bases`).

An effect is linear in its parameters, ``Y += X @ theta``, with design columns ``X`` built from
the base model's prediction. It is fitted jointly with the base: its columns and the residual
are first cleared of what the base model's own parameters can absorb (per-pixel projection on
the base Jacobian, Frisch-Waugh-Lovell), then the base is refitted with the effect removed, and
the two alternate until the weighted cost stops falling. The columns are rebuilt from the
refitted base every round, so an effect far above its detection limit (which distorts the first
base fit) is found from the same start as a small one.

This module holds the data and state of a fit and the alternation itself (:func:`fitpredict`);
the least-squares pieces it is built from (Gram products, the projector off the base Jacobian,
one effect's fit) are in :mod:`hsiffc.diagnose.effectfit` and importable from here as well.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .effectfit import (fit_effect, fit_pair_effect, gram, pair_regression, projector,
                        separable_fraction)
from .effects import EFFECTS, Context

__all__ = ["BIG_EFFECT", "MAX_ROUNDS", "ROUND_TOL", "Data", "State", "context", "cost",
           "describe_params", "fit_effect", "fit_pair_effect", "fitpredict", "gram",
           "pair_regression", "projector", "refit_base", "separable_fraction"]


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
