"""The library of candidate effects the base leakage model lacks.

Each effect is a physically motivated, small additive term ``Y += X @ theta`` on top of the
base model (the paper's leakage model with a constant dark level), with its own parameters,
linear in them so that it can be fitted to the base model's residual for all pixels at once.
The design columns ``X`` are built from the base model's prediction (signal above dark, light
rate), the exposure and the acquisition order. Each effect can also be *injected* into
simulated frames, so that diagnosis can be tested on data with an undeclared effect.

Scopes: ``global`` (a few parameters shared by the sensor), ``pixel`` (parameters per pixel),
``step`` (one parameter per light step, shared by the pixels), ``pair`` (a change between the
frames of one step: fitted on the frame differences, it acts on the held-out frames only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Context:
    """What effect columns are built from; arrays (P, S) unless stated.

    Parameters
    ----------
    t : ndarray, ms
        Exposure.
    k : ndarray, DN/ms
        Base-model light rate (0 for darks).
    signal : ndarray, DN
        Base-model response above the dark level.
    order : ndarray, (S,)
        Acquisition order scaled to [-1, 1].
    prev_signal : ndarray, DN
        Base-model signal of the previous step in acquisition order.
    light : ndarray of bool, (S,)
        Light steps.
    full_scale : float, DN
        ``2**bit_depth - 1``.
    dydt : ndarray, DN/ms
        Base-model ``dY/dt = k - a e^{bY}``.
    dydlnk : ndarray, DN
        Base-model ``dY / d ln k``.
    """

    t: np.ndarray  # exposure, ms
    k: np.ndarray  # base-model light rate, DN/ms (0 for darks)
    signal: np.ndarray  # base-model response above the dark level, DN
    order: np.ndarray  # (S,) acquisition order scaled to [-1, 1]
    prev_signal: np.ndarray  # base-model signal of the previous step in acquisition order
    light: np.ndarray  # (S,) bool
    full_scale: float
    dydt: np.ndarray  # base-model dY/dt = k - a e^{bY}, DN/ms
    dydlnk: np.ndarray  # base-model dY / d ln k, DN


@dataclass(frozen=True)
class Effect:
    """One candidate effect (see the module docstring).

    Parameters
    ----------
    name : str
        Its name (``hsiffc diagnose --list-effects``).
    summary : str
        One line describing it.
    scope : {"global", "pair", "pixel", "step"}
        What its parameters belong to.
    param_names : tuple of str
        Names of its parameters.
    columns : callable
        :class:`Context` -> (P, S, m) design columns of the effect.
    interpret : callable
        Fitted parameters (dict) -> one sentence.
    """

    name: str
    summary: str  # one line for the README and --list-effects
    scope: str  # "global", "pixel" or "step"
    param_names: tuple
    columns: Callable  # Context -> (P, S, m)
    interpret: Callable  # params dict -> one sentence

    def n_params(self, n_pixels: int, n_light_steps: int) -> int:
        """Free parameters the effect adds (for the information criterion).

        Parameters
        ----------
        n_pixels : int
            Pixels analysed.
        n_light_steps : int
            Light steps of the fit.

        Returns
        -------
        int
        """
        m = len(self.param_names)
        return {"global": m, "pair": m, "pixel": m * n_pixels, "step": n_light_steps}[self.scope]


def _legendre(x, n):
    cols = [x, 1.5 * x ** 2 - 0.5, 2.5 * x ** 3 - 1.5 * x]
    return cols[:n]


def _stack(*cols):
    return np.stack(np.broadcast_arrays(*cols), axis=-1)


def _dy_dk(c):
    """dY/dk: how the response moves with an extra rate collected in the well (DN per DN/ms);
    the exposure for darks (no leakage there)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        light = np.where(c.k > 0, c.dydlnk / np.where(c.k > 0, c.k, 1.0), c.t)
    return np.where(c.light[None, :], light, c.t)


EFFECTS: dict[str, Effect] = {}


def _register(effect: Effect) -> Effect:
    EFFECTS[effect.name] = effect
    return effect


_register(Effect(
    "dark_current",
    "dark signal growing with exposure, per pixel (thermal generation; EMVA 1288 dark current)",
    "pixel", ("dark_current_dn_per_ms",),
    lambda c: _stack(_dy_dk(c)),
    lambda p: (f"the dark level rises by {p['median_dark_current_dn_per_ms']:.3g} DN/ms "
               "(median pixel): thermally generated charge, which grows with exposure and "
               "temperature"),
))
_register(Effect(
    "exposure_offset",
    "effective exposure differs from the nominal one by a constant t0 (shutter/trigger delay)",
    "global", ("t0_ms",),
    lambda c: _stack(c.dydt),
    lambda p: (f"the light dose behaves as if every exposure were {p['t0_ms']:.4g} ms longer: "
               "an exposure-timing offset (trigger or shutter delay), which matters most at "
               "short exposures and low signal"),
))
_register(Effect(
    "readout_nonlinearity",
    "sensor-wide response nonlinearity that depends on the signal only (ADC / source-follower "
    "compression; EMVA 1288 linearity error): quadratic and cubic in the signal",
    "global", ("c2", "c3"),
    lambda c: _stack((c.signal / c.full_scale) ** 2, (c.signal / c.full_scale) ** 3),
    lambda p: (f"the response bends with signal alone (quadratic {p['c2']:.3g}, cubic "
               f"{p['c3']:.3g} DN per full scale; {p['deviation_at_full_scale_dn']:.3g} DN at full "
               "scale, negative = compressive): a readout (ADC or source-follower) nonlinearity "
               "shared by the sensor, which unlike leakage does not depend on the light rate"),
))
_register(Effect(
    "pixel_nonlinearity",
    "per-pixel quadratic response nonlinearity (pixel-to-pixel differences in linearity)",
    "pixel", ("c2",),
    lambda c: _stack((c.signal / c.full_scale) ** 2),
    lambda p: (f"pixels bend differently with signal (spread of the quadratic term "
               f"{p['spread_c2']:.3g} DN per full scale): per-pixel linearity differences"),
))
_register(Effect(
    "offset_drift",
    "black level drifting with acquisition order (temperature or supply drift during the sweep)",
    "global", ("p1", "p2", "p3"),
    lambda c: _stack(*[np.broadcast_to(v, c.t.shape) for v in _legendre(c.order, 3)]),
    lambda p: (f"the offset drifts over the acquisition by up to {p['peak_dn']:.3g} DN: a "
               "temperature or supply drift during the sweep"),
))
_register(Effect(
    "illumination_error",
    "per-step error of the light level common to all pixels (lamp instability, photon count)",
    "step", ("gain_error",),
    lambda c: _stack(c.dydlnk),
    lambda p: (f"the light level of single steps differs from the stated one by "
               f"{100 * p['median_abs']:.3g} % (median over steps; RMS {100 * p['rms']:.3g} %, "
               "largest at the weakest steps, where it is least determined), equally in every "
               "pixel: light-source instability or an error of the step's photon count"),
))
_register(Effect(
    "image_lag",
    "a fraction of the previous frame's signal carried into the next (lag, persistence)",
    "global", ("lag",),
    lambda c: _stack(c.prev_signal),
    lambda p: (f"{100 * p['lag']:.3g} % of the previous step's signal reappears: image lag "
               "(incomplete charge transfer or persistence)"),
))

_register(Effect(
    "frame_light_change",
    "the light changes between the frames of one step (source warming or flicker): the second "
    "frame of a step sees a light rate (1 + eps) times the first",
    "pair", ("eps",),
    lambda c: _stack(c.dydlnk),
    lambda p: (f"the light of a step's next frame differs by {100 * p['eps']:.3g} % from the frame "
               "before (equally in every pixel): the light source drifts within a step (warm-up, "
               "flicker); frames of one step are not exchangeable"),
))

ALIASES = {"gain_nonlinearity": "readout_nonlinearity"}  # earlier name, still accepted

# an effect outside the library, for testing that structure nobody declared is reported
OUTSIDE = {
    "adc_ripple": "periodic ADC differential nonlinearity: + A sin(2 pi Y / 37 DN)",
}


def inject(name: str, size: float, *, t, k, signal, order, prev_signal, light, full_scale,
           rng, dydt=None, dydlnk=None) -> np.ndarray:
    """Additive DN of effect ``name`` of a given ``size`` for frames of a simulated sweep.

    Arguments are (P, S) arrays of the true exposure, light rate and signal (S steps, P pixels).
    ``size`` is in each effect's natural unit: DN/ms (dark_current, median of a log-normal
    per-pixel spread), ms (exposure_offset), DN at full scale (readout_nonlinearity: the quadratic
    term, negative = compressive; pixel_nonlinearity: the per-pixel spread), DN (offset_drift:
    linear peak; adc_ripple: amplitude), relative (illumination_error: RMS; image_lag: fraction;
    frame_light_change: light change per frame within a step, applied by :func:`add_effect`).

    Parameters
    ----------
    name : str
        Effect name (or alias).
    size : float
        Its size in the unit above.
    t, k, signal : ndarray, (P, S)
        True exposure (ms), light rate (DN/ms) and signal above dark (DN).
    order : ndarray, (S,)
        Acquisition order scaled to [-1, 1].
    prev_signal : ndarray, (P, S), DN
        True signal of the previous step.
    light : ndarray of bool, (S,)
        Light steps.
    full_scale : float, DN
        ADC full scale.
    rng : numpy.random.Generator
        Source of the random spreads.
    dydt, dydlnk : ndarray, (P, S), optional
        ``dY/dt`` (DN/ms) and ``dY/d ln k`` (DN) of the true model (needed by
        exposure_offset, frame_light_change and illumination_error).

    Returns
    -------
    ndarray, (P, S), DN
        To add to the true response.

    Raises
    ------
    KeyError
        Unknown effect (the message lists the known ones).
    """
    fs = full_scale
    name = ALIASES.get(name, name)
    if name == "dark_current":
        dc = size * rng.lognormal(0.0, 0.3, size=(t.shape[0], 1))
        return dc * t
    if name == "exposure_offset":  # Y(t + t0) - Y(t), to first order
        return size * dydt
    if name == "readout_nonlinearity":
        return size * (signal / fs) ** 2
    if name == "frame_light_change":  # per frame index within the step: see add_effect
        return size * np.where(light, dydlnk, 0.0)
    if name == "pixel_nonlinearity":
        c = size * rng.standard_normal((t.shape[0], 1))
        return c * (signal / fs) ** 2
    if name == "offset_drift":
        return np.broadcast_to(size * order, t.shape).copy()
    if name == "illumination_error":
        eps = size * rng.standard_normal(t.shape[1])
        return np.where(light, eps, 0.0) * dydlnk  # Y(k (1 + eps)) - Y(k), to first order
    if name == "image_lag":
        return size * prev_signal
    if name == "adc_ripple":
        return size * np.sin(2 * np.pi * (signal + 32.0) / 37.0) * (signal > 0)
    raise KeyError(f"unknown effect {name!r}; known: {sorted(EFFECTS) + sorted(OUTSIDE)}")


def truth_terms(sweep) -> dict:
    """The noise-free quantities an effect is built from, per pixel and step of a simulated
    sweep (``meta["truth"]``): exposure ``t`` (S,) ms, ``light`` (S,) bool, light rate
    ``k_light`` and total rate ``k`` (P, S) DN/ms, leakage ``a`` and ``b`` and dark level ``d``
    (P, 1), the expected response ``expected`` and ``signal`` above dark (P, S) DN, ``dydt`` and
    ``dydlnk``, acquisition ``order`` (S,) and the previous step's signal ``prev`` (P, S).

    Parameters
    ----------
    sweep : Sweep
        A simulated sweep with ``meta["truth"]``.

    Returns
    -------
    dict

    Raises
    ------
    ValueError
        The sweep has no ``meta["truth"]``.
    """
    from ..leakage import model as leakage_model

    truth = sweep.meta.get("truth")
    if truth is None:
        raise ValueError("add_effect needs a simulated sweep with meta['truth'] "
                         "(MosaicSensor.sweep)")
    steps = sweep.steps()
    light = np.array([sweep.kind[sweep.step == s][0] == "light" for s in steps])
    t = np.array([sweep.exposure_ms[sweep.step == s][0] for s in steps])
    levels = np.asarray(sweep.meta.get("levels", np.where(light, 1.0, 0.0)), float)
    k_light = truth.k_dn_per_ms.reshape(-1, 1) * levels[None, :]
    k = np.where(light[None, :], k_light, 0.0) + truth.dark_current_dn_per_ms.reshape(-1, 1)
    a = truth.a_dn_per_ms.reshape(-1, 1)
    b = truth.b_per_dn.reshape(-1, 1)
    d = truth.dark_dn.reshape(-1, 1)
    expected = leakage_model.response(t[None, :], k, a, b, d)
    eps = 1e-4
    dydlnk = (leakage_model.response(t[None, :], k * (1 + eps), a, b, d)
              - leakage_model.response(t[None, :], k * (1 - eps), a, b, d)) / (2 * eps)
    signal = expected - d
    prev = np.zeros_like(signal)
    prev[:, 1:] = signal[:, :-1]
    return {"steps": steps, "light": light, "t": t, "k_light": k_light, "k": k, "a": a, "b": b,
            "d": d, "expected": expected, "signal": signal, "prev": prev,
            "dydt": k - leakage_model.leakage_rate(expected, a, b), "dydlnk": dydlnk,
            "order": (np.arange(len(steps)) / max(len(steps) - 1, 1)) * 2 - 1}


def effect_term(sweep, name: str, size: float, *, seed: int = 0, in_well: bool = True,
                terms: dict | None = None) -> np.ndarray:
    """What effect ``name`` of ``size`` adds to the noise-free response of every pixel and step
    of a simulated sweep, (P, S) in DN (see :func:`add_effect`; ``frame_light_change``: what
    it adds to the second frame of a step).

    Parameters
    ----------
    sweep : Sweep
        A simulated sweep with ``meta["truth"]``.
    name : str
        Effect name.
    size : float
        Its size (see :func:`inject`).
    seed : int
        Seed of the effect's random spreads.
    in_well : bool
        dark_current only: collected in the well (True) or added after the leakage.
    terms : dict, optional
        :func:`truth_terms` of the sweep (computed when not given).

    Returns
    -------
    ndarray, (P, S), DN
    """
    from ..leakage import model as leakage_model

    c = truth_terms(sweep) if terms is None else terms
    t, light = c["t"], c["light"]
    extra = inject(name, size, t=np.broadcast_to(t, c["signal"].shape),
                   k=c["k_light"] * light[None, :], signal=c["signal"], order=c["order"],
                   prev_signal=c["prev"], light=light, full_scale=float(sweep.full_scale_dn),
                   rng=np.random.default_rng(seed), dydt=c["dydt"], dydlnk=c["dydlnk"])
    if ALIASES.get(name, name) == "dark_current" and in_well:  # collected and leaking
        extra = leakage_model.response(t[None, :], c["k"] + extra / np.maximum(t[None, :], 1e-12),
                                       c["a"], c["b"], c["d"]) - c["expected"]
    return extra


def add_term(sweep, extra, *, per_frame: bool = False, meta: dict | None = None):
    """A copy of ``sweep`` with ``extra`` (P, S) DN added to the raw frames of every step
    (``per_frame``: ``j * extra`` to frame j of the step), rounded and clipped to the ADC range
    as the sensor would.

    Parameters
    ----------
    sweep : Sweep
        Frames (N, H, W).
    extra : ndarray, (P, S), DN
        P = H * W pixels, S steps (in ``sweep.steps()`` order).
    per_frame : bool
        Scale by the frame's index within its step.
    meta : dict, optional
        Entries to add to the copy's ``meta``.

    Returns
    -------
    Sweep
    """
    from dataclasses import replace as replace_fields

    h, w = sweep.frame_shape
    data = sweep.data.astype(np.float64)
    for i, s in enumerate(sweep.steps()):
        sel = np.flatnonzero(sweep.step == s)
        for j, f in enumerate(sel):
            data[f] += (j if per_frame else 1) * extra[:, i].reshape(h, w)
    data = np.clip(np.rint(data), 0, sweep.full_scale_dn).astype(sweep.data.dtype)
    return replace_fields(sweep, data=data, meta={**sweep.meta, **(meta or {})})


def add_effect(sweep, name: str, size: float, *, seed: int = 0, in_well: bool = True):
    """A copy of a simulated sweep (with ``meta["truth"]``) with effect ``name`` added to its
    raw frames (then rounded and clipped to the ADC range as the sensor would).

    The effect acts on the true signal of each step: light steps use the truth's light rate,
    dark steps none; acquisition order is the frame order. ``in_well`` (dark_current only; the
    default): the extra dark charge is collected in the well and leaks with the signal (through
    the model's ODE); False adds it to the response after the leakage.

    Parameters
    ----------
    sweep : Sweep
        A simulated sweep (``meta["truth"]`` from :mod:`hsiffc.simulate`).
    name : str
        Effect name (``hsiffc diagnose --list-effects``).
    size : float
        Its size in the effect's unit (see :func:`inject`).
    seed : int
        Seed of the effect's random spreads.
    in_well : bool
        dark_current only: collected in the well (True) or added after the leakage.

    Returns
    -------
    Sweep
        A copy with the effect in its raw frames (DN, the sweep's dtype) and the effect
        recorded in ``meta``.

    Raises
    ------
    ValueError
        The sweep has no ``meta["truth"]``.

    Examples
    --------
    >>> from hsiffc.diagnose.simulated import simulated_sweep
    >>> sweep = simulated_sweep("exposure", shape=(4, 4), n_steps=6, seed=3)
    >>> lagged = add_effect(sweep, "image_lag", 0.05)
    >>> lagged.data.shape == sweep.data.shape, bool((lagged.data != sweep.data).any())
    (True, True)
    """
    extra = effect_term(sweep, name, size, seed=seed, in_well=in_well)
    return add_term(sweep, extra, per_frame=ALIASES.get(name, name) == "frame_light_change",
                    meta={"injected_effect": {"name": name, "size": size, "seed": seed}})
