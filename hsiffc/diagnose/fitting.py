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
one effect's fit) are in :mod:`hsiffc.diagnose.effectfit` and importable from here as well, and
the samples (:class:`~hsiffc.diagnose.fitdata.Data`) in :mod:`hsiffc.diagnose.fitdata`.
"""

from __future__ import annotations

import numpy as np

from .effectfit import (fit_effect, fit_frame_pairs, fit_on_differences, fit_pair_effect, gram,
                        pair_regression, projector, separable_fraction)
from .effects import EFFECTS, Context
from .fitdata import Data

__all__ = ["BIG_EFFECT", "MAX_ROUNDS", "ROUND_TOL", "Data", "State", "context", "cost",
           "describe_params", "fit_effect", "fit_frame_pairs", "fit_pair_effect", "fitpredict",
           "gram",
           "pair_regression", "projector", "refit_base", "separable_fraction"]


MAX_ROUNDS = 16
ROUND_TOL = 1e-4  # relative fall of the weighted cost that ends the alternation
BIG_EFFECT = 2.0  # RMS of a newly added effect, in noise sigmas, that calls for fresh base starts


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
                  dydlnk=np.where(data.light[None, :], dydlnk, 0.0), n_fit=data.n_fit,
                  order_ho=data.order_ho)
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
    held_out: dict = {}  # held-out predictions of the effects fitted on the frame differences
    previous = np.inf
    first = True
    for _ in range(rounds if plain else 0):
        m, jac, ctx = context(base, state.theta, data)
        project = projector(jac, data.w)
        for name in plain:
            res = np.where(data.valid, data.y - m - state.sum_effects(m.shape, skip=name), 0.0)
            state.effects[name] = _fit_one(EFFECTS[name], ctx, res, data, project,
                                           held_out, name)
        total = state.sum_effects(m.shape)
        added = total - state0.sum_effects(m.shape) if first else 0.0
        # an effect that moves the data by more than its noise has distorted the base it was
        # first fitted against: refit the base from fresh starts too (per pixel the best)
        big = first and np.mean(data.w * added ** 2, where=data.valid) > BIG_EFFECT ** 2
        if quick and first and not big:  # linearised base update, no refit
            res = np.where(data.valid, data.y - m - total, 0.0)
            state.prediction = m + (res - project(res)) + total
            return _pair_effects(names, state, ctx, data, held_out)
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
        state.effects[name] = _fit_one(EFFECTS[name], ctx, res, data, None, held_out, name)
    state.prediction = m + state.sum_effects(m.shape)
    return _pair_effects(names, state, ctx, data, held_out)


def on_differences(effect) -> bool:
    """Is ``effect`` fitted on the frame differences (:func:`fit_on_differences`): one global
    parameter, its own held-out columns, and no evidence in the step means?"""
    return (effect.scope == "global" and effect.ho_columns is not None
            and not effect.steps_are_evidence and len(effect.param_names) == 1)


def _fit_one(effect, ctx, res, data: Data, project, held_out: dict, name: str):
    """One effect's (params, fit-half prediction): on the frame differences where
    :func:`on_differences` (its held-out prediction then goes into ``held_out[name]``, for
    :func:`_pair_effects` with the same ``ctx``), else on the residual ``res`` (jointly with
    the base where ``project``)."""
    if on_differences(effect):
        params, pred, held_out[name] = fit_on_differences(effect, ctx, data)
        return params, pred
    return fit_effect(effect, ctx, res, data.w, project)


def _pair_effects(names, state, ctx, data, held_out):
    """What the effects add to the held-out half beyond the fit half's prediction: a
    within-step effect (fitted on the frame differences), the part between the halves of a
    ``frame`` effect, the held-out prediction of an effect fitted on the frame differences
    (``held_out``, from :func:`_fit_one` with this ``ctx``) and the held-out columns of an
    effect whose columns differ there."""
    if state.prediction is None:
        state.prediction = state.base.predict(state.theta, data.t, data.r)
    for name in names:
        e = EFFECTS[name]
        if e.scope == "pair":
            state.effects[name] = fit_pair_effect(e, ctx, data, state.prediction)
            state.ho_extra = state.ho_extra + state.effects[name][1]
        elif e.scope == "frame":
            step, pred = state.effects[name]
            between, extra = fit_frame_pairs(e, ctx, data)
            state.effects[name] = (np.stack([np.ravel(step), between]), pred)
            state.ho_extra = state.ho_extra + extra
        elif on_differences(e):
            pred = state.effects[name][1]
            state.ho_extra = state.ho_extra + held_out[name] - pred
        elif e.ho_columns is not None:
            theta, pred = state.effects[name]
            state.ho_extra = state.ho_extra + e.ho_columns(ctx) @ theta - pred
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
        Its parameters (from :func:`fit_effect`; a ``frame`` effect: (2, S), the factors of the
        fit half and those between the halves).

    Returns
    -------
    dict
        Global: the parameters by name (plus the effect's derived figures); per pixel: median,
        robust spread and count; per step: count, RMS, median and largest magnitude (a
        ``frame`` effect: and the RMS between the frames).
    """
    e = EFFECTS[name]
    if e.scope in ("global", "pair"):
        p = {k: float(v) for k, v in zip(e.param_names, theta)}
        return {**p, **e.figures(np.asarray(theta, float))}
    if e.scope == "pixel":
        v = theta[:, 0]
        return {f"median_{e.param_names[0]}": float(np.median(v)),
                f"spread_{e.param_names[0]}": float(1.4826 * np.median(np.abs(v - np.median(v)))),
                "n_pixels": int(v.size)}
    between = None
    if e.scope == "frame":
        theta, between = theta[0], theta[1]
    v = theta[theta != 0]
    out = {"n_steps": int(v.size), "rms": float(np.sqrt(np.mean(v ** 2))) if v.size else 0.0,
           "median_abs": float(np.median(np.abs(v))) if v.size else 0.0,
           "max_abs": float(np.abs(v).max()) if v.size else 0.0}
    if between is not None:
        b = between[between != 0]
        out["rms_between_frames"] = float(np.sqrt(np.mean(b ** 2))) if b.size else 0.0
    return out
