"""The library of candidate effects the base leakage model lacks.

Each effect is a physically motivated, small additive term ``Y += X @ theta`` on top of the
base model (the paper's leakage model with a constant dark level), with its own parameters,
linear in them so that it can be fitted to the base model's residual for all pixels at once.
The design columns ``X`` are built from the base model's prediction (signal above dark, light
rate), the exposure and the acquisition order. Each effect can also be *injected* into
simulated frames, so that diagnosis can be tested on data with an undeclared effect.

Scopes: ``global`` (a few parameters shared by the sensor), ``pixel`` (parameters per pixel),
``step`` (one parameter per light step, shared by the pixels), ``pair`` (a change between the
frames of one step: fitted on the frame differences, it acts on the held-out frames only),
``frame`` (a factor per light step on the fit half and one between the halves).

Each effect is one record (:class:`Effect`) that carries everything about it: its columns,
its injection into simulated data, the design rule that skips it, its derived figures and the
parameters no working sensor has. Adding an effect is one :func:`_register` call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Context:
    """What effect columns are built from (and injections, on a simulated sweep's truth);
    arrays (P, S) unless stated.

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
    n_fit : ndarray, (S,), optional
        Frames averaged in each fit-half sample (default 1).
    order_ho : ndarray, (S,), optional
        Acquisition order of the held-out frames of each step, on the scale of ``order``
        (default ``order``).
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
    n_fit: np.ndarray | None = None  # (S,) frames in each fit-half sample
    order_ho: np.ndarray | None = None  # (S,) acquisition order of the held-out frames


@dataclass
class FrameContext:
    """The raw frames of a simulated sweep an effect acting frame by frame is put into.

    Parameters
    ----------
    frames : ndarray, (N, P), DN, float
        Frames in acquisition order (changed in place by the injection).
    step_index : ndarray of int, (N,)
        Step of each frame (index into the steps, ``sweep.steps()`` order).
    frame_in_step : ndarray of int, (N,)
        Index of the frame within its step.
    terms : dict
        :func:`truth_terms` of the sweep (the truth per step, (P, S)).
    """

    frames: np.ndarray
    step_index: np.ndarray
    frame_in_step: np.ndarray
    terms: dict


def _no_skip(design, dark) -> None:
    return None


def _no_figures(theta) -> dict:
    return {}


def _plausible(params, scale) -> None:
    return None


@dataclass(frozen=True)
class Effect:
    """One candidate effect: how it is fitted, put into simulated data, skipped and judged.

    Adding an effect is one :func:`_register` call here (and its docs row).

    Parameters
    ----------
    name : str
        Its name (``hsiffc diagnose --list-effects``).
    summary : str
        One line describing it.
    scope : {"global", "pair", "pixel", "step", "frame"}
        What its parameters belong to (``frame``: a factor per light step on the fit half and
        one per light step between the halves, fitted on the frame differences).
    param_names : tuple of str
        Names of its parameters.
    columns : callable
        :class:`Context` -> (P, S, m) design columns of the effect (of the fit half).
    interpret : callable
        Fitted parameters (dict) -> one sentence.
    inject : callable, optional
        ``inject(ctx, size, rng)`` -> (P, S) DN the effect of ``size`` (``unit``) adds to every
        frame of a step of a simulated sweep (``ctx`` the truth's :class:`Context`).
    inject_frames : callable, optional
        ``inject_frames(frame_context, size, rng)``: the effect put into the raw frames one by
        one (effects that change from frame to frame), in place.
    unit : str
        Unit of the injected ``size``.
    skip : callable
        ``skip(design, dark_model) -> reason or None``: why the design cannot identify it
        (beyond the rules of its scope, :func:`hsiffc.diagnose.design.structural_skip`).
    figures : callable
        Fitted parameters (ndarray) -> derived figures for the report (dict).
    implausible : callable
        ``implausible(params, scale) -> reason or None``: parameters no working sensor has
        (``scale``: ``full_scale_dn``, ``max_exposure_ms``, ``min_exposure_ms``); the effect
        is then reported as a stand-in, not a finding.
    ho_columns : callable, optional
        :class:`Context` -> (P, S, m): the effect's columns on the held-out half where they
        differ from those of the fit half (an effect that depends on the frame within a step).
    steps_are_evidence : bool
        With ``ho_columns``: the effect is shown by the step means (a slow change in
        acquisition time), its held-out columns only follow it to the held-out frames' later
        time; the frame differences are not asked to show it on their own.
    pooled : bool
        A one-parameter per-pixel effect whose pixels' estimates are pooled towards the
        sensor's (precision-weighted, random-effects shrinkage): where the base absorbs all but
        a sliver of its column, a pixel's own estimate is mostly noise.
    """

    name: str
    summary: str  # one line for the README and --list-effects
    scope: str  # "global", "pixel", "step", "pair" or "frame"
    param_names: tuple
    columns: Callable  # Context -> (P, S, m)
    interpret: Callable  # params dict -> one sentence
    inject: Callable | None = None
    inject_frames: Callable | None = None
    unit: str = ""
    skip: Callable = _no_skip
    figures: Callable = _no_figures
    implausible: Callable = _plausible
    ho_columns: Callable | None = None
    steps_are_evidence: bool = False
    pooled: bool = False

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
        return {"global": m, "pair": m, "pixel": m * n_pixels, "step": n_light_steps,
                "frame": 2 * n_light_steps}[self.scope]


def _legendre(x, n):
    cols = [x, 1.5 * x ** 2 - 0.5, 2.5 * x ** 3 - 1.5 * x]
    return cols[:n]


def _curve_peak(theta):
    """Largest magnitude over [-1, 1] of a Legendre series (degrees 1..n) with ``theta``."""
    order = np.linspace(-1, 1, 201)
    return float(np.abs(sum(v * c for v, c in zip(theta, _legendre(order, len(theta))))).max())


def _stack(*cols):
    return np.stack(np.broadcast_arrays(*cols), axis=-1)


def _dy_dk(c):
    """dY/dk: how the response moves with an extra rate collected in the well (DN per DN/ms);
    the exposure for darks (no leakage there)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        light = np.where(c.k > 0, c.dydlnk / np.where(c.k > 0, c.k, 1.0), c.t)
    return np.where(c.light[None, :], light, c.t)


def _one_exposure(design, dark):
    if design.exposures < 2:
        return ("every sample has the same exposure: a dark signal is indistinguishable from "
                "the dark level")
    return None


def _too_big(fraction_of_full_scale, what):
    def check(params, scale):
        v = abs(float(params[what]))
        if v > fraction_of_full_scale * scale["full_scale_dn"]:
            return (f"{what} {params[what]:.4g} DN is more than "
                    f"{100 * fraction_of_full_scale:g} % of full scale")
        return None
    return check


def _out_of(what, low, high, unit=""):
    def check(params, scale):
        v = float(params[what])
        if not low <= v <= high:
            return f"{what} {v:.4g}{unit} is outside {low:g} .. {high:g}{unit}"
        return None
    return check


EFFECTS: dict[str, Effect] = {}


def _register(effect: Effect) -> Effect:
    EFFECTS[effect.name] = effect
    return effect


def _dark_current_skip(design, dark):
    if "n_dark_exposures" in dark:
        return "already in the base model (measured from the dark frames)"
    return _one_exposure(design, dark)


def _outside_skip(design, dark):
    if "n_dark_exposures" in dark:
        return ("the dark signal is in the base model (measured from the dark frames), where "
                "the data choose whether it leaks with the light's charge or not")
    return _one_exposure(design, dark)


def _negative_dark(key):
    def check(params, scale):
        if params[key] < 0 and abs(params[key]) > 3 * params.get(
                key.replace("median", "spread"), 0.0) / np.sqrt(max(params["n_pixels"], 1)):
            return f"a negative dark signal ({params[key]:.3g} DN/ms, median pixel)"
        return None
    return check


_register(Effect(
    "dark_current",
    "dark signal growing with exposure, per pixel (thermal generation; EMVA 1288 dark current)",
    "pixel", ("dark_current_dn_per_ms",),
    lambda c: _stack(_dy_dk(c)),
    lambda p: (f"the dark level rises by {p['median_dark_current_dn_per_ms']:.3g} DN/ms "
               "(median pixel): thermally generated charge, which grows with exposure and "
               "temperature"),
    # log-normal over the pixels with median ``size``; collected in the well (leaks with the
    # signal: see effect_term)
    inject=lambda c, size, rng: size * rng.lognormal(0.0, 0.3, size=(c.t.shape[0], 1)) * c.t,
    unit="DN/ms (median pixel)", skip=_dark_current_skip,
    implausible=_negative_dark("median_dark_current_dn_per_ms"),
))


_register(Effect(
    "dark_outside_well",
    "dark signal growing with exposure that does not leak: collected outside the photodiode "
    "(a global-shutter storage node, amplifier glow), per pixel",
    "pixel", ("dark_signal_dn_per_ms",),
    lambda c: _stack(c.t),  # added after the leakage: exactly t on every sample
    lambda p: (f"a dark signal of {p['median_dark_signal_dn_per_ms']:.3g} DN/ms (median pixel) "
               "that does not leak with the signal: charge collected outside the photodiode "
               "(a storage node, or glow of the readout), added after the leakage"),
    inject=lambda c, size, rng: size * rng.lognormal(0.0, 0.3, size=(c.t.shape[0], 1)) * c.t,
    unit="DN/ms (median pixel)", skip=_outside_skip,
    implausible=_negative_dark("median_dark_signal_dn_per_ms"), pooled=True,
))


def _offset_skip(design, dark):
    if design.light_exposures < 2:
        return ("all light steps share one exposure: a timing offset is indistinguishable from "
                "the light rate (responsivity)")
    return None


def _offset_implausible(params, scale):
    if abs(params["t0_ms"]) > scale["max_exposure_ms"]:
        return (f"a timing offset of {params['t0_ms']:.4g} ms, longer than the longest "
                f"exposure ({scale['max_exposure_ms']:.4g} ms)")
    return None


_register(Effect(
    "exposure_offset",
    "effective exposure differs from the nominal one by a constant t0 (shutter/trigger delay)",
    "global", ("t0_ms",),
    lambda c: _stack(c.dydt),
    lambda p: (f"the light dose behaves as if every exposure were {p['t0_ms']:.4g} ms longer: "
               "an exposure-timing offset (trigger or shutter delay), which matters most at "
               "short exposures and low signal"),
    inject=lambda c, size, rng: size * c.dydt,  # Y(t + t0) - Y(t), to first order
    unit="ms", skip=_offset_skip, implausible=_offset_implausible,
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
    inject=lambda c, size, rng: size * (c.signal / c.full_scale) ** 2,
    unit="DN at full scale (quadratic; negative = compressive)",
    figures=lambda th: {"deviation_at_full_scale_dn": float(th[0] + th[1])},
    implausible=_too_big(0.1, "deviation_at_full_scale_dn"),
))
_register(Effect(
    "pixel_nonlinearity",
    "per-pixel quadratic response nonlinearity (pixel-to-pixel differences in linearity)",
    "pixel", ("c2",),
    lambda c: _stack((c.signal / c.full_scale) ** 2),
    lambda p: (f"pixels bend differently with signal (spread of the quadratic term "
               f"{p['spread_c2']:.3g} DN per full scale): per-pixel linearity differences"),
    inject=lambda c, size, rng: (size * rng.standard_normal((c.t.shape[0], 1))
                                 * (c.signal / c.full_scale) ** 2),
    unit="DN at full scale (spread over the pixels)",
    implausible=_too_big(0.1, "spread_c2"),
))
_register(Effect(
    "offset_drift",
    "black level drifting with acquisition order (temperature or supply drift during the sweep)",
    "global", ("p1", "p2", "p3"),
    lambda c: _stack(*[np.broadcast_to(v, c.t.shape) for v in _legendre(c.order, 3)]),
    lambda p: (f"the offset drifts over the acquisition by up to {p['peak_dn']:.3g} DN: a "
               "temperature or supply drift during the sweep"),
    inject=lambda c, size, rng: np.broadcast_to(size * c.order, c.t.shape).copy(),
    unit="DN (linear peak)",
    figures=lambda th: {"peak_dn": _curve_peak(th)},
    implausible=_too_big(0.2, "peak_dn"),
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
    # Y(k (1 + eps)) - Y(k), to first order
    inject=lambda c, size, rng: (np.where(c.light, size * rng.standard_normal(c.t.shape[1]),
                                          0.0) * c.dydlnk),
    unit="relative (RMS over the steps)",
    implausible=_out_of("rms", 0.0, 0.2),
))
_register(Effect(
    "lamp_drift",
    "the light drifts smoothly with acquisition order (a lamp warming up, a source that "
    "drifts): a relative light change that is a cubic in acquisition order, shared by the pixels",
    "global", ("q1", "q2", "q3"),
    lambda c: _stack(*[c.dydlnk * v[None, :] for v in _legendre(c.order, 3)]),
    lambda p: (f"the light drifts over the acquisition by up to {100 * p['peak']:.3g} % "
               "(smoothly in acquisition order, equally in every pixel): a lamp warming up or "
               "a drifting source; order the steps randomly and monitor the light"),
    inject=lambda c, size, rng: (np.where(c.light, size * c.order, 0.0) * c.dydlnk),
    unit="relative (linear peak)",
    figures=lambda th: {"peak": _curve_peak(th)},
    implausible=_out_of("peak", 0.0, 0.5),
    # the held-out frames of a step come later: the drift goes on between the frames
    ho_columns=lambda c: _stack(*[c.dydlnk * v[None, :] for v in _legendre(
        c.order if c.order_ho is None else c.order_ho, 3)]),
    steps_are_evidence=True,
))
_register(Effect(
    "image_lag",
    "a fraction of the previous frame's signal carried into the next (lag, persistence)",
    "global", ("lag",),
    lambda c: _stack(c.prev_signal),
    lambda p: (f"{100 * p['lag']:.3g} % of the previous step's signal reappears: image lag "
               "(incomplete charge transfer or persistence)"),
    inject=lambda c, size, rng: size * c.prev_signal,
    unit="fraction of the previous step's signal",
    implausible=_out_of("lag", -0.01, 0.3),
))


def _frame_lag_fit(c):
    """Carried into the fit half: its first frame carries the previous step's last frame,
    its other frames (3 or more a step) a frame of the same step."""
    n = np.ones(c.t.shape[1]) if c.n_fit is None else np.asarray(c.n_fit, float)
    return _stack((c.prev_signal + (n[None, :] - 1) * c.signal) / n[None, :])


def _frame_lag_frames(fc, size, rng):
    """A fraction ``size`` of each frame's signal above the dark level is read again in the
    next frame (the frames in acquisition order; darks carry it too)."""
    d = fc.terms["d"][:, 0]
    signal = fc.frames - d[None, :]
    fc.frames[1:] += size * signal[:-1]


def _pair_skip(design, dark):
    if not design.pairs:
        return "one frame per step: a change between the frames of a step cannot be seen"
    return None


_register(Effect(
    "frame_lag",
    "a fraction of each frame's signal carried into the next frame (lag within and between "
    "steps): the first frame of a step carries the step before, the others their own step",
    "global", ("lag",),
    _frame_lag_fit,
    lambda p: (f"{100 * p['lag']:.3g} % of each frame's signal reappears in the next frame: "
               "image lag from frame to frame (incomplete charge transfer); the first frame of "
               "a step carries the step before"),
    inject_frames=_frame_lag_frames, unit="fraction of the previous frame's signal",
    skip=_pair_skip, implausible=_out_of("lag", -0.01, 0.3),
    ho_columns=lambda c: _stack(c.signal),
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
    # per frame index within the step: see add_term(per_frame=True)
    inject=lambda c, size, rng: size * np.where(c.light, c.dydlnk, 0.0),
    unit="relative light change per frame", skip=_pair_skip,
    implausible=_out_of("eps", -0.2, 0.2),
))


def _flicker_frames(fc, size, rng):
    """Every light frame sees its own light level, ``1 + size * N(0, 1)`` times the step's."""
    light = fc.terms["light"][fc.step_index]
    eps = np.where(light, size * rng.standard_normal(fc.frames.shape[0]), 0.0)
    fc.frames += eps[:, None] * fc.terms["dydlnk"][:, fc.step_index].T


_register(Effect(
    "frame_flicker",
    "the light level of every frame differs at random (flicker of the source from frame to "
    "frame): a factor per light step on the frames that fit and one between the halves, "
    "shared by the pixels",
    "frame", ("gain_error",),
    lambda c: _stack(c.dydlnk),
    lambda p: (f"the light of single frames differs by {100 * p['rms_between_frames']:.3g} % "
               "RMS between the frames of a step (equally in every pixel): the source flickers "
               "from frame to frame; frames of one step are not exchangeable and their "
               "differences are not noise"),
    inject_frames=_flicker_frames, unit="relative (RMS over the frames)", skip=_pair_skip,
    implausible=_out_of("rms_between_frames", 0.0, 0.2),
))

def _frame_mean_signal(c):
    """The mean signal of each step's pixels over full scale, on every pixel of the step
    (P, S): what an offset common to the pixels of a frame that follows its signal sees."""
    m = np.mean(c.signal, axis=0, keepdims=True) / c.full_scale
    return np.broadcast_to(m, c.signal.shape)


def _frame_signal_shape(c):
    """Columns of an offset common to the pixels of a frame that is any smooth function of
    the frame's mean signal (P, S, 7): a line with a change of slope at every eighth of the
    brightest light step's mean signal (the line itself is the base's gain and dark level).
    An offset that sets in above a level, as a clamp does, is no polynomial."""
    m = _frame_mean_signal(c)
    light = np.asarray(c.light, bool)
    top = float(m[0, light].max()) if light.any() else float(m.max())
    return _stack(*[np.maximum(m - q * top / 8.0, 0.0) for q in range(1, 8)])


#: An offset common to the pixels of a frame that follows the frame's mean signal, whatever
#: its shape (:func:`_frame_signal_shape`): a black-level clamp is one, outside the library.
FRAME_SIGNAL_OFFSET = Effect(
    "common_offset_of_frame_signal",
    "an offset common to the pixels of a frame, a smooth function of the frame's mean signal "
    "(not each pixel's own): piecewise linear, a change of slope at every eighth of the "
    "brightest step's", "global", tuple(f"slope_change_{q}_8" for q in range(1, 8)),
    _frame_signal_shape,
    lambda p: "an offset common to the pixels that follows the frame's mean signal")

#: Offsets common to the pixels of a frame, outside the library (a black-level clamp that
#: follows the frame's signal is one): fitted in place of the library effect they share a
#: pattern with, to tell whether that effect stands in for them (never candidates, never
#: injected). ``readout_nonlinearity`` bends each pixel's response with its own signal, and
#: ``lamp_drift`` scales it smoothly in acquisition order (which follows the signal in a sorted
#: sweep); their probe is an offset that follows the mean signal of the frame, the same for
#: every pixel. ``illumination_error`` scales each pixel's signal per step; its probe is one
#: offset (DN) per light step, the same for every pixel.
OFFSET_PROBES = {
    "readout_nonlinearity": FRAME_SIGNAL_OFFSET,
    "lamp_drift": FRAME_SIGNAL_OFFSET,
    "illumination_error": Effect(
        "common_offset_per_step",
        "an offset (DN) per light step common to the pixels", "step", ("offset_dn",),
        lambda c: _stack(np.broadcast_to(c.light[None, :].astype(float), c.signal.shape)),
        lambda p: "an offset per light step common to the pixels"),
}

#: Per-step effects whose factors may follow the frame's signal instead of varying at random
#: from step to step: where an offset that follows the frame's mean signal (a few parameters)
#: predicts the held-out data as well as one factor per step, the factors are a misfit of the
#: model, not a light error (:func:`hsiffc.diagnose.select.offset_stand_in`).
SMOOTH_PROBES = {"illumination_error": FRAME_SIGNAL_OFFSET}


ALIASES = {"gain_nonlinearity": "readout_nonlinearity"}  # earlier name, still accepted

# an effect outside the library, for testing that structure nobody declared is reported
OUTSIDE = {
    "adc_ripple": "periodic ADC differential nonlinearity: + A sin(2 pi Y / 37 DN)",
}


def inject(name: str, size: float, *, t, k, signal, order, prev_signal, light, full_scale,
           rng, dydt=None, dydlnk=None) -> np.ndarray:
    """Additive DN of effect ``name`` of a given ``size`` for frames of a simulated sweep.

    Arguments are (P, S) arrays of the true exposure, light rate and signal (S steps, P pixels).
    ``size`` is in each effect's ``unit`` (:class:`Effect`; ``adc_ripple``: amplitude in DN).

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
        exposure_offset, frame_light_change, illumination_error and lamp_drift).

    Returns
    -------
    ndarray, (P, S), DN
        To add to the true response.

    Raises
    ------
    KeyError
        Unknown effect, or one that acts frame by frame (the message lists the known ones).
    """
    name = ALIASES.get(name, name)
    if name == "adc_ripple":
        return size * np.sin(2 * np.pi * (signal + 32.0) / 37.0) * (signal > 0)
    effect = EFFECTS.get(name)
    if effect is None or effect.inject is None:
        raise KeyError(f"unknown effect {name!r} (or one put in frame by frame: add_effect); "
                       f"known: {sorted(EFFECTS) + sorted(OUTSIDE)}")
    zeros = np.zeros_like(signal)
    ctx = Context(t=t, k=k, signal=signal, order=order, prev_signal=prev_signal, light=light,
                  full_scale=full_scale, dydt=zeros if dydt is None else dydt,
                  dydlnk=zeros if dydlnk is None else dydlnk)
    return effect.inject(ctx, size, rng)


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


def add_frames(sweep, change, *, meta: dict | None = None):
    """A copy of a simulated sweep whose raw frames ``change(frame_context)`` alters in place
    (a :class:`FrameContext` of float frames (N, P) in acquisition order), rounded and clipped
    to the ADC range as the sensor would.

    Parameters
    ----------
    sweep : Sweep
        A simulated sweep with ``meta["truth"]``.
    change : callable
        ``change(frame_context)``.
    meta : dict, optional
        Entries to add to the copy's ``meta``.

    Returns
    -------
    Sweep
    """
    from dataclasses import replace as replace_fields

    terms = truth_terms(sweep)
    steps = list(terms["steps"])
    n = sweep.n_frames
    step_index = np.array([steps.index(s) for s in sweep.step])
    frame_in_step = np.zeros(n, int)
    for s in steps:
        sel = np.flatnonzero(sweep.step == s)
        frame_in_step[sel] = np.arange(sel.size)
    frames = sweep.data.reshape(n, -1).astype(np.float64)
    change(FrameContext(frames=frames, step_index=step_index, frame_in_step=frame_in_step,
                        terms=terms))
    data = np.clip(np.rint(frames), 0, sweep.full_scale_dn).reshape(sweep.data.shape)
    return replace_fields(sweep, data=data.astype(sweep.data.dtype),
                          meta={**sweep.meta, **(meta or {})})


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
    name = ALIASES.get(name, name)
    meta = {"injected_effect": {"name": name, "size": size, "seed": seed}}
    effect = EFFECTS.get(name)
    if effect is not None and effect.inject_frames is not None:
        return add_frames(sweep, lambda fc: effect.inject_frames(
            fc, size, np.random.default_rng(seed)), meta=meta)
    extra = effect_term(sweep, name, size, seed=seed, in_well=in_well)
    return add_term(sweep, extra, per_frame=name == "frame_light_change", meta=meta)
