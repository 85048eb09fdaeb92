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
(:func:`~hsiffc.diagnose.design.clip_level`), that sit on a full well's plateau below it with
the read noise alone (:func:`~hsiffc.diagnose.design.well_plateau`) or at its lowest code are
left out.

Its named parts, in the order :func:`diagnose` runs them: the samples (:func:`prepare`, a
:class:`Samples`), the base model's fit, the noise model (:class:`NoiseModel`: the frame
differences tested against the temporal-noise model and cleared before they are the floor),
the search from one starting model (:func:`search`, run from each base), the leakage check, the
residual check (:func:`residual_check`), the verdict and the typed result
(:class:`~hsiffc.diagnose.result.Diagnosis`, read as a dict too). An effect kept while the
verdict is unexplained, or with physically implausible parameters, is reported as a stand-in
for what the library lacks (``stand_in_for_unexplained``), not as a finding.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import DataFormatError
from ..data.sweep import Sweep
from . import design as ds
from .bases import LeakageBase, LinearBase, SharedLeakageBase
from .effects import ALIASES, EFFECTS, OUTSIDE, inject
from .fitdata import Data
from .fitting import (State, context, describe_params, fitpredict, gram, projector, refit_base,
                      separable_fraction)
from .result import Diagnosis, ResidualArrays
from .select import (RULE, UNEXPLAINED_OF_FLOOR, Fitted, equally_good, evaluate,
                     frame_constant_stand_in, greedy, improves, leakage_check, leakage_stand_in,
                     offset_left, offset_stand_in, paired, refit)
from .structure import groupings, structure

__all__ = ["diagnose", "Diagnosis", "EFFECTS", "NoiseModel", "OUTSIDE", "Samples", "inject",
           "list_effects", "prepare", "search"]

MIN_LIGHT_STEPS = 4
#: BIC lower by more than this (very strong evidence) makes the dark signal one collected
#: outside the photodiode, where its held-out error is as good
DARK_BIC_MARGIN = 10.0


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


class NoiseModel:
    """The temporal noise of the held-out samples, and what it is for a model.

    With frame pairs it is measured on the differences between the halves of every step,
    tested against the noise model and cleared of what follows the signal across the pixels
    (:func:`hsiffc.diagnose.design.noise_pairs`; ``test`` holds the figures); a model with an
    effect between the halves gets it measured on the differences less what the effect
    predicts (:meth:`var_step_of`). Without frame pairs it is the spread of the held-out
    residual across the pixels of a step (:func:`hsiffc.diagnose.design.noise_from_spread`).
    Integer raw data add the rounding bias of quiet samples (:func:`quantisation_bias`).

    Parameters
    ----------
    smp : dict
        From :func:`hsiffc.diagnose.design.samples`.
    both : ndarray of bool, (P, S)
        Samples valid in both halves.
    quantum : float, DN
        Step of the recorded values (0: float data).
    shape : (int, int)
        (P, S).
    """

    def __init__(self, smp, both, quantum, shape):
        self.smp, self.both, self.quantum, self.shape = smp, both, quantum, shape
        self.pairs = bool(smp["pairs"])
        self.test = {}
        self.var_step = None  # (S,) DN^2, one frame per step
        self.noise2 = None  # (P, S) DN^2, one held-out sample
        self.source = ("frame pairs (the held-out minus the fit frames of every step, cleared "
                       "of what follows the signal across the pixels)" if self.pairs else
                       "spread of the held-out residual across pixels within a step")

    def from_pairs(self):
        """Measure the noise on the frame pairs (with the test)."""
        self.var_step, self.test = ds.noise_pairs(self.smp, self.both, with_test=True)
        self.noise2 = self._noise2(self.var_step)

    def from_spread(self, var1):
        """Set the noise from the spread model ``var1`` (P, S) of one frame, DN^2."""
        self.noise2 = var1 / self.smp["n_ho"][None, :]
        self.var_step = np.median(var1, axis=0)
        self.test = {"note": "no frame pairs: the noise is the spread across pixels"}

    def _noise2(self, vs):
        # integer raw data: the rounding bias of a quiet pixel is in the held-out error but
        # not in the frame pairs
        return np.broadcast_to((vs / self.smp["n_ho"] + ds.quantisation_bias(
            vs, self.quantum))[None, :], self.shape)

    def var_step_of(self, state):
        """The noise of one frame per step (S,) for a model: with an effect between the halves
        in it, measured on the frame differences less what it predicts."""
        extra = state.ho_extra
        if not self.pairs or np.ndim(extra) == 0:
            return self.var_step
        return ds.noise_pairs({**self.smp, "y_ho": self.smp["y_ho"] - extra}, self.both)

    def noise2_of(self, state, vs=None):
        """The noise variance (P, S) of each held-out sample for a model; ``vs``: its
        :meth:`var_step_of`, where already measured."""
        vs = self.var_step_of(state) if vs is None else vs
        return self.noise2 if vs is self.var_step else self._noise2(vs)

    def refloor(self, fitted, floor, valid_ho):
        """The noise floor ``floor`` of the start model, for ``fitted``."""
        if np.ndim(fitted.state.ho_extra) == 0:
            return floor
        less = float(np.mean((self.noise2 - self.noise2_of(fitted.state))[valid_ho]))
        return float(np.sqrt(max(floor ** 2 - less, 1e-12 * floor ** 2)))

    def floor(self, pred_var, valid_ho):
        """RMS noise (DN) of the held-out samples, the fit's own prediction variance
        ``pred_var`` (P, S) included."""
        return float(np.sqrt(np.mean((self.noise2 + pred_var)[valid_ho])))

    def simulate_frames(self, level, n_frames, rng, sigma_step):
        """The mean of ``n_frames`` simulated frames per step around ``level`` (P, S): integer
        data with frame pairs are simulated as the ADC records them, so the rounding bias of
        quiet pixels (common to the pixels of a step) is in the null."""
        q = self.sim_quantum
        if q <= 0:
            return level + sigma_step / np.sqrt(n_frames) * rng.standard_normal(level.shape)
        total = np.zeros(level.shape)
        for k in range(int(n_frames.max())):
            frame = np.round((level + sigma_step * rng.standard_normal(level.shape)) / q)
            total += np.where(k < n_frames, frame * q, 0.0)
        return total / np.maximum(n_frames, 1)

    @property
    def sim_quantum(self):
        """The rounding the null simulates (DN): the ADC's, with frame pairs."""
        return self.quantum if self.pairs else 0.0


@dataclass
class Search:
    """The result of :func:`search` from one starting model: the model selected, and the
    candidates the design skips, those its base absorbs (``weak``) and the ties."""

    final: Fitted
    start: Fitted
    skipped: list
    weak: dict
    ambiguous: list
    floor: float


@dataclass
class Problem:
    """What every search works on: the samples, design, dark model, candidate names, counts and
    the noise model (see :func:`diagnose`)."""

    data: Data
    des: ds.Design
    dark_desc: dict
    names: list
    n_pix: int
    n_light: int
    noise: NoiseModel
    candidates: list = field(default_factory=list)

    def refloor(self, fitted, floor):
        """:meth:`NoiseModel.refloor` on this problem's held-out samples."""
        return self.noise.refloor(fitted, floor, self.data.valid_ho)


def search(problem: Problem, start: Fitted, floor: float) -> Search:
    """The greedy search (:func:`hsiffc.diagnose.select.greedy`) from one starting model, with
    the candidates this design can identify next to its base.

    Parameters
    ----------
    problem : Problem
        The samples and candidates.
    start : Fitted
        The base model alone.
    floor : float, DN
        The noise floor with that base.

    Returns
    -------
    Search
    """
    st = start.state
    skipped, testable, weak = _identifiable(problem.names, st.base, st.theta, problem.data,
                                            problem.des, problem.dark_desc)
    ambiguous: list = []
    final = greedy(start, testable, problem.data, floor, problem.n_pix, problem.n_light,
                   problem.candidates, label=st.base.name, ambiguous=ambiguous,
                   refloor=problem.refloor)
    return Search(final, start, skipped, weak, ambiguous, floor)


def _check_names(effects):
    names = list(EFFECTS) if effects is None else [ALIASES.get(n, n) for n in effects]
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effects {unknown}; the library has {list(EFFECTS)}")
    return names


def _stand_ins(current, selected, unexplained, scale):
    """The report's entry of each selected effect, each marked a stand-in where the verdict is
    unexplained or its parameters are implausible (:attr:`Effect.implausible`)."""
    chosen = []
    for name in selected:
        p = describe_params(name, current.effects[name][0])
        why = EFFECTS[name].implausible(p, scale)
        reason = (f"physically implausible parameters ({why})" if why else
                  "the verdict is unexplained: the effect stands in for structure the library "
                  "does not describe" if unexplained else None)
        chosen.append({"name": name, "params": p, "interpretation": EFFECTS[name].interpret(p),
                       "stand_in_for_unexplained": reason is not None,
                       "stand_in_reason": reason})
    return chosen


def _dark_in_well_or_not(base, theta, start, base_fit, data, noise_floor, n_pix, n_light,
                         dark_desc):
    """The leakage base with the dark signal collected outside the photodiode (added after the
    leakage, :class:`~hsiffc.diagnose.bases.LeakageBase` ``dark_leaks=False``), fitted beside
    the one whose dark current leaks with the light's charge; kept where it passes the
    selection rule's held-out test against it (:func:`~hsiffc.diagnose.select.improves`).
    Both have the same parameters, so only the held-out error tells them apart.

    Returns the base, its start parameters, its state after the base step, its fit and the
    dark model's description (``leaks`` and the comparison's figures added)."""
    y, t, r, valid, w = data.y, data.t, data.r, data.valid, data.w
    alt = LeakageBase(True, dark_leaks=False)
    alt.full_scale = base.full_scale
    theta_alt = alt.start(y, t, r, valid, w)
    start_alt = refit_base(y, data, State(alt, theta_alt))
    alt_fit = evaluate(start_alt, [], data, n_pix, n_light)
    gain, se = paired(base_fit, alt_fit, data.valid_ho)
    z = gain / max(se, 1e-300)
    # the same parameters: the fit half's BIC decides where the held-out error does not (a
    # dark signal's shot noise can make the held-out test weak), as long as the held-out
    # error is as good
    by_bic = (base_fit.bic - alt_fit.bic > DARK_BIC_MARGIN
              and equally_good(base_fit, alt_fit, data.valid_ho, noise_floor))
    if improves(base_fit, alt_fit, gain, se, noise_floor) or by_bic:
        return alt, theta_alt, start_alt, alt_fit, {
            **dark_desc, "leaks": False,
            "model": ("dark level + dark signal per pixel collected outside the photodiode "
                      "(additive: it does not leak; measured from the dark frames)"),
            "reason": dark_desc["reason"].replace("added to the light rate and ", "") + (
                f"; a dark signal that does not leak (collected outside the photodiode: a "
                f"storage node, amplifier glow) fits better than one that leaks with the "
                f"light's charge (held-out error lower by {z:.1f} standard errors, BIC by "
                f"{base_fit.bic - alt_fit.bic:.0f})")}
    return base, theta, start, base_fit, {
        **dark_desc, "leaks": True,
        "reason": dark_desc["reason"] + (
            f"; a dark signal that does not leak (collected outside the photodiode) was "
            f"tried and does not fit better (held-out error lower by {z:.1f} standard errors, "
            f"BIC by {base_fit.bic - alt_fit.bic:.0f})")}


@dataclass
class Samples:
    """The samples diagnose fits (:func:`prepare`): the sweep (its sweep steps alone for an
    EMVA 1288 set), the pixel subset and where its pixels are, the dict of
    :func:`~hsiffc.diagnose.design.samples` (step means ``y`` and ``y_ho`` of the fit and
    held-out halves in DN, exposures ``t`` in ms, relative light rates ``r``, ...), the
    design, the level the data reach (``fs``, DN: the ADC's full scale, or the clip where the
    frames clip first), each pixel's dark level (``dark0``, DN), the frame variance as a
    function of the signal (DN^2; None without frame pairs), the valid samples of each half and
    the fit weights (1/DN^2)."""

    sweep: Sweep
    sub: Sweep
    rows: np.ndarray
    cols: np.ndarray
    band: np.ndarray
    smp: dict
    des: ds.Design
    fs: float
    dark0: np.ndarray
    var_fn: object
    valid: np.ndarray
    valid_ho: np.ndarray
    w: np.ndarray

    @property
    def light(self) -> np.ndarray:
        """Which samples are light steps, (S,) bool."""
        return self.smp["kind"] == "light"


def prepare(sweep: Sweep, max_pixels: int, seed: int, full_well_dn=None) -> Samples:
    """The samples of ``sweep`` that :func:`diagnose` fits: a pixel subset, step means of the
    fit and held-out halves, and every sample left out that is clipped, unusable or within 4
    frame SDs of the level the data reach.

    Parameters
    ----------
    sweep : Sweep
    max_pixels, seed : int
        As :func:`diagnose`.
    full_well_dn : float, optional, DN
        Step means at or above it are not used.

    Returns
    -------
    Samples

    Raises
    ------
    DataFormatError
        Fewer than ``MIN_LIGHT_STEPS`` usable light steps, or no pixel with enough valid
        samples.
    """
    if "sweep_steps" in sweep.meta:  # EMVA 1288: the sweep, not the spatial set
        sweep = sweep.select(np.isin(sweep.step, sweep.meta["sweep_steps"]))
    sub, rows, cols, band = ds.subset(sweep, max_pixels, seed)
    smp = ds.samples(sub, full_well_dn)
    des = ds.describe(smp)
    if des.n_light_steps < MIN_LIGHT_STEPS:
        _refuse(f"{des.n_light_steps} usable light steps (exposure > 0, known light rate); "
                f"diagnose needs at least {MIN_LIGHT_STEPS} to fit a response and test it on "
                "held-out data. Record more light steps", sweep)
    y, y_ho, kind = smp["y"], smp["y_ho"], smp["kind"]
    fs = float(sweep.full_scale_dn)
    if smp["plateau"] is not None:  # a full well below full scale, read noise after it
        fs = smp["clip_dn"]
        pl = smp["plateau"]
        des.notes.append(f"the response stops at {fs:.6g} DN, below the ADC's full scale "
                         f"({sweep.full_scale_dn} DN), with the read noise alone after it "
                         f"({pl['plateau_dn2']:.3g} DN^2 a frame against {pl['read_dn2']:.3g} "
                         f"read and {pl['shot_dn2']:.3g} shot): a full well that fills first; "
                         "steps with a frame there are left out and it acts as full scale")
    elif smp["clip_dn"] is not None:  # the data clip below the ADC's full scale
        fs = smp["clip_dn"]
        des.notes.append(f"the frames clip at {fs:g} DN, below the ADC's full scale "
                         f"({sweep.full_scale_dn} DN): a full well that fills first; steps with "
                         "a frame there are left out and the clip acts as full scale")
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
    n_light = int((valid & (kind == "light")[None, :]).sum(axis=1).max(initial=0))
    if n_light < MIN_LIGHT_STEPS:  # darks alone would be fitted as a flat "response"
        _refuse(f"no pixel has {MIN_LIGHT_STEPS} light samples below full scale (at most "
                f"{n_light}): the light steps are clipped or within the noise of full scale "
                f"({fs:g} DN); record the sweep with less light or shorter exposures", sweep)
    w = np.where(valid, smp["n_fit"][None, :] / var_frame, 0.0)
    return Samples(sweep, sub, rows, cols, band, smp, des, fs, dark0, var_fn, valid, valid_ho, w)


def _fit_base(s: Samples):
    """The base model (leakage per pixel where the pixels have enough fit samples, else a
    linear response; the dark model the darks show) fitted on ``s``. The samples the model
    itself puts within 5 SDs of full scale are left out of ``s`` first (selected by the
    prediction, independent of the held-out noise). Returns the base, its parameters, whether
    it has a dark current and the dark model's description."""
    y, t, r = s.smp["y"], s.smp["t"], s.smp["r"]
    use_dc, dark_desc = ds.dark_model(y, t, r, s.valid, s.w, s.des)
    n_fit_samples = float(np.median(s.valid.sum(axis=1)))
    base = (LeakageBase(use_dc) if n_fit_samples >= LeakageBase.n_core + use_dc + 3
            else LinearBase(use_dc))
    base.full_scale = s.fs
    if base.name == "linear":
        s.des.notes.append(f"{n_fit_samples:.0f} fit samples per pixel (median): too few for "
                           "the leakage model (4 parameters), the base is a linear response")
    theta = base.start(y, t, r, s.valid, s.w)
    pred = base.predict(theta, t, r)
    sd_pred = np.sqrt(s.var_fn(pred - s.dark0[:, None])) if s.var_fn is not None else 0.0
    keep = pred < s.fs - 5.0 * sd_pred
    s.valid, s.valid_ho = s.valid & keep, s.valid_ho & keep
    s.w = np.where(s.valid, s.w, 0.0)
    theta = base.fit(y, t, r, s.valid, s.w, theta, max_iter=40)
    return base, theta, use_dc, dark_desc


def _fit_data(s: Samples) -> Data:
    """What every fit works on (:class:`~hsiffc.diagnose.fitdata.Data`): the samples of ``s``
    with each step's place in acquisition order (from -1 to 1), the step before it and the
    place of its held-out frames."""
    smp = s.smp
    order_rank = np.argsort(np.argsort(smp["step"]))
    order = (order_rank / max(len(order_rank) - 1, 1)) * 2 - 1
    by_order = np.argsort(smp["step"])
    prev_index = np.full(len(order), -1)
    prev_index[by_order[1:]] = by_order[:-1]
    # the held-out frames of a step, ``frame_gap`` frames later: on the scale of ``order``
    # (one step 2 / (S - 1)), a frame is that over the step's frames
    per_step = np.asarray(smp["n_fit"], float) + np.asarray(smp["n_ho"], float)
    order_ho = order + (smp["frame_gap"] * 2.0 / max(len(order) - 1, 1)
                        / np.maximum(per_step, 1.0))
    return Data(y=smp["y"], y_ho=smp["y_ho"], t=smp["t"], r=smp["r"], valid=s.valid,
                valid_ho=s.valid_ho, w=s.w, order=order, prev_index=prev_index, light=s.light,
                full_scale=s.fs, frame_gap=smp["frame_gap"],
                n_fit=np.asarray(smp["n_fit"], float), order_ho=order_ho)


def _measure_noise(s: Samples, data: Data, base, theta):
    """The noise model (:class:`NoiseModel`): from the frame differences, tested against the
    temporal-noise model first (a within-step change noted in the design), or, without frame
    pairs, from the spread of the held-out residual across the pixels, with the base refitted
    on the weights it gives (``s.w`` and ``data.w`` updated). Returns the model and the base's
    parameters."""
    quantum = 1.0 if np.issubdtype(s.sub.data.dtype, np.integer) else 0.0  # DN
    smp, valid, valid_ho = s.smp, s.valid, s.valid_ho
    noise = NoiseModel(smp, valid & valid_ho, quantum, smp["y"].shape)
    if noise.pairs:
        noise.from_pairs()
        data.frames_differ = bool(noise.test["within_step"])
        if noise.test["within_step"]:
            s.des.notes.append(
                f"the frame differences hold more than the noise model allows (p = "
                f"{noise.test['p_value']:.2g}: RMS {noise.test['raw_dn']:.3g} DN a frame "
                f"against {noise.test['clean_dn']:.3g} DN once what follows the signal across "
                "the pixels is taken out): the frames of a step are not exchangeable, the noise "
                "is measured on the cleared differences and effects that change from frame to "
                "frame are candidates")
        return noise, theta
    t, r = smp["t"], smp["r"]
    m = base.predict(theta, t, r)
    pv = _prediction_variance(base, theta, data)
    var_fn = ds.noise_from_spread(np.where(valid_ho, smp["y_ho"] - m, 0.0), valid_ho,
                                  m - base.dark(theta), pv, smp["n_ho"])
    var1 = var_fn(m - base.dark(theta))
    data.w = s.w = np.where(valid, smp["n_fit"][None, :] / var1, 0.0)
    theta = base.fit(smp["y"], t, r, valid, s.w, theta, max_iter=40)
    noise.from_spread(var1)
    return noise, theta


def _search_bases(problem: Problem, base, theta, base_fit, noise_floor, use_dc):
    """The search from the base (:func:`search`), and for a leakage base from the same model
    with one leakage shape for the sensor too: that one first where the per-pixel model
    predicts the held-out data measurably worse (it follows the noise of the fit half: a base
    worse than a simpler one would let any effect that makes up part of the difference look
    like a find), each kept where it predicts measurably better; else the selected model is
    refitted with one shape and kept where it is as good with fewer parameters.

    Returns the search kept (:class:`Search`), the per-pixel model with its start where one
    shape for the sensor replaced it (else None) and the shared base's fit (None for a linear
    base)."""
    data, n_pix, n_light = problem.data, problem.n_pix, problem.n_light
    valid_ho = data.valid_ho
    starts = [(base_fit, noise_floor)]
    sh_state = sh_fit = None
    if base.name == "leakage":
        shared = SharedLeakageBase(use_dc, dark_leaks=base.dark_leaks)
        shared.full_scale = data.full_scale
        sh_state = State(shared, shared.start(data.y, data.t, data.r, data.valid, data.w,
                                               per_pixel=theta))
        sh_fit = evaluate(refit_base(data.y, data, sh_state), [], data, n_pix, n_light)
        if not equally_good(sh_fit, base_fit, valid_ho, noise_floor):
            floor = problem.noise.floor(_prediction_variance(shared, sh_state.theta, data),
                                        valid_ho)
            starts.insert(0, (sh_fit, floor))
    result = search(problem, *starts[0])
    per_pixel = None
    if len(starts) > 1:
        # the search from the per-pixel model too, whole model against whole model
        other = search(problem, *starts[1])
        if not equally_good(other.final, result.final, valid_ho, other.floor):
            result = other
        else:
            per_pixel = (other.final, other.start)
    final = result.final
    if final.state.base.name == "leakage" and "pixel_nonlinearity" not in final.names:
        # not tried next to a per-pixel nonlinearity, which says that the bend differs from
        # pixel to pixel
        sh_final = (refit(final.names, data, sh_state, n_pix, n_light) if final.names else sh_fit)
        if sh_final.bic < final.bic and equally_good(final, sh_final, valid_ho, result.floor):
            per_pixel = (final, result.start)
            result = replace(result, final=sh_final, start=sh_fit)
    return result, per_pixel, sh_fit


def _leakage_or_not(problem: Problem, result: Search, use_dc):
    """Is the bending of the response leakage at all? The selected model against a linear base
    with its own candidates (:func:`~hsiffc.diagnose.select.leakage_check`). Returns the search
    with the model kept (its skipped, weak and ambiguous effects those of the linear base where
    that wins), the leakage verdict and the linear base's fit."""
    data, n_pix, n_light = problem.data, problem.n_pix, problem.n_light
    lin = LinearBase(use_dc)
    lin_state = State(lin, lin.start(data.y, data.t, data.r, data.valid, data.w))
    # the same linearised base step as the leakage bases and every trial fit get
    lin_fit = evaluate(refit_base(data.y, data, lin_state), [], data, n_pix, n_light)
    skipped_lin, testable_lin, weak_lin = _identifiable(problem.names, lin, lin_state.theta,
                                                        data, problem.des, problem.dark_desc)
    ambiguous_lin: list = []
    final, leakage = leakage_check(result.final, lin_fit, testable_lin, data, result.floor,
                                   n_pix, n_light, problem.des, problem.candidates,
                                   ambiguous_lin, refloor=problem.refloor)
    result = replace(result, final=final)
    if final.state.base.name == "linear":
        result = replace(result, skipped=skipped_lin, weak=weak_lin, ambiguous=ambiguous_lin)
    if leakage["verdict"] == "cannot tell":
        result.ambiguous.append({"effects": leakage["models"], "reason": leakage["reason"]})
    return result, leakage, lin_fit


def _figures(mse, floor):
    """RMS, noise floor and systematic RMS (DN) of a held-out mean squared error."""
    rms = float(np.sqrt(mse))
    return {"rms_dn": rms, "noise_floor_dn": floor,
            "systematic_rms_dn": float(np.sqrt(max(rms ** 2 - floor ** 2, 0.0)))}


@dataclass
class Verdict:
    """What :func:`_verdict` decides: the report entry of each selected effect (stand-ins
    marked), whether the sweep is unexplained and why, and the figures after (DN)."""

    chosen: list
    unexplained: bool
    reason: str
    after: dict


def _verdict(final: Fitted, check: ResidualCheck, data: Data, scale: dict, lin_fit, sh_fit,
             leakage: dict) -> Verdict:
    """Unexplained or not: systematic error left above ``UNEXPLAINED_OF_FLOOR`` of the noise
    floor (whatever the binned structure tests say: the figure printed and the sentence
    agree), structure in the residual, an effect with implausible parameters, one that stands
    in for an offset common to the pixels of a frame, such an offset left, or the leakage base
    taking one up (``leakage`` gets ``stand_in_for_unexplained`` then). Every selected effect
    is a stand-in where the verdict is unexplained."""
    current, selected = final.state, final.names
    floor_after = check.floor(data.valid_ho)
    after = _figures(final.mse, floor_after)
    too_big = after["systematic_rms_dn"] > UNEXPLAINED_OF_FLOOR * floor_after
    structured = check.structured
    chosen = _stand_ins(current, selected, bool(structured or too_big), scale)
    implausible = [e["name"] for e in chosen if e["stand_in_for_unexplained"]]
    # an effect that stands in for an offset common to the pixels of a frame
    offsets = {e["name"]: p for e in chosen if not e["stand_in_for_unexplained"]
               and (p := offset_stand_in(final, e["name"], data))}
    if not offsets:  # effects whose part that differs between a frame's pixels is not there
        flat = frame_constant_stand_in(
            final, [e["name"] for e in chosen if not e["stand_in_for_unexplained"]], data)
        offsets = dict.fromkeys(flat["effects"], flat) if flat else {}
    left = offset_left(final, data, floor_after)
    # the leakage base taking up an offset common to the pixels of a frame
    leak_in = (leakage_stand_in(final, lin_fit, sh_fit, data, floor_after) if lin_fit is not None
               else None)
    if leak_in:
        leakage["stand_in_for_unexplained"] = True
        leakage["stand_in_reason"] = leak_in["reason"]
    unexplained = bool(structured or too_big or implausible or offsets or left or leak_in)
    if unexplained:  # every selected effect is a stand-in then
        chosen = _stand_ins(current, selected, True, scale)
        for e in chosen:
            if e["name"] in offsets:
                e["stand_in_reason"] = offsets[e["name"]]["reason"]
    reason = _unexplained_reason(structured, too_big, after, floor_after)
    if not (structured or too_big):  # the reasons the figures do not show, first
        if offsets:
            reason = (f"{', '.join(offsets)} stand{'s' if len(offsets) == 1 else ''} in for an "
                      "offset common to the pixels of a frame: the library does not describe "
                      "what the data show; " + reason)
        if left:
            reason = left["reason"] + "; " + reason
        if leak_in:
            reason = leak_in["reason"] + "; " + reason
        if implausible:
            reason = (f"{', '.join(implausible)} fit{'s' if len(implausible) == 1 else ''} "
                      "with physically implausible parameters: the library does not describe "
                      "what the data show; " + reason)
    return Verdict(chosen, unexplained, reason, after)


def diagnose(sweep: Sweep, *, max_pixels: int = 2048, seed: int = 0, effects=None,
             full_well_dn: float | None = None) -> Diagnosis:
    """Diagnose where the base model misses a sweep; see the module docstring.

    Parameters
    ----------
    sweep : Sweep
        Any sweep design: exposure sweeps, light sweeps at a fixed exposure, mixed; with or
        without dark frames; two or more frames per step (frame pairs held out) or one
        (alternate steps held out).
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
    Diagnosis
        The fields of ``hsiffc diagnose --json`` (design, base model, noise floor in DN,
        RMS before and after in DN, selected effects with their sizes, which are stand-ins,
        what stays unexplained), read as a dict too, plus the arrays the report plots
        (``"_arrays"``). Run time: seconds (measured by ``benchmarks/bench_diagnose.py``).

    Raises
    ------
    ValueError
        Unknown effect names (the message lists the library).
    DataFormatError
        A design nothing can be learned from (fewer than 4 usable light steps, no valid sample).
    """
    t0 = time.perf_counter()
    names = _check_names(effects)
    s = prepare(sweep, max_pixels, seed, full_well_dn)
    sweep, smp, des, y = s.sweep, s.smp, s.des, s.smp["y"]
    base, theta, use_dc, dark_desc = _fit_base(s)
    data = _fit_data(s)
    noise, theta = _measure_noise(s, data, base, theta)
    valid, valid_ho = s.valid, s.valid_ho
    # the base alone gets the linearised (Gauss-Newton) step every candidate's trial fit makes,
    # so a base fit short of its optimum does not credit that step to whichever effect is tried
    start = refit_base(y, data, State(base, theta))
    noise_floor = noise.floor(_prediction_variance(base, theta, data), valid_ho)
    if not np.isfinite(noise_floor) or noise_floor <= 0:
        _refuse("the temporal noise cannot be measured on this sweep (no valid held-out "
                "sample with a finite noise); record two frames per step", sweep)
    n_pix, n_light = y.shape[0], int(s.light.sum())
    base_fit = evaluate(start, [], data, n_pix, n_light)
    if use_dc and base.name == "leakage":
        # the dark signal collected in the photodiode (leaking with the light's charge) or
        # outside it (a storage node, amplifier glow): the data choose
        base, theta, start, base_fit, dark_desc = _dark_in_well_or_not(
            base, theta, start, base_fit, data, noise_floor, n_pix, n_light, dark_desc)
        noise_floor = noise.floor(_prediction_variance(base, theta, data), valid_ho)
    problem = Problem(data, des, dark_desc, names, n_pix, n_light, noise)
    result, per_pixel, sh_fit = _search_bases(problem, base, theta, base_fit, noise_floor, use_dc)
    leakage, lin_fit = {"verdict": "not tested", "reason": "the base model is linear"}, None
    if base.name in ("leakage", "shared leakage"):
        result, leakage, lin_fit = _leakage_or_not(problem, result, use_dc)
    final, base_fit, noise_floor = result.final, result.start, result.floor
    check = residual_check(problem, final, s.rows, s.cols, s.band, noise_floor, seed)
    if (check.structured or check.too_big(final)) and per_pixel is not None \
            and final.state.base.name == "shared leakage":
        # one leakage shape is as good on the held-out error, but leaves a pattern over the
        # pixels, or a systematic error its smaller fit noise no longer hides (a leakage
        # amplitude that spreads over the pixels): the per-pixel model is kept where it
        # leaves neither
        alt = residual_check(problem, per_pixel[0], s.rows, s.cols, s.band, noise_floor, seed)
        if not (alt.structured or alt.too_big(per_pixel[0])):
            final, base_fit = per_pixel
            check = alt
            leakage["shape"] = (
                "per pixel: one leakage shape for the sensor fits the held-out error as well "
                "with fewer parameters, but leaves a pattern over the pixels or a systematic "
                "error in the residual that the per-pixel model does not")
    current, selected, t = final.state, final.names, smp["t"]
    findings_before, _ = structure(base_fit.res, valid_ho, check.groups, noise_floor,
                                   null=check.null, sd=check.sd_sample)
    scale = {"full_scale_dn": s.fs, "max_exposure_ms": float(t[smp["usable"]].max()),
             "min_exposure_ms": float(t[smp["usable"]].min())}
    v = _verdict(final, check, data, scale, lin_fit, sh_fit, leakage)
    n_total = int(smp["usable"].sum() * n_pix)
    return Diagnosis(
        dataset=str(sweep.source or "in-memory sweep"),
        base_model=current.base.describe + (
            ", constant dark level" if not use_dc else "; dark current from the dark frames"
            if current.base.dark_leaks else "; dark signal outside the photodiode (additive, "
            "not leaking) from the dark frames"),
        design=des.as_dict(), leakage=leakage,
        dark_model=ds.describe_dark_current(current.base.dc(current.theta), dark_desc),
        n_pixels=int(n_pix), n_pixels_sensor=int(np.prod(sweep.frame_shape)),
        n_samples=int(valid_ho.sum()), n_invalid_samples=int(n_total - (valid | valid_ho).sum()),
        noise_floor_dn=noise_floor, noise_source=noise.source, noise_test=noise.test,
        before=_figures(base_fit.mse, noise_floor), after=v.after,
        selected_effects=list(selected),
        findings=[e["name"] for e in v.chosen if not e["stand_in_for_unexplained"]],
        stand_ins=[e["name"] for e in v.chosen if e["stand_in_for_unexplained"]],
        effects=v.chosen, skipped=_with_weak(result.skipped, result.weak, selected),
        candidates=problem.candidates, unexplained=v.unexplained,
        unexplained_reason=v.reason, ambiguous=result.ambiguous,
        residual_structure_after=check.findings, residual_structure_before=findings_before,
        held_out=smp["held_out"], selection_rule=RULE, runtime_s=time.perf_counter() - t0,
        arrays=ResidualArrays(res_before=base_fit.res, res_after=final.res, valid=valid_ho, t=t,
                              signal=check.ctx.signal, light=s.light, order=data.order,
                              rows=s.rows, cols=s.cols, band=s.band, step=smp["step"]))

@dataclass
class ResidualCheck:
    """What :func:`residual_check` found: the context of the model, the groupings, the noise
    of each held-out sample (variance and SD, DN), the null of each grouping, the findings and
    whether any is significant."""

    ctx: object
    groups: dict
    valid_ho: np.ndarray
    var_sample: np.ndarray
    sd_sample: np.ndarray
    null: dict
    findings: list
    structured: bool

    def floor(self, valid_ho) -> float:
        """RMS noise (DN) of the held-out samples of the model checked."""
        return float(np.sqrt(np.mean(self.var_sample[valid_ho])))

    def too_big(self, fitted) -> bool:
        """The systematic error ``fitted`` leaves is above ``UNEXPLAINED_OF_FLOOR`` of this
        floor."""
        floor = self.floor(self.valid_ho)
        return fitted.mse - floor ** 2 > (UNEXPLAINED_OF_FLOOR * floor) ** 2


def residual_check(problem: Problem, fitted: Fitted, rows, cols, band, noise_floor: float,
                   seed: int) -> ResidualCheck:
    """Structure left in the held-out residual of a fitted model, against what the model
    itself leaves: simulate it with the measured noise, refit, and measure the same residual
    structure (parametric bootstrap, 2 draws).

    Parameters
    ----------
    problem : Problem
        The samples and the noise model.
    fitted : Fitted
        The model.
    rows, cols, band : ndarray of int, (P,)
        Where the pixels are.
    noise_floor : float, DN
        The noise floor.
    seed : int
        Seed of the simulation.

    Returns
    -------
    ResidualCheck
    """
    data, noise = problem.data, problem.noise
    valid_ho, smp = data.valid_ho, noise.smp
    cur = fitted.state
    ctx = context(cur.base, cur.theta, data)[2]
    groups = groupings(valid_ho, ctx.signal, data.light, rows, cols, band)
    # the model's own fit noise (its base may be less well determined next to an effect)
    pv = _prediction_variance(cur.base, cur.theta, data, cur)
    vs = noise.var_step_of(cur)
    var_sample = noise.noise2_of(cur, vs) + pv
    sd_sample = np.sqrt(var_sample)  # noise of each held-out sample, DN
    sigma_step = np.sqrt(ds.noise_before_rounding(vs, noise.sim_quantum))
    rng = np.random.default_rng(seed + 1)
    null = {}
    for _ in range(2):
        y_sim = noise.simulate_frames(cur.prediction, smp["n_fit"], rng, sigma_step)
        y_sim_ho = noise.simulate_frames(cur.prediction + cur.ho_extra, smp["n_ho"], rng,
                                         sigma_step)
        if not noise.pairs:
            y_sim_ho = y_sim
        sim_data = Data(**{**data.__dict__, "y": y_sim, "y_ho": y_sim_ho})
        sim = (fitpredict(fitted.names, sim_data, cur, quick=True) if fitted.names
               else refit_base(y_sim, sim_data, cur))
        sim_res = np.where(valid_ho, y_sim_ho - sim.prediction - sim.ho_extra, 0.0)
        for f in structure(sim_res, valid_ho, groups, noise_floor, sd=sd_sample)[0]:
            null[f["grouping"]] = max(null.get(f["grouping"], 0.0), f["null_statistic"])
    findings, structured = structure(fitted.res, valid_ho, groups, noise_floor, null=null,
                                     sd=sd_sample)
    return ResidualCheck(ctx, groups, valid_ho, var_sample, sd_sample, null, findings,
                         structured)
