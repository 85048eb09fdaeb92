"""How often does ``diagnose`` name the right effect on sweeps it was never tuned on?

A seeded generator of small simulated sweeps (:func:`case_spec`, :func:`build_case`), each with
random sensor parameters (8-16 bit, read noise, PRNU, dark level, linear or leaky pixels, dark
current when there are dark frames; the full well lies just above the ADC's full scale, so that
bright samples clip at full scale, which diagnose leaves out), a random design (exposure sweeps
at 1-4 light rates, light sweeps at one exposure, mixed designs; with or without dark frames)
and one of:

- nothing (a clean control);
- one library effect at 2x, 5x, 10x or 100x its detection limit;
- two library effects at 10x each;
- an effect outside the library: ``column_gain_jump`` (half the column groups change gain
  halfway through the acquisition), ``slow_lag`` (image lag decaying over several steps, time
  constant 4 steps, where the library's lag lasts one step) or ``adc_ripple``.

**Detection limit (DL).** An effect's size is given in units of its detection limit on *that*
sweep: the size at which the part of the effect the true base model cannot absorb (the
noise-free effect projected off the Jacobian of the true per-pixel model, over the light
samples below 90 % of full scale) has an RMS of ``DL_OF_NOISE`` (0.1) times the temporal noise
of one frame. Sizes whose effect would exceed ``MAX_OF_FULL_SCALE`` of full scale are not
drawn (a smaller multiple, or another effect, is drawn instead), and effects the design cannot
identify at all (a timing offset or a dark current on a sweep at one exposure) are not drawn.

The seeds split into halves: even seeds are the development half (tune on these), odd seeds
the evaluation half (only scored). :func:`run` diagnoses the cases, :func:`summarise` scores
them (named right, false alarms, out-of-library reported as unexplained, a confusion matrix)
and :func:`markdown` renders the tables of the diagnose docs page::

    python3 -m hsiffc.diagnose.evaluation --half eval --cases 480 --json eval.json
    python3 -m hsiffc.diagnose.evaluation --half eval --cases 480 --page docs/diagnose.md

The second form also diagnoses the sweeps of ``../shared/data`` (one row each) and writes the
tables between ``<!-- BEGIN evaluation -->`` and ``<!-- END evaluation -->`` of the page.

More seed streams hold what the first lacks: the failure classes of issue 53 (from
``CLASS_SEED0``, ``--classes N``), a linear sensor with an exposure offset and a soft well
compression (from ``CLASS2_SEED0``, ``--classes2 N``; :func:`ccd_sweep`) and the same sensor
whose well fills below the ADC's range (from ``CLASS3_SEED0``, ``--classes3 N``), each written
from its own physics, each scored on its own.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

DL_OF_NOISE = 0.1
MAX_OF_FULL_SCALE = 0.15
MULTIPLES = (2, 5, 10, 100)
SHAPE = (32, 64)
MAX_PIXELS = 1024
OUTSIDE_EFFECTS = ("column_gain_jump", "slow_lag", "adc_ripple")
#: the sweeps of ``../shared/data``, each a row of its own, with what was put in (their
#: README): nobody here tuned diagnose on them
SHARED_PUT_IN = {
    "emva1288-cmos8-roi": "a real CMOS sensor (unknown)",
    "emva1288-refsim-linear12-exposure": "linear, no leakage (EMVA 1288 reference simulator)",
    "emva1288-refsim-linear10-light": "linear, no leakage (EMVA 1288 reference simulator)",
    "indep-ccd12-offset": "exposure offset 0.03 ms, a soft well compression (2 % at 3500 DN), "
                          "no leakage (independent generator)",
    "indep-cmos10-light-nonlinear": "readout compression common to every pixel (cubic, 3 % at "
                                    "full scale), a dark signal that does not leak (one "
                                    "exposure), no leakage (independent generator)",
}
SHARED_SETS = tuple(SHARED_PUT_IN)
#: shared sets that are linear: diagnose must keep a linear base and select nothing
LINEAR_SETS = ("emva1288-refsim-linear12-exposure", "emva1288-refsim-linear10-light")
#: shared sets made without leakage: diagnose should find it not needed
NO_LEAKAGE_SETS = LINEAR_SETS + ("indep-ccd12-offset", "indep-cmos10-light-nonlinear")
GOALS = {"named_right_5x": 0.90, "false_alarm_clean": 0.05, "outside_unexplained": 0.90}
#: the library the first generator draws its effects from (the effects added later are drawn
#: by the failure classes; a longer list would change every seed's draws)
FIRST_LIBRARY = ("dark_current", "exposure_offset", "readout_nonlinearity",
                 "pixel_nonlinearity", "offset_drift", "illumination_error", "image_lag",
                 "frame_light_change")


def half_of(seed: int) -> str:
    """``"dev"`` for even seeds, ``"eval"`` for odd ones.

    Parameters
    ----------
    seed : int

    Returns
    -------
    str

    Examples
    --------
    >>> half_of(4), half_of(7)
    ('dev', 'eval')
    """
    return "dev" if seed % 2 == 0 else "eval"


def seeds(half: str, n_cases: int, n_class_cases: int = 0, n_ccd_cases: int = 0,
          n_well_cases: int = 0) -> list[int]:
    """The seeds of one half among the first ``n_cases`` seeds, among the first
    ``n_class_cases`` seeds of the failure classes (``CLASS_SEED0`` on), among the first
    ``n_ccd_cases`` of the linear-sensor stream (``CLASS2_SEED0`` on) and among the first
    ``n_well_cases`` of the full-well stream (``CLASS3_SEED0`` on).

    Parameters
    ----------
    half : {"dev", "eval", "all"}
    n_cases : int
        Seeds 0 .. n_cases - 1.
    n_class_cases : int
        Seeds CLASS_SEED0 .. CLASS_SEED0 + n_class_cases - 1.
    n_ccd_cases : int
        Seeds CLASS2_SEED0 .. CLASS2_SEED0 + n_ccd_cases - 1.
    n_well_cases : int
        Seeds CLASS3_SEED0 .. CLASS3_SEED0 + n_well_cases - 1.

    Returns
    -------
    list of int
    """
    if half not in ("dev", "eval", "all"):
        raise ValueError(f"half must be 'dev', 'eval' or 'all', got {half!r}")
    every = (list(range(n_cases)) + list(range(CLASS_SEED0, CLASS_SEED0 + n_class_cases))
             + list(range(CLASS2_SEED0, CLASS2_SEED0 + n_ccd_cases))
             + list(range(CLASS3_SEED0, CLASS3_SEED0 + n_well_cases)))
    return [s for s in every if half == "all" or half_of(s) == half]


def _sensor(rng, bit_depths):
    """Bit depth, full scale (DN), full well (e-), dark level (DN) and conversion gain (DN/e-)
    of a random sensor; the ADC clips before the full well."""
    bits = int(rng.choice(bit_depths))
    fs = 2 ** bits - 1
    full_well = float(np.exp(rng.uniform(np.log(4e3), np.log(4e4))))
    dark = float(fs * rng.uniform(0.01, 0.06) + 2.0)
    return bits, fs, full_well, dark, 1.05 * (fs - dark) / full_well


def case_spec(seed: int) -> dict:
    """The random choices of case ``seed`` (sensor, design, what is put in); JSON-safe.

    Parameters
    ----------
    seed : int

    Returns
    -------
    dict
    """
    if seed >= CLASS3_SEED0:
        return well_case_spec(seed)
    if seed >= CLASS2_SEED0:
        return ccd_case_spec(seed)
    if seed >= CLASS_SEED0:
        return class_case_spec(seed)
    rng = np.random.default_rng(np.random.SeedSequence([38, seed]))
    bits, fs, full_well, dark, gain = _sensor(rng, [8, 10, 12, 14, 16])
    design = str(rng.choice(["exposure", "light", "mixed"]))
    darks = bool(rng.random() < 0.6)
    leaky = bool(rng.random() < 0.5)
    spec = {
        "seed": seed, "half": half_of(seed), "bit_depth": bits, "design": design,
        "darks": darks, "leaky": leaky, "n_steps": int(rng.integers(16, 37)),
        "n_rates": int(rng.integers(1, 5)) if design == "exposure" else 0,
        "shuffled": bool(rng.random() < 0.4),
        "t_max_ms": float(rng.uniform(20.0, 200.0)),
        "fill": float(rng.uniform(0.8, 1.25) if leaky else rng.uniform(0.75, 1.1)),
        "params": {
            "bit_depth": bits, "full_well_e": full_well, "conversion_gain_dn_per_e": gain,
            "read_noise_dn": float(np.exp(rng.uniform(np.log(2), np.log(25))) * gain),
            "dark_level_dn": dark, "dsnu_dn": float(dark * rng.uniform(0.02, 0.1)),
            "prnu": float(rng.uniform(0.002, 0.02)),
            "dark_current_dn_per_ms": (float(fs * np.exp(rng.uniform(np.log(1e-6),
                                                                      np.log(2e-4))))
                                       if darks and rng.random() < 0.3 else 0.0),
            "dark_current_spread": float(rng.uniform(0.2, 1.0)),
            "leak_b_per_dn": float(rng.uniform(6.0, 14.0) / fs),
            "leak_ref_dn": float(0.8 * fs),
            "leak_a_spread": 0.2,
        },
        "leak_of_rate": float(rng.uniform(0.3, 1.0)),
    }
    u = rng.random()
    kind = "clean" if u < 0.2 else "single" if u < 0.7 else "pair" if u < 0.8 else "outside"
    spec["kind"] = kind
    spec["effect_seed"] = int(rng.integers(2 ** 31))
    spec["multiple"] = int(rng.choice(MULTIPLES))
    spec["candidates"] = [str(x) for x in rng.permutation(list(FIRST_LIBRARY))]
    spec["outside"] = str(rng.choice(OUTSIDE_EFFECTS))
    return spec


def _library():
    from .effects import EFFECTS
    return list(EFFECTS)


def _design_steps(spec, rng):
    n, t_max = spec["n_steps"], spec["t_max_ms"]
    if spec["design"] == "light":
        t = np.full(n, t_max)
        levels = np.linspace(0.02, 1.0, n)
        order = rng.permutation(n) if spec["shuffled"] else np.arange(n)
        return t[order], levels[order]
    if spec["design"] == "mixed":
        t = rng.permutation(np.geomspace(t_max / 80.0, t_max, n))
        return t, np.exp(rng.uniform(np.log(0.15), 0.0, n))
    rates = np.geomspace(1.0, rng.uniform(0.2, 0.5), spec["n_rates"]) if spec["n_rates"] > 1 \
        else np.ones(1)
    per = int(np.ceil(n / rates.size))
    t = np.concatenate([np.geomspace(t_max / 60.0, t_max, per) for _ in rates])
    levels = np.repeat(rates, per)
    order = rng.permutation(t.size) if spec["shuffled"] else np.arange(t.size)
    return t[order], levels[order]


def clean_sweep(spec: dict):
    """The simulated sweep of a case without anything put in (``meta["truth"]`` kept).

    Parameters
    ----------
    spec : dict
        From :func:`case_spec`.

    Returns
    -------
    Sweep
    """
    from ..simulate import MosaicSensor, SensorParams

    p = dict(spec["params"])
    rng = np.random.default_rng(np.random.SeedSequence([38, spec["seed"], 1]))
    t, levels = _design_steps(spec, rng)
    fs = 2 ** spec["bit_depth"] - 1
    k_max = spec["fill"] * (fs - p["dark_level_dn"]) / spec["t_max_ms"]
    p["leak_rate_dn_per_ms"] = spec["leak_of_rate"] * k_max if spec["leaky"] else 1e-12
    sensor = MosaicSensor(SHAPE, params=SensorParams(**p), seed=spec["seed"])
    unit = sensor.light_rate("lamp A", irradiance_w_m2=1.0)
    irr = k_max / float(np.median(unit[sensor.band_map == np.argmax(
        [np.median(unit[sensor.band_map == b]) for b in range(sensor.mosaic.n_bands)])]))
    return sensor.sweep_varying_light(t, levels, "lamp A", irradiance_w_m2=irr,
                                      n_frames=spec.get("n_frames", 2), darks=spec["darks"],
                                      seed=spec["seed"] + 1000)


def outside_term(sweep, name: str, size: float, terms: dict) -> np.ndarray:
    """What an effect outside the library adds (P, S) in DN; ``size`` is relative
    (``column_gain_jump``: gain change; ``slow_lag``: fraction carried into the next step) or
    DN (``adc_ripple``: amplitude).

    Parameters
    ----------
    sweep : Sweep
        The simulated sweep.
    name : {"column_gain_jump", "slow_lag", "adc_ripple"}
    size : float
    terms : dict
        :func:`hsiffc.diagnose.effects.truth_terms` of the sweep.

    Returns
    -------
    ndarray, (P, S), DN
    """
    signal, order = terms["signal"], terms["order"]
    if name == "column_gain_jump":
        cols = np.indices(sweep.frame_shape)[1].ravel()
        block = ((cols // 4) % 2 == 1)[:, None]
        return size * signal * block * (order[None, :] > 0)
    if name == "slow_lag":
        tau = 4.0
        out = np.zeros_like(signal)
        for j in range(1, signal.shape[1]):
            out[:, j:] += np.exp(-(j - 1) / tau) * signal[:, :-j]
        return size * out
    if name == "adc_ripple":
        return size * np.sin(2 * np.pi * (signal + 32.0) / 37.0) * (signal > 0)
    raise ValueError(f"unknown outside effect {name!r}; known: {OUTSIDE_EFFECTS}")


def _noise_and_projector(sweep, terms):
    """Per-frame temporal noise (P, S) DN, the mask of usable light samples and the projector
    off the true base model's Jacobian."""
    from ..calibrate import model_and_jacobian
    from .effectfit import projector

    truth = sweep.meta["truth"]
    p = sweep.meta["simulator"]["params"]
    light, t = terms["light"], terms["t"]
    levels = np.asarray(sweep.meta["levels"], float)
    g = truth.k_dn_per_ms.reshape(-1, 1)
    theta = np.column_stack([np.log(np.maximum(g[:, 0], 1e-12)),
                             np.log(terms["a"][:, 0]), np.log(terms["b"][:, 0]),
                             terms["d"][:, 0]])
    _, jac = model_and_jacobian(theta, t, np.where(light, levels, 0.0),
                                truth.dark_current_dn_per_ms.reshape(-1, 1))
    var = (p["read_noise_dn"] ** 2 + 1 / 12.0
           + p["conversion_gain_dn_per_e"] * np.maximum(terms["signal"], 0.0))
    fs = float(sweep.full_scale_dn)
    ok = terms["expected"] < 0.9 * fs
    mask = ok & light[None, :]
    w = np.where(ok, 1.0 / var, 0.0)
    return np.sqrt(var), mask, projector(jac, w)


def detection_limit(sweep, extra_unit, terms, pair=False) -> float:
    """The size (in the unit of ``extra_unit``'s size) whose separable RMS is ``DL_OF_NOISE``
    times the temporal noise of one frame; inf when nothing of it is separable.

    Parameters
    ----------
    sweep : Sweep
        The simulated sweep.
    extra_unit : ndarray, (P, S), DN
        The effect at size 1.
    terms : dict
        :func:`hsiffc.diagnose.effects.truth_terms`.
    pair : bool
        A within-step effect (its frame difference is separable as a whole).

    Returns
    -------
    float
    """
    sd, mask, project = _noise_and_projector(sweep, terms)
    sep = 0.5 * extra_unit if pair else project(np.where(np.isfinite(extra_unit), extra_unit, 0))
    rms = float(np.sqrt(np.mean(sep[mask] ** 2))) if mask.any() else 0.0
    noise = float(np.sqrt(np.mean(sd[mask] ** 2))) if mask.any() else 1.0
    return DL_OF_NOISE * noise / rms if rms > 0 else np.inf


def _identifiable(name, spec, sweep):
    one_exposure = spec["design"] == "light"
    if name in ("exposure_offset", "dark_current") and one_exposure:
        return False
    return True


def _unit_term(sweep, name, spec, terms):
    from .effects import effect_term

    if name in OUTSIDE_EFFECTS:
        return outside_term(sweep, name, 1.0, terms)
    return effect_term(sweep, name, 1.0, seed=spec["effect_seed"], terms=terms)


def build_case(spec: dict):
    """The sweep of a case and what was put in it.

    Parameters
    ----------
    spec : dict
        From :func:`case_spec`.

    Returns
    -------
    sweep : Sweep
        The sweep with the effects in its raw frames.
    truth : dict
        ``kind``, ``effects`` [{name, multiple, size, detection_limit}], ``outside`` (bool).
    """
    from .effects import add_term, effect_term, truth_terms

    if spec.get("round") == 3:
        return _build_class_case(spec)
    if spec.get("round") in (5, 6):
        return ccd_sweep(spec)
    sweep = clean_sweep(spec)
    terms = truth_terms(sweep)
    fs = float(sweep.full_scale_dn)
    kind = spec["kind"]
    put = []
    if kind in ("single", "pair", "outside"):
        names = [spec["outside"]] if kind == "outside" else spec["candidates"]
        want = 2 if kind == "pair" else 1
        multiples = [10] if kind == "pair" else sorted(
            {m for m in MULTIPLES if m <= spec["multiple"]}, reverse=True)
        for name in names:
            if len(put) == want:
                break
            if not _identifiable(name, spec, sweep):
                continue
            unit = _unit_term(sweep, name, spec, terms)
            dl = detection_limit(sweep, unit, terms, pair=name == "frame_light_change")
            for m in multiples:
                size = m * dl
                peak = float(np.abs(unit).max()) * size
                if np.isfinite(size) and peak <= MAX_OF_FULL_SCALE * fs:
                    put.append({"name": name, "multiple": m, "size": float(size),
                                "detection_limit": float(dl)})
                    break
        if len(put) < want:  # nothing fits this sweep: a clean control
            kind, put = "clean", []
    for e in put:
        if e["name"] in OUTSIDE_EFFECTS:
            extra = outside_term(sweep, e["name"], e["size"], terms)
        else:
            extra = effect_term(sweep, e["name"], e["size"], seed=spec["effect_seed"],
                                terms=terms)
        sweep = add_term(sweep, extra, per_frame=e["name"] == "frame_light_change")
    return sweep, {"kind": kind, "effects": put, "outside": kind == "outside"}


# --- the failure classes of issue 53 -----------------------------------------------------------
#: seeds from here on are cases of the failure classes (:func:`class_case_spec`)
CLASS_SEED0 = 100_000
#: library effects of the classes (each must be named) and effects outside the library (each
#: must be reported unexplained, the effects selected beside it as stand-ins)
CLASS_EFFECTS = ("lamp_drift", "frame_flicker", "frame_lag", "dark_outside_well")
CLASS_OUTSIDE = ("black_clamp", "blooming")
#: what the class seeds hold, in turn (each half gets each in turn)
CLASS_KINDS = ("clean",) + CLASS_EFFECTS + CLASS_OUTSIDE
CLASS_MULTIPLES = (5, 10, 30)
MAX_DARK_OF_FULL_SCALE = 0.3  # dark signal outside the photodiode at the longest exposure


def class_case_spec(seed: int) -> dict:
    """The random choices of failure-class case ``seed`` (>= ``CLASS_SEED0``): a sensor drawn as
    by :func:`case_spec`, designs the first generator lacks (3 and 4 frames per step besides
    2; 10, 12 and 14 bit; sorted or shuffled order; with or without darks) and one of
    ``CLASS_KINDS``, in turn (seeds ``CLASS_SEED0 + 2 i`` and ``+ 2 i + 1`` share a kind, so
    both halves hold each kind).

    Parameters
    ----------
    seed : int

    Returns
    -------
    dict
    """
    rng = np.random.default_rng(np.random.SeedSequence([53, seed]))
    what = CLASS_KINDS[((seed - CLASS_SEED0) // 2) % len(CLASS_KINDS)]
    bits, fs, full_well, dark, gain = _sensor(rng, [10, 12, 14, 14])
    design = str(rng.choice(["exposure", "light", "mixed"]))
    if what == "dark_outside_well" and design == "light":
        design = "exposure"  # a dark signal needs two exposures
    leaky = bool(rng.random() < 0.5) or what == "dark_outside_well"  # else it is dark_current
    darks = bool(rng.random() < 0.5)
    shuffled = bool(rng.random() < 0.5)
    if what == "lamp_drift" and design != "mixed":
        shuffled = True  # in a sorted sweep a drift in acquisition order follows the signal
    spec = {
        "seed": seed, "half": half_of(seed), "round": 3, "bit_depth": bits, "design": design,
        "darks": darks, "leaky": leaky, "n_steps": int(rng.integers(16, 37)),
        "n_rates": int(rng.integers(1, 5)) if design == "exposure" else 0,
        "shuffled": shuffled, "n_frames": int(rng.choice([2, 3, 4])),
        "t_max_ms": float(rng.uniform(20.0, 200.0)),
        "fill": float(rng.uniform(0.8, 1.25) if leaky else rng.uniform(0.75, 1.1)),
        "params": {
            "bit_depth": bits, "full_well_e": full_well, "conversion_gain_dn_per_e": gain,
            "read_noise_dn": float(np.exp(rng.uniform(np.log(2), np.log(25))) * gain),
            "dark_level_dn": dark, "dsnu_dn": float(dark * rng.uniform(0.02, 0.1)),
            "prnu": float(rng.uniform(0.002, 0.02)), "dark_current_dn_per_ms": 0.0,
            "dark_current_spread": 0.5, "leak_b_per_dn": float(rng.uniform(6.0, 14.0) / fs),
            "leak_ref_dn": float(0.8 * fs), "leak_a_spread": 0.2,
        },
        "leak_of_rate": float(rng.uniform(0.3, 1.0)),
        "kind": "clean" if what == "clean" else (
            "outside" if what in CLASS_OUTSIDE else "single"),
        "class": what, "effect_seed": int(rng.integers(2 ** 31)),
        "multiple": int(rng.choice(CLASS_MULTIPLES)),
        "warm_up": float(rng.uniform(0.15, 1.0)),  # lamp drift: time constant / acquisition
    }
    if what == "dark_outside_well":
        # a dark signal outside the photodiode differs from one that leaks only where the
        # light's charge leaks: sensors driven into their leakage, exposures up to 200 ms
        spec.update(fill=float(rng.uniform(1.05, 1.25)), leak_of_rate=float(rng.uniform(0.7, 1.0)),
                    t_max_ms=float(rng.uniform(100.0, 200.0)))
    return spec


def _frame_index(sweep):
    """Step index (into ``sweep.steps()``) of every frame, and the frame's acquisition time
    in [0, 1] (a camera at a fixed frame rate: the frame index)."""
    steps = list(sweep.steps())
    index = np.array([steps.index(s) for s in sweep.step])
    return index, np.arange(sweep.n_frames) / max(sweep.n_frames - 1, 1)


def _warm_up(time, tau):
    """A lamp warming up: its relative light rises as 1 - exp(-time / tau), scaled to 1 over
    the acquisition and centred (the mean light is the stated one)."""
    g = (1 - np.exp(-time / tau)) / (1 - np.exp(-1 / tau))
    return g - g.mean()


def _clamp_offset(mean_signal, fs):
    """Black-level clamp: the optical-black reference follows the frame's mean signal above
    30 % of full scale (DN of offset per DN of mean signal above it; negative: the clamp
    pulls the frame down)."""
    return -np.maximum(mean_signal - 0.3 * fs, 0.0)


def _bloom(signal_frames, shape, threshold):
    """Charge a pixel collects above ``threshold`` (DN) spills into its 4 neighbours:
    ``signal_frames`` (N, P) above dark -> what each pixel receives at unit spill (N, P)."""
    excess = np.maximum(signal_frames - threshold, 0.0).reshape((-1,) + tuple(shape))
    out = np.zeros_like(excess)
    out[:, 1:, :] += excess[:, :-1, :]
    out[:, :-1, :] += excess[:, 1:, :]
    out[:, :, 1:] += excess[:, :, :-1]
    out[:, :, :-1] += excess[:, :, 1:]
    return out.reshape(signal_frames.shape)


def class_unit(sweep, spec, terms) -> np.ndarray:
    """What a failure class adds at size 1 to the noise-free step means (P, S), DN: what its
    detection limit is measured on (for a change between the frames of a step, the change of
    the held-out frame; for a dark signal outside the photodiode, what it differs by from one
    collected in the well, which leaks: only that tells the two apart).

    Parameters
    ----------
    sweep : Sweep
    spec : dict
        From :func:`class_case_spec`.
    terms : dict
        :func:`hsiffc.diagnose.effects.truth_terms`.

    Returns
    -------
    ndarray, (P, S), DN
    """
    what = spec["class"]
    light = terms["light"][None, :]
    index, time = _frame_index(sweep)
    step_time = np.array([time[index == i].mean() for i in range(len(terms["steps"]))])
    if what == "lamp_drift":
        return light * terms["dydlnk"] * _warm_up(step_time, spec["warm_up"])[None, :]
    if what == "frame_flicker":
        return light * terms["dydlnk"]
    if what == "frame_lag":
        return terms["signal"] - terms["prev"]
    if what == "dark_outside_well":
        # what tells it from a dark current that leaks (which the base takes from the darks,
        # or dark_current without them): the dark signal's leakage at the light's level
        t = np.broadcast_to(terms["t"][None, :], terms["signal"].shape)
        k = terms["k_light"]
        with np.errstate(invalid="ignore", divide="ignore"):
            dydk = np.where(k > 0, terms["dydlnk"] / np.where(k > 0, k, 1.0), t)
        return np.where(light, t - dydk, 0.0)
    fs = float(sweep.full_scale_dn) - terms["d"].mean()
    if what == "black_clamp":
        mean = terms["signal"].mean(axis=0)
        return np.broadcast_to(_clamp_offset(mean, fs)[None, :], terms["signal"].shape)
    if what == "blooming":
        return _bloom(terms["signal"].T, sweep.frame_shape, 0.6 * fs).T
    raise ValueError(f"unknown failure class {what!r}; known: {CLASS_KINDS}")


def class_frames(sweep, spec, size, terms):
    """The sweep with failure class ``spec["class"]`` of ``size`` put into its raw frames one
    by one, written here from the physics of each effect (not through the effect library):
    a lamp warming up in acquisition time; the light of every frame off at random; a fraction
    of each frame's signal read again in the next; a dark signal collected outside the
    photodiode (with its shot noise); a black-level clamp that follows the frame's mean signal;
    charge above 60 % of the range spilling into the 4 neighbours.

    Parameters
    ----------
    sweep : Sweep
        The clean simulated sweep.
    spec : dict
        From :func:`class_case_spec`.
    size : float
        Relative (lamp_drift: full warm-up; frame_flicker: RMS per frame; frame_lag and
        blooming: fraction; black_clamp: DN per DN of mean signal), or DN/ms
        (dark_outside_well: median pixel).
    terms : dict
        :func:`hsiffc.diagnose.effects.truth_terms`.

    Returns
    -------
    Sweep
    """
    from dataclasses import replace as replace_fields

    what = spec["class"]
    rng = np.random.default_rng(spec["effect_seed"])
    index, time = _frame_index(sweep)
    n = sweep.n_frames
    frames = sweep.data.reshape(n, -1).astype(np.float64)
    light = terms["light"][index]
    d = terms["d"][:, 0]
    fs = float(sweep.full_scale_dn) - float(d.mean())
    if what == "lamp_drift":
        frames += (light * size * _warm_up(time, spec["warm_up"]))[:, None] \
            * terms["dydlnk"][:, index].T
    elif what == "frame_flicker":
        eps = np.where(light, size * rng.standard_normal(n), 0.0)
        frames += eps[:, None] * terms["dydlnk"][:, index].T
    elif what == "frame_lag":
        frames[1:] += size * (frames[:-1] - d[None, :])
    elif what == "dark_outside_well":
        gain = sweep.meta["simulator"]["params"]["conversion_gain_dn_per_e"]
        rate = size * rng.lognormal(0.0, 0.3, frames.shape[1])  # DN/ms per pixel
        t = sweep.exposure_ms[:, None]
        frames += gain * rng.poisson(rate[None, :] * t / gain)
    elif what == "black_clamp":
        frames += size * _clamp_offset((frames - d[None, :]).mean(axis=1), fs)[:, None]
    elif what == "blooming":
        frames += size * _bloom(frames - d[None, :], sweep.frame_shape, 0.6 * fs)
    else:
        raise ValueError(f"unknown failure class {what!r}; known: {CLASS_KINDS}")
    data = np.clip(np.rint(frames), 0, sweep.full_scale_dn).reshape(sweep.data.shape)
    return replace_fields(sweep, data=data.astype(sweep.data.dtype))


def _build_class_case(spec):
    from .effects import truth_terms

    sweep = clean_sweep(spec)
    if spec["kind"] == "clean":
        return sweep, {"kind": "clean", "effects": [], "outside": False, "class": "clean"}
    terms = truth_terms(sweep)
    unit = class_unit(sweep, spec, terms)
    pair = spec["class"] in ("frame_flicker", "frame_lag")
    dl = detection_limit(sweep, unit, terms, pair=pair)
    fs = float(sweep.full_scale_dn)
    put = None
    # the largest change the class makes to a frame at size 1 (DN): a dark signal outside the
    # photodiode adds its whole self, up to MAX_DARK_OF_FULL_SCALE of full scale
    peak, cap = float(np.abs(unit).max()), MAX_OF_FULL_SCALE
    if spec["class"] == "dark_outside_well":
        peak, cap = float(terms["t"].max()), MAX_DARK_OF_FULL_SCALE
    for m in sorted({m for m in CLASS_MULTIPLES if m <= spec["multiple"]}, reverse=True):
        size = m * dl
        if np.isfinite(size) and peak * size <= cap * fs:
            put = {"name": spec["class"], "multiple": m, "size": float(size),
                   "detection_limit": float(dl)}
            break
    if put is None:
        return sweep, {"kind": "clean", "effects": [], "outside": False, "class": "clean"}
    sweep = class_frames(sweep, spec, put["size"], terms)
    return sweep, {"kind": spec["kind"], "effects": [put], "outside": spec["kind"] == "outside",
                   "class": spec["class"]}



# --- round five: a linear sensor with an exposure offset and a soft well compression ----------
#: seeds from here on are cases of the linear-sensor stream (:func:`ccd_case_spec`)
CLASS2_SEED0 = 200_000
#: what the stream's seeds hold, in turn (each half gets each in turn)
CCD_KINDS = ("clean_linear", "exposure_offset", "well_compression", "offset_and_compression")
#: the library effects that name each kind: a well that compresses as it fills, with one
#: capacity for the sensor, is a function of each pixel's own signal only, the same for every
#: pixel: on the data that is a readout nonlinearity (the library cannot tell where in the
#: chain a compression common to the pixels happens)
CCD_NAMES = {"clean_linear": (), "exposure_offset": ("exposure_offset",),
             "well_compression": ("readout_nonlinearity",),
             "offset_and_compression": ("exposure_offset", "readout_nonlinearity")}
CCD_COMPRESSION_AT = 0.85  # the compression is stated at this fraction of the range above dark


def ccd_case_spec(seed: int) -> dict:
    """The random choices of linear-sensor case ``seed`` (>= ``CLASS2_SEED0``): a CCD-like or
    mosaic sensor without leakage (10-14 bit, dark level, read noise, PRNU), an exposure sweep
    at one light level or several (sorted or shuffled, with or without darks at every
    exposure, 2-4 frames per step) and one of ``CCD_KINDS`` in turn: nothing, an exposure
    offset (light collected for the nominal exposure plus 0.2-2 % of the longest), a soft
    compression of the well as it fills (0.5-4 % at 85 % of the range) or both.

    Parameters
    ----------
    seed : int

    Returns
    -------
    dict
    """
    rng = np.random.default_rng(np.random.SeedSequence([53, 5, seed]))
    what = CCD_KINDS[((seed - CLASS2_SEED0) // 2) % len(CCD_KINDS)]
    bits, fs, full_well, dark, gain = _sensor(rng, [10, 12, 14])
    n_rates = 1 if rng.random() < 0.5 else int(rng.integers(2, 4))
    darks = bool(rng.random() < 0.5)
    offset = "offset" in what
    if offset and n_rates == 1:
        # one light level without darks: the offset's light (k t0 a pixel) is one more dark
        # level, which nothing can tell from the dark level; such a sweep is not drawn
        darks = True
    t_max = float(np.exp(rng.uniform(np.log(1.0), np.log(200.0))))
    return {
        "seed": seed, "half": half_of(seed), "round": 5, "class": what, "bit_depth": bits,
        "design": "exposure", "darks": darks, "leaky": False,
        "n_steps": int(rng.integers(16, 41)), "n_rates": n_rates,
        "shuffled": bool(rng.random() < 0.3), "n_frames": int(rng.choice([2, 3, 4])),
        "t_max_ms": t_max, "t_min_ms": t_max / float(rng.uniform(50.0, 350.0)),
        "spacing": str(rng.choice(["linear", "geometric"])),
        "mosaic": bool(rng.random() < 0.5), "fill": float(rng.uniform(0.75, 1.0)),
        "params": {"bit_depth": bits, "full_well_e": full_well,
                   "conversion_gain_dn_per_e": gain, "dark_level_dn": dark,
                   "dsnu_dn": float(rng.uniform(0.1, 1.0)),
                   "read_noise_dn": float(np.exp(rng.uniform(np.log(2), np.log(25))) * gain),
                   "prnu": float(rng.uniform(0.002, 0.01)), "dark_current_dn_per_ms": 0.0},
        "t0_of_max": float(rng.uniform(0.002, 0.02)) if offset else 0.0,
        "compression": float(rng.uniform(0.005, 0.04)) if "compression" in what else 0.0,
        "effect_seed": int(rng.integers(2 ** 31)),
    }


def _well_capacity(compression: float, x0: float) -> float:
    """The scale ``S`` (DN) of a well that fills as ``S (1 - exp(-x / S))``, whose response is
    ``compression`` low (relative) at the linear signal ``x0`` (DN); inf for none."""
    if compression <= 0:
        return np.inf
    lo, hi = x0 / 50.0, x0 / compression  # the deficit x / (2 S) to first order
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        deficit = 1.0 - mid * -np.expm1(-x0 / mid) / x0
        lo, hi = (mid, hi) if deficit > compression else (lo, mid)
    return float(np.sqrt(lo * hi))


def _ccd_multiple(extra, signal, t, levels, darks, var, ok) -> float:
    """The multiple of its detection limit an effect that adds ``extra`` (P, S) DN to the
    light samples of a linear sensor is: the RMS of what a line per pixel (dark level and
    gain; the dark level fixed by the darks where there are some, zero-effect samples at the
    dark level) cannot absorb, over the samples ``ok``, in units of ``DL_OF_NOISE`` times the
    noise of one frame ``var`` (P, S) DN^2."""
    x = np.broadcast_to(levels * t, signal.shape)
    w = np.where(ok, 1.0 / var, 0.0)
    if darks:  # a dark step at every exposure: as many samples of the dark level alone
        w_dark = (1.0 / var.min(axis=1))[:, None] * np.ones_like(t)[None, :]
        x = np.concatenate([x, 0.0 * x], axis=1)
        w = np.concatenate([w, w_dark], axis=1)
        extra = np.concatenate([extra, 0.0 * extra], axis=1)
    a = np.stack([np.ones_like(x), x], axis=-1)  # (P, S, 2)
    normal = np.einsum("psi,ps,psj->pij", a, w, a)
    rhs = np.einsum("psi,ps,ps->pi", a, w, extra)[..., None]
    beta = np.linalg.solve(normal + 1e-12 * np.eye(2), rhs)[..., 0]
    sep = (extra - np.einsum("psi,pi->ps", a, beta))[:, :signal.shape[1]]
    rms = float(np.sqrt(np.mean(sep[ok] ** 2)))
    return rms / (DL_OF_NOISE * float(np.sqrt(np.mean(var[ok]))))


def ccd_sweep(spec: dict):
    """The sweep of a linear-sensor case, written here from its physics (not through the
    simulator or the effect library): each pixel collects photo-electrons (Poisson) at its
    light rate for the nominal exposure plus ``t0``; its well compresses the charge softly as
    it fills (``S (1 - exp(-q / S))``, one capacity for the sensor); where the spec draws a
    ``well`` (:func:`well_case_spec`), the charge stops at the pixel's full well below the
    ADC's range (:func:`_full_well`); then the pixel's dark level, read noise, rounding and the
    ADC's clip at full scale. Darks (where drawn) follow
    every light step at its exposure and hold the dark level alone (no dark current). An
    effect drawn below 5 times its detection limit on the sweep (:func:`_ccd_multiple`) is
    raised to 5 times it.

    Parameters
    ----------
    spec : dict
        From :func:`ccd_case_spec`.

    Returns
    -------
    sweep : Sweep
    truth : dict
        ``kind``, ``effects`` [{name, size, unit, multiple}], ``outside`` (False), ``class``,
        ``stream`` (5; 6 with a ``well``, and ``well_dn`` above dark, ``well_soft``), ``t0_ms``
        and ``compression``.
    """
    from ..data.sweep import Sweep

    p = spec["params"]
    rng = np.random.default_rng(np.random.SeedSequence([53, 5, spec["seed"], 1]))
    fs = 2 ** spec["bit_depth"] - 1
    gain, d0, rn = p["conversion_gain_dn_per_e"], p["dark_level_dn"], p["read_noise_dn"]
    n_pix = SHAPE[0] * SHAPE[1]
    # pixel response: a 4 x 4 mosaic of band factors (or one band: a CCD) with PRNU
    band = np.ones((4, 4))
    if spec["mosaic"]:
        band = rng.uniform(0.4, 1.0, (4, 4))
        band /= band.max()
    resp = (np.tile(band, (SHAPE[0] // 4, SHAPE[1] // 4)).ravel()
            * (1.0 + p["prnu"] * rng.standard_normal(n_pix)))
    dark = d0 + p["dsnu_dn"] * rng.standard_normal(n_pix)
    # the light rates (DN/ms of linear signal at response 1): the brightest pixel of the
    # brightest rate fills ``fill`` of the range at the longest exposure
    rates = np.geomspace(1.0, rng.uniform(0.2, 0.5), spec["n_rates"]) if spec["n_rates"] > 1 \
        else np.ones(1)
    k_max = spec["fill"] * (fs - d0) / (spec["t_max_ms"] * resp.max())
    per = int(np.ceil(spec["n_steps"] / rates.size))
    space = np.linspace if spec["spacing"] == "linear" else np.geomspace
    t_nom = np.concatenate([space(spec["t_min_ms"], spec["t_max_ms"], per) for _ in rates])
    levels = np.repeat(rates, per)
    order = rng.permutation(t_nom.size) if spec["shuffled"] else np.arange(t_nom.size)
    t_nom, levels = t_nom[order], levels[order]
    well = spec.get("well")  # round six: a full well below the ADC's range
    top = fs if well is None else d0 + well["of_range"] * (fs - d0)  # DN
    x0 = CCD_COMPRESSION_AT * (top - d0)

    def mean_signal(t0, compression):  # noise-free signal above dark (P, S), DN
        x = k_max * resp[:, None] * (levels * (t_nom + t0))[None, :]
        scale = _well_capacity(compression, x0)
        return x if not np.isfinite(scale) else -scale * np.expm1(-x / scale)

    clean = mean_signal(0.0, 0.0)
    var = rn ** 2 + 1 / 12.0 + gain * clean
    ok = clean + d0 < 0.9 * top
    sizes = {"t0": spec["t0_of_max"] * spec["t_max_ms"], "compression": spec["compression"]}
    multiples = {}
    for key in ("t0", "compression"):
        if not sizes[key]:
            continue
        for _ in range(3):  # raised to 5x its detection limit where drawn below
            args = (sizes[key], 0.0) if key == "t0" else (0.0, sizes[key])
            m = _ccd_multiple(mean_signal(*args) - clean, clean, t_nom, levels,
                              spec["darks"], var, ok)
            if m >= 5.0:
                break
            sizes[key] *= 5.05 / m
        multiples[key] = float(m)
    t0, compression = sizes["t0"], sizes["compression"]
    capacity = _well_capacity(compression, x0) / gain  # e-
    full_well = None if well is None else _full_well(well, (top - d0) / gain, n_pix, spec["seed"])
    frames, exposure, kind, photons, step = [], [], [], [], []
    n_f = spec["n_frames"]
    for t, lev in zip(t_nom, levels):
        electrons = rng.poisson(np.broadcast_to(lev * k_max * resp * (t + t0) / gain,
                                                (n_f, n_pix))).astype(np.float64)
        if np.isfinite(capacity):
            electrons = -capacity * np.expm1(-electrons / capacity)
        if full_well is not None:
            electrons = full_well(electrons)
        steps = [(gain * electrons, "light")] + ([(0.0 * electrons, "dark")]
                                                 if spec["darks"] else [])
        for signal, what in steps:
            frames.append(dark + signal + rn * rng.standard_normal((n_f, n_pix)))
            exposure += [t] * n_f
            kind += [what] * n_f
            photons += [lev * t if what == "light" else np.nan] * n_f
            step += [len(frames) - 1] * n_f
    data = np.clip(np.rint(np.concatenate(frames)), 0, fs).astype(np.uint16)
    sweep = Sweep(data.reshape((-1,) + SHAPE), exposure, kind, spec["bit_depth"], step=step,
                  photons=photons, illumination=["lamp" if k == "light" else "" for k in kind],
                  source="simulated (round five: a linear sensor, hsiffc.diagnose.evaluation)",
                  meta={"generator": "hsiffc.diagnose.evaluation.ccd_sweep", "t0_ms": t0,
                        "compression": compression,
                        **({} if well is None else {"well_dn": top - d0})})
    effects = []
    if t0:
        effects.append({"name": "exposure_offset", "size": t0, "unit": "ms",
                        "multiple": multiples["t0"]})
    if compression:
        effects.append({"name": "readout_nonlinearity", "size": compression,
                        "unit": f"relative, at {CCD_COMPRESSION_AT:g} of the range above dark",
                        "multiple": multiples["compression"]})
    truth = {"kind": "clean" if not effects else "pair" if len(effects) == 2 else "single",
             "effects": effects, "outside": False, "class": spec["class"], "stream": 5,
             "t0_ms": t0, "compression": compression}
    if well is not None:
        truth.update(stream=6, well_dn=float(top - d0), well_soft=well["soft"])
    return sweep, truth


# --- round six: the same linear sensor, whose well fills below the ADC's range -----------------
#: seeds from here on are cases of the full-well stream (:func:`well_case_spec`)
CLASS3_SEED0 = 300_000


def well_case_spec(seed: int) -> dict:
    """The random choices of full-well case ``seed`` (>= ``CLASS3_SEED0``): a linear-sensor
    case as :func:`ccd_case_spec` draws it (the same kinds in turn), whose well fills below the
    ADC's full scale (55-95 % of the range above dark), so that the brightest samples sit on a
    plateau with the read noise after the well (no pile-up at one code): a hard well or a soft
    one (the response rounds into it over 0.3-1.5 % of the capacity), the capacity spread
    0-0.5 % over the pixels, and the brightest pixel's linear signal at the longest exposure
    1.02-1.5 times the well. Drawn from a seed sequence of its own.

    Parameters
    ----------
    seed : int

    Returns
    -------
    dict
    """
    spec = ccd_case_spec(seed)
    rng = np.random.default_rng(np.random.SeedSequence([53, 6, seed]))
    well = {"of_range": float(rng.uniform(0.55, 0.95)), "over": float(rng.uniform(1.02, 1.5)),
            "soft": float(rng.uniform(0.003, 0.015)) if rng.random() < 0.5 else 0.0,
            "spread": float(rng.uniform(0.0, 0.005))}
    return {**spec, "round": 6, "well": well, "fill": well["of_range"] * well["over"]}


def _full_well(well: dict, capacity_e: float, n_pix: int, seed: int):
    """The charge a pixel holds of ``q`` electrons collected (a function of ``q``, (..., P)):
    at most its capacity (``capacity_e`` with the spread of ``well``), reached hard (``min``) or
    softly (a smooth minimum over ``soft`` of the capacity); the charge beyond drains away, so a
    full pixel has no shot noise."""
    rng = np.random.default_rng(np.random.SeedSequence([53, 6, seed, 2]))
    cap = capacity_e * (1.0 + well["spread"] * rng.standard_normal(n_pix))
    width = well["soft"] * capacity_e
    if width <= 0:
        return lambda q: np.minimum(q, cap)
    return lambda q: cap - width * np.logaddexp(0.0, (cap - q) / width)


def ccd_verdict(truth: dict, found: dict) -> dict:
    """Score a linear-sensor case: ``right`` when exactly the effects that name its kind
    (``CCD_NAMES``) are selected, nothing is unexplained and leakage is not claimed (none was
    put in: ``leakage`` not ``"needed"``); ``false_alarm`` for a clean control with something
    selected, unexplained or leakage claimed; ``leakage_claimed``.

    Parameters
    ----------
    truth : dict
        From :func:`ccd_sweep`.
    found : dict
        What diagnose found (``selected``, ``unexplained``, ``leakage``).

    Returns
    -------
    dict

    Examples
    --------
    >>> ccd_verdict({"class": "exposure_offset"},
    ...             {"selected": ["exposure_offset"], "unexplained": False,
    ...              "leakage": "cannot tell"})
    {'right': True, 'false_alarm': False, 'leakage_claimed': False}
    """
    claimed = found.get("leakage") == "needed"
    right = (set(found["selected"]) == set(CCD_NAMES[truth["class"]])
             and not found["unexplained"] and not claimed)
    return {"right": right, "false_alarm": truth["class"] == "clean_linear" and not right,
            "leakage_claimed": claimed}


def run_case(seed: int) -> dict:
    """Build case ``seed``, diagnose it and score it.

    Parameters
    ----------
    seed : int

    Returns
    -------
    dict
        The case (spec summary and what was put in), what diagnose found and the verdict.
    """
    from . import diagnose
    from ..errors import DataFormatError

    spec = case_spec(seed)
    sweep, truth = build_case(spec)
    t0 = time.perf_counter()
    try:
        out = diagnose(sweep, max_pixels=MAX_PIXELS, seed=seed)
        found = {"selected": out["selected_effects"], "unexplained": out["unexplained"],
                 "ambiguous": out.get("ambiguous", []), "base": out["base_model"],
                 "dark_current_in_base": "dark current" in out["dark_model"]["model"],
                 # the dark signal in the base, collected outside the photodiode (not leaking)
                 "dark_outside_in_base": out["dark_model"].get("leaks") is False,
                 "noise_floor_dn": out["noise_floor_dn"],
                 "systematic_after_dn": out["after"]["systematic_rms_dn"],
                 # what each test of the residual found: grouping, structured and null RMS
                 # (DN), p-value, significant
                 "structure": [[f["grouping"], f["structured_rms_dn"],
                                f["null_structured_rms_dn"], f["p_value"], f["significant"]]
                               for f in out["residual_structure_after"]],
                 "stand_ins": list(out.get("stand_ins", [])),
                 "leakage": out["leakage"]["verdict"], "refused": None}
    except DataFormatError as exc:
        found = {"selected": [], "unexplained": False, "ambiguous": [], "base": "",
                 "dark_current_in_base": False, "stand_ins": [], "refused": str(exc)}
    found["runtime_s"] = time.perf_counter() - t0
    case = {k: spec[k] for k in ("seed", "half", "bit_depth", "design", "darks", "leaky",
                                 "n_steps", "n_rates", "shuffled")}
    case["n_frames"] = spec.get("n_frames", 2)
    case["class"] = truth.get("class")
    case["sensor_dark_current"] = spec["params"]["dark_current_dn_per_ms"] > 0
    score = (ccd_verdict(truth, found) if truth.get("stream") in (5, 6)
             else verdict(truth, found))
    return {"case": case, "truth": truth, "found": found, **score}


def verdict(truth: dict, found: dict) -> dict:
    """Score one case: ``right`` (the effects put in, and only they, are named; for a clean
    control nothing selected and nothing unexplained; for an effect outside the library
    ``unexplained``) and ``false_alarm`` (a clean control with something selected or
    unexplained).

    Parameters
    ----------
    truth : dict
        From :func:`build_case`.
    found : dict
        What diagnose found (``selected``, ``unexplained``, ``dark_current_in_base``).

    Returns
    -------
    dict
        ``right`` and ``false_alarm`` (bool).

    Examples
    --------
    >>> verdict({"kind": "single", "effects": [{"name": "image_lag"}]},
    ...         {"selected": ["image_lag"], "unexplained": False, "dark_current_in_base": False})
    {'right': True, 'false_alarm': False}
    """
    sel = set(found["selected"])
    if truth["kind"] == "clean":
        alarm = bool(sel) or bool(found["unexplained"])
        return {"right": not alarm, "false_alarm": alarm}
    if truth["kind"] == "outside":
        return {"right": bool(found["unexplained"]), "false_alarm": False}
    want = {e["name"] for e in truth["effects"]}
    if "dark_current" in want and found.get("dark_current_in_base"):
        sel = sel | {"dark_current"}
    if "dark_outside_well" in want and found.get("dark_outside_in_base"):
        sel = sel | {"dark_outside_well"}
    return {"right": sel == want, "false_alarm": False}


def run(case_seeds, jobs: int = 1, progress=None) -> list[dict]:
    """:func:`run_case` for every seed (in ``jobs`` processes).

    Parameters
    ----------
    case_seeds : sequence of int
    jobs : int
        Worker processes (1: in this process).
    progress : callable, optional
        Called with each result as it comes.

    Returns
    -------
    list of dict
        In the order of the seeds.
    """
    results = []
    if jobs <= 1:
        for s in case_seeds:
            results.append(run_case(s))
            if progress:
                progress(results[-1])
        return results
    from concurrent.futures import ProcessPoolExecutor
    with ProcessPoolExecutor(jobs) as pool:
        for r in pool.map(run_case, case_seeds):
            results.append(r)
            if progress:
                progress(r)
    return results


def _row_label(r):
    t = r["truth"]
    if t["kind"] == "clean":
        return "clean"
    if t["kind"] == "pair":
        return "pair: " + " + ".join(sorted(e["name"] for e in t["effects"]))
    return t["effects"][0]["name"] + (" (outside)" if t["kind"] == "outside" else "")


def summarise(results: list[dict]) -> dict:
    """Scores and the confusion matrix of a list of :func:`run_case` results.

    Parameters
    ----------
    results : list of dict

    Returns
    -------
    dict
        ``scores`` (fractions with their counts), ``by_multiple``, ``confusion``
        (row label -> {n, column -> count}) and ``columns``.
    """
    def frac(rows, key="right"):
        n = len(rows)
        k = sum(bool(r[key]) for r in rows)
        return {"fraction": k / n if n else None, "right": k, "n": n}

    every = results
    ccd = [r for r in results if r["truth"].get("stream") == 5]  # scored on their own
    well = [r for r in results if r["truth"].get("stream") == 6]
    results = [r for r in results if r["truth"].get("stream") not in (5, 6)]
    single = [r for r in results if r["truth"]["kind"] == "single"]
    pairs = [r for r in results if r["truth"]["kind"] == "pair"]
    outside = [r for r in results if r["truth"]["kind"] == "outside"]
    clean = [r for r in results if r["truth"]["kind"] == "clean"]
    big = [r for r in single if r["truth"]["effects"][0]["multiple"] >= 5]
    scores = {
        "named_right_5x": frac(big),
        "named_right_2x": frac([r for r in single if r["truth"]["effects"][0]["multiple"] == 2]),
        "pairs_both_named": frac(pairs),
        "false_alarm_clean": frac(clean, "false_alarm"),
        "outside_unexplained": frac([r for r in outside
                                     if r["truth"]["effects"][0]["multiple"] >= 5]),
        "outside_unexplained_2x": frac([r for r in outside
                                        if r["truth"]["effects"][0]["multiple"] == 2]),
        "ambiguous_reported": frac([dict(r, right=bool(r["found"]["ambiguous"]))
                                    for r in results]),
    }
    unexplained = [r for r in results if r["found"]["unexplained"] and r["found"]["selected"]]
    scores["stand_ins_labelled"] = frac([dict(r, right=set(r["found"].get("stand_ins", []))
                                              == set(r["found"]["selected"]))
                                         for r in unexplained])
    by_multiple = {str(m): frac([r for r in single if r["truth"]["effects"][0]["multiple"] == m])
                   for m in MULTIPLES}
    by_class = {}
    for what in CLASS_KINDS:
        rows = [r for r in results if r["case"].get("class") == what
                or (what == "clean" and r["case"].get("class") == "clean")]
        if not rows:
            continue
        by_class[what] = {"right": frac(rows), "false_alarm": frac(rows, "false_alarm"),
                          "designs": sorted({f"{r['case']['n_frames']} frames" for r in rows}),
                          # the detection ladder: right at each multiple of the detection limit
                          "by_multiple": {str(m): frac([r for r in rows if r["truth"]["effects"]
                                                        and r["truth"]["effects"][0]["multiple"]
                                                        == m]) for m in CLASS_MULTIPLES}}
    columns = ["nothing"] + _library() + ["unexplained"]
    confusion: dict = {}
    for r in results:
        if r["truth"]["kind"] == "single" and r["truth"]["effects"][0]["multiple"] < 5:
            continue
        if r["truth"]["kind"] == "outside" and r["truth"]["effects"][0]["multiple"] < 5:
            continue
        label = _row_label(r)
        row = confusion.setdefault(label, {"n": 0, **{c: 0 for c in columns}})
        row["n"] += 1
        sel = list(r["found"]["selected"])
        if r["found"].get("dark_current_in_base") and "dark_current" in label:
            sel.append("dark_current")
        if r["found"].get("dark_outside_in_base") and "dark_outside_well" in label:
            sel.append("dark_outside_well")
        for name in sel:
            row[name] += 1
        if not sel:
            row["nothing"] += 1
        if r["found"]["unexplained"]:
            row["unexplained"] += 1
    order = ["clean"] + _library()
    keys = sorted(confusion, key=lambda k: (order.index(k) if k in order else len(order), k))
    return {"scores": scores, "by_multiple": by_multiple, "by_class": by_class,
            "columns": columns,
            "confusion": {k: confusion[k] for k in keys}, "n_cases": len(every),
            "runtime_s": float(sum(r["found"]["runtime_s"] for r in every)),
            **({"ccd": summarise_ccd(ccd)} if ccd else {}),
            **({"well": summarise_ccd(well)} if well else {})}


def summarise_ccd(results: list[dict]) -> dict:
    """Scores of the linear-sensor stream (:func:`ccd_case_spec`), per kind and per design
    (one light level or several, with or without darks): right, leakage claimed, the
    exposure offset found, and what was selected.

    Parameters
    ----------
    results : list of dict
        :func:`run_case` results of the stream's seeds.

    Returns
    -------
    dict
        kind -> {n, right, leakage_claimed, offset_found, selected {name: count},
        leakage {verdict: count}, designs {label: [right, n]}}.
    """
    out: dict = {}
    for what in CCD_KINDS:
        rows = [r for r in results if r["truth"]["class"] == what]
        if not rows:
            continue
        row = {"n": len(rows), "right": sum(r["right"] for r in rows),
               "leakage_claimed": sum(bool(r.get("leakage_claimed")) for r in rows),
               "offset_found": sum("exposure_offset" in r["found"]["selected"] for r in rows),
               "unexplained": sum(bool(r["found"]["unexplained"]) for r in rows),
               "selected": {}, "leakage": {}, "designs": {}}
        for r in rows:
            for name in r["found"]["selected"] or ["nothing"]:
                row["selected"][name] = row["selected"].get(name, 0) + 1
            v = r["found"].get("leakage", "refused")
            row["leakage"][v] = row["leakage"].get(v, 0) + 1
            label = (("one light level" if r["case"]["n_rates"] == 1 else "several light levels")
                     + (", darks" if r["case"]["darks"] else ", no darks"))
            cell = row["designs"].setdefault(label, [0, 0])
            cell[0] += bool(r["right"])
            cell[1] += 1
        out[what] = row
    return out


def shared_rows(data_dir: Path) -> list[dict]:
    """Diagnose every shared data set that is present; one row each.

    Parameters
    ----------
    data_dir : Path
        ``../shared/data``.

    Returns
    -------
    list of dict
    """
    from . import diagnose
    from ..io import read_sweep

    rows = []
    for name in SHARED_SETS:
        path = data_dir / name
        if not path.exists():
            continue
        out = diagnose(read_sweep(path))
        ok = None
        if name in LINEAR_SETS:
            ok = out["base_model"].startswith("linear") and not out["selected_effects"]
        rows.append({"set": name, "put_in": SHARED_PUT_IN[name],
                     "base": out["base_model"].split(",")[0].split(";")[0],
                     "selected": out["selected_effects"], "unexplained": out["unexplained"],
                     "ambiguous": out.get("ambiguous", []), "leakage": out["leakage"]["verdict"],
                     "noise_floor_dn": out["noise_floor_dn"],
                     "systematic_after_dn": out["after"]["systematic_rms_dn"],
                     "linear_and_nothing_selected": ok,
                     # none put in: not claimed ("not needed", or "cannot tell" where the
                     # design reaches every signal at one light rate)
                     "leakage_as_put_in": (out["leakage"]["verdict"] != "needed"
                                           if name in NO_LEAKAGE_SETS else None),
                     "stand_ins": out.get("stand_ins", [])})
    return rows


def _pct(s):
    return "-" if s["fraction"] is None else f"{100 * s['fraction']:.0f} % ({s['right']}/{s['n']})"


def markdown(summary: dict, shared: list[dict], how: str) -> str:
    """The evaluation's tables in Markdown.

    Parameters
    ----------
    summary : dict
        From :func:`summarise`.
    shared : list of dict
        From :func:`shared_rows`.
    how : str
        How and where it was measured (one sentence).

    Returns
    -------
    str
    """
    sc = summary["scores"]
    goal_rows = [
        ("library effect at >= 5x its detection limit named right (and nothing else)",
         sc["named_right_5x"], ">= 90 %", GOALS["named_right_5x"], True),
        ("false alarms on clean sweeps (something selected or unexplained)",
         sc["false_alarm_clean"], "<= 5 %", GOALS["false_alarm_clean"], False),
        ("out-of-library effect at >= 5x reported unexplained", sc["outside_unexplained"],
         ">= 90 %", GOALS["outside_unexplained"], True),
    ]
    lines = [how, "", "| measure | result | goal | met |", "|---|---|---|---|"]
    for label, s, goal, g, higher in goal_rows:
        met = "-" if s["fraction"] is None else (
            "yes" if (s["fraction"] >= g if higher else s["fraction"] <= g) else "**no**")
        lines.append(f"| {label} | {_pct(s)} | {goal} | {met} |")
    lab = sc.get("stand_ins_labelled", {"fraction": None, "right": 0, "n": 0})
    lines.append("| cases reported unexplained with effects selected: all of them labelled "
                 f"stand-ins | {_pct(lab)} | 100 % | "
                 + ("-" if lab["fraction"] is None else
                    "yes" if lab["fraction"] == 1.0 else "**no**") + " |")
    lines += [f"| library effect at 2x named right | {_pct(sc['named_right_2x'])} | | |",
              f"| pairs (10x each): both named, nothing else | {_pct(sc['pairs_both_named'])} "
              "| | |",
              f"| out-of-library effect at 2x reported unexplained | "
              f"{_pct(sc['outside_unexplained_2x'])} | | |",
              f"| cases with an `ambiguous` entry | {_pct(sc['ambiguous_reported'])} | | |", ""]
    if summary.get("by_class"):
        lines += ["The failure classes of issue 53 (seeds from "
                  f"{CLASS_SEED0}; 2, 3 or 4 frames per step, 10-14 bit, sorted or shuffled, "
                  "with or without darks; effects at 5x, 10x or 30x their detection limit; "
                  "right: the class named alone, or for a class outside the library reported "
                  "unexplained, or for a clean control nothing selected or unexplained):", "",
                  "| class | right | false alarms | frames per step |", "|---|---|---|---|"]
        for what, row in summary["by_class"].items():
            label = what + (" (outside)" if what in CLASS_OUTSIDE else "")
            alarm = _pct(row["false_alarm"]) if what == "clean" else ""
            lines.append(f"| {label} | {_pct(row['right'])} | {alarm} | "
                         f"{', '.join(row['designs'])} |")
        lines += ["", "Detection ladder of the failure classes (right, by the multiple of the "
                  "detection limit put in):", "",
                  "| class | " + " | ".join(f"{m}x" for m in CLASS_MULTIPLES) + " |",
                  "|---|" + "---|" * len(CLASS_MULTIPLES)]
        for what, row in summary["by_class"].items():
            if what == "clean" or "by_multiple" not in row:
                continue
            label = what + (" (outside)" if what in CLASS_OUTSIDE else "")
            lines.append(f"| {label} | " + " | ".join(_pct(row["by_multiple"][str(m)])
                                                     for m in CLASS_MULTIPLES) + " |")
        lines.append("")
    if summary.get("ccd"):
        lines += markdown_ccd(summary["ccd"])
    if summary.get("well"):
        lines += markdown_ccd(summary["well"], well=True)
    lines += ["Named right, by size (single library effects):", "",
              "| multiple of the detection limit | " + " | ".join(
                  f"{m}x" for m in MULTIPLES) + " |",
              "|---|" + "---|" * len(MULTIPLES),
              "| named right | " + " | ".join(_pct(summary["by_multiple"][str(m)])
                                             for m in MULTIPLES) + " |", ""]
    cols = summary["columns"]
    short = {c: c.replace("_", " ") for c in cols}
    lines += ["Confusion matrix (rows: what was put in, library effects at >= 5x, outside "
              "effects at >= 5x; columns: how many of the row's cases selected that effect, "
              "selected nothing, or were reported unexplained; a case can count in several "
              "columns):", "",
              "| put in | n | " + " | ".join(short[c] for c in cols) + " |",
              "|---|---|" + "---|" * len(cols)]
    for label, row in summary["confusion"].items():
        lines.append(f"| {label} | {row['n']} | " + " | ".join(
            str(row[c]) if row[c] else "." for c in cols) + " |")
    if shared:
        lines += ["", "Shared data sets (`../shared/data`, one row each, none tuned on; the two "
                  "linear reference simulations must keep a linear base with nothing selected; "
                  "the sets made without leakage should not find it needed):", "",
                  "| set | put in | base | selected | leakage | unexplained | ambiguous | noise "
                  "floor (DN) | systematic after (DN) | linear, nothing selected | leakage as "
                  "put in |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        yes_no = {None: "-", True: "yes", False: "**no**"}
        for r in shared:
            amb = "; ".join(" / ".join(a["effects"]) for a in r["ambiguous"]) or "-"
            sel = ", ".join(r["selected"]) or "-"
            if r["stand_ins"]:
                sel += " (stand-ins: " + ", ".join(r["stand_ins"]) + ")"
            lines.append(f"| {r['set']} | {r['put_in']} | {r['base']} | {sel} | "
                         f"{r['leakage']} | {'yes' if r['unexplained'] else 'no'} | {amb} | "
                         f"{r['noise_floor_dn']:.3g} | {r['systematic_after_dn']:.3g} | "
                         f"{yes_no[r['linear_and_nothing_selected']]} | "
                         f"{yes_no[r['leakage_as_put_in']]} |")
    return "\n".join(lines) + "\n"


def markdown_ccd(ccd: dict, well: bool = False) -> list[str]:
    """The lines of the linear-sensor stream's table (:func:`summarise_ccd`), or with ``well``
    of the full-well stream's (:func:`well_case_spec`).

    Parameters
    ----------
    ccd : dict
        From :func:`summarise_ccd`.
    well : bool
        The full-well stream.

    Returns
    -------
    list of str
    """
    def count(d):
        return ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in sorted(d.items())) or "-"

    head = (f"The same linear sensor whose well fills below the ADC's range (seeds from "
            f"{CLASS3_SEED0}; a plateau at 55-95 % of the range, hard or soft, with the read "
            "noise after it" if well else
            f"A linear sensor with an exposure offset and a soft well compression (seeds from "
            f"{CLASS2_SEED0}")
    lines = [f"{head}; no leakage; 10-14 bit, exposure sweeps at one light level or "
             "several, sorted or shuffled, with or without darks, 2-4 frames per step; offsets "
             "0.2-2 % of the longest exposure, compressions 0.5-4 % at 85 % of the range; "
             "right: " + ", ".join(f"{k.replace('_', ' ')}: "
                                   f"{' + '.join(v) if v else 'nothing'}"
                                   for k, v in CCD_NAMES.items())
             + ", nothing unexplained and leakage not `needed`):", "",
             "| put in | right | leakage claimed | exposure offset found | unexplained | "
             "selected | leakage verdicts | right by design |", "|---|---|---|---|---|---|---|---|"]
    for what, row in ccd.items():
        n = row["n"]
        designs = "; ".join(f"{k} {v[0]}/{v[1]}" for k, v in sorted(row["designs"].items()))
        right = _pct({"fraction": row["right"] / n, "right": row["right"], "n": n})
        lines.append(f"| {what.replace('_', ' ')} | {right} | {row['leakage_claimed']}/{n} | "
                     f"{row['offset_found']}/{n} | {row['unexplained']}/{n} | "
                     f"{count(row['selected'])} | {count(row['leakage'])} | {designs} |")
    return lines + [""]


def _class_label(r):
    """The row of a case in the before/after tables: its class (outside ones marked)."""
    t = r["truth"]
    if t.get("stream") in (5, 6):
        return ("linear sensor" + (", full well" if t["stream"] == 6 else "") + ": "
                + t["class"].replace("_", " "))
    if t["kind"] == "clean":
        return "clean"
    name = t["effects"][0]["name"]
    return name + (" (outside)" if t["kind"] == "outside" else "")


def before_after(before: list[dict], after: list[dict]) -> str:
    """The before/after table: the same seeds scored with the code before (``before``, cases of
    :func:`run_case` saved by ``--json``) and now, per class and overall.

    Parameters
    ----------
    before, after : list of dict
        :func:`run_case` results (the ``cases`` of two ``--json`` files).

    Returns
    -------
    str
        Markdown.
    """
    old = {r["case"]["seed"]: r for r in before}
    rows = [r for r in after if r["case"]["seed"] in old]
    groups: dict = {}
    for r in rows:
        groups.setdefault(_class_label(r), []).append(r)
    lines = ["| put in (evaluation half) | n | right before | right now | false alarms before | "
             "false alarms now |", "|---|---|---|---|---|---|"]

    def line(name, rs):
        n = len(rs)
        rb = sum(old[r["case"]["seed"]]["right"] for r in rs)
        ra = sum(r["right"] for r in rs)
        fb = sum(old[r["case"]["seed"]]["false_alarm"] for r in rs)
        fa = sum(r["false_alarm"] for r in rs)
        return f"| {name} | {n} | {rb}/{n} | {ra}/{n} | {fb} | {fa} |"
    order = ["clean"] + [c for c in CLASS_EFFECTS] + [c + " (outside)" for c in CLASS_OUTSIDE]
    for name in sorted(groups, key=lambda k: (order.index(k) if k in order else len(order), k)):
        lines.append(line(name, groups[name]))
    lines.append(line("all", rows))
    return "\n".join(lines) + "\n"


def by_round(befores: list[tuple[str, list[dict]]], after: list[dict]) -> str:
    """One table of every round: per class, the cases right with each code before (``befores``:
    label and :func:`run_case` results of the same seeds, oldest first) and now, one column
    each; a code before is scored on the seeds it holds (``right/held``: an evaluation half
    grown since it ran holds seeds it never saw), and the column head says how many it holds.

    Parameters
    ----------
    befores : list of (str, list of dict)
    after : list of dict

    Returns
    -------
    str
        Markdown.
    """
    olds = [(name, {r["case"]["seed"]: r for r in cases}) for name, cases in befores]
    groups: dict = {}
    for r in after:
        groups.setdefault(_class_label(r), []).append(r)
    heads = [f"`{name}` ({sum(r['case']['seed'] in old for r in after)})" for name, old in olds]
    lines = ["| put in (evaluation half) | n | " + " | ".join(heads) + " | now |",
             "|---|---|" + "---|" * (len(heads) + 1)]

    def line(name, rs):
        cells = []
        for _, old in olds:
            held = [old[r["case"]["seed"]] for r in rs if r["case"]["seed"] in old]
            cells.append(f"{sum(o['right'] for o in held)}/{len(held)}" if held else "-")
        return (f"| {name} | {len(rs)} | " + " | ".join(cells)
                + f" | {sum(r['right'] for r in rs)}/{len(rs)} |")
    order = ["clean"] + [c for c in CLASS_EFFECTS] + [c + " (outside)" for c in CLASS_OUTSIDE]
    for name in sorted(groups, key=lambda k: (order.index(k) if k in order else len(order), k)):
        lines.append(line(name, groups[name]))
    lines.append(line("all", after))
    return "\n".join(lines) + "\n"


def write_page(page: Path, text: str) -> None:
    """Replace the text between ``<!-- BEGIN evaluation -->`` and ``<!-- END evaluation -->``
    of ``page`` (atomically).

    Parameters
    ----------
    page : Path
    text : str

    Raises
    ------
    ValueError
        The page lacks the markers.
    """
    from ..files.atomic import atomic_write_text

    begin, end = "<!-- BEGIN evaluation -->", "<!-- END evaluation -->"
    doc = page.read_text()
    if begin not in doc or end not in doc:
        raise ValueError(f"{page}: no '{begin}' ... '{end}' markers to write between; add them "
                         "where the evaluation belongs")
    head, rest = doc.split(begin, 1)
    _, tail = rest.split(end, 1)
    atomic_write_text(page, head + begin + "\n\n" + text + "\n" + end + tail, overwrite=True)


def main(argv=None) -> int:
    """``python3 -m hsiffc.diagnose.evaluation`` (see the module docstring).

    Parameters
    ----------
    argv : list of str, optional

    Returns
    -------
    int
        Exit status.
    """
    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.diagnose.evaluation",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--half", choices=("dev", "eval", "all"), default="dev",
                    help="which half of the seeds (default dev: tune on dev, score eval)")
    ap.add_argument("--cases", type=int, default=480,
                    help="seeds 0 .. CASES-1 (default 480: 240 per half)")
    ap.add_argument("--classes", type=int, default=0,
                    help="also the first CLASSES seeds of the failure classes of issue 53 (from "
                         f"{CLASS_SEED0}; half of them in each half)")
    ap.add_argument("--classes2", type=int, default=0,
                    help="also the first CLASSES2 seeds of the linear-sensor stream (an exposure "
                         f"offset and a soft well compression, from {CLASS2_SEED0}; half of them "
                         "in each half)")
    ap.add_argument("--classes3", type=int, default=0,
                    help="also the first CLASSES3 seeds of the full-well stream (the linear "
                         "sensor whose well fills below the ADC's range, from "
                         f"{CLASS3_SEED0}; half of them in each half)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--json", type=Path, help="write every case and the summary here")
    ap.add_argument("--page", type=Path, help="write the tables into this Markdown page")
    ap.add_argument("--before", type=Path, action="append", default=[],
                    help="a --json file of the same seeds run with the code before: adds a "
                         "before/after table (may be given more than once: one table each)")
    ap.add_argument("--from-json", type=Path,
                    help="render the tables from the cases of this --json file instead of "
                         "running them again")
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[3] / "shared" / "data",
                    help="shared data sets (default ../shared/data next to the repository)")
    args = ap.parse_args(argv)
    if args.cases < 1:
        ap.error(f"--cases must be >= 1, got {args.cases}")
    t0 = time.time()
    done = []

    def progress(r):
        done.append(r)
        f = r["found"]
        print(f"[{len(done)}] seed {r['case']['seed']} {r['case']['design']:8s} "
              f"{_row_label(r):40s} -> {','.join(f['selected']) or 'nothing':40s} "
              f"unexplained={f['unexplained']} {'ok' if r['right'] else 'WRONG'} "
              f"({f['runtime_s']:.1f} s)", flush=True)
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        results = saved["cases"]
    else:
        results = run(seeds(args.half, args.cases, args.classes, args.classes2, args.classes3),
                      jobs=args.jobs, progress=progress)
    summary = summarise(results)
    shared = shared_rows(args.data) if args.page else []
    wall = time.time() - t0
    how = (f"Measured by `python3 -m hsiffc.diagnose.evaluation --half {args.half} --cases "
           f"{args.cases}{' --classes ' + str(args.classes) if args.classes else ''}"
           f"{' --classes2 ' + str(args.classes2) if args.classes2 else ''}"
           f"{' --classes3 ' + str(args.classes3) if args.classes3 else ''}"
           f"{' --jobs ' + str(args.jobs) if args.jobs > 1 else ''} --page "
           f"docs/diagnose.md` on {platform.machine()}, {platform.python_version()}: "
           f"{summary['n_cases']} sweeps of the {args.half} half ({SHAPE[0]} x {SHAPE[1]} px, "
           f"{MAX_PIXELS} analysed), {wall:.0f} s.")
    if args.from_json:
        how = (how.replace(f"{wall:.0f} s.", f"{summary['runtime_s']:.0f} s of diagnosis.")
               + f" Tables rendered from `{args.from_json.as_posix()}` (`--from-json`).")
    text = markdown(summary, shared, how)
    if len(args.before) > 1:
        befores = [(path.stem, json.loads(path.read_text())["cases"]) for path in args.before]
        text += ("\nRight, round by round (one column per `--before` file, oldest first, "
                 "scored on the seeds it holds: right/held; each file's note is under its table "
                 "below):\n\n" + by_round(befores, results))
    for path in args.before:
        before = json.loads(path.read_text())
        text += ("\nBefore and after, on the same seeds (before: "
                 f"`{path.as_posix()}`{'; ' + before['note'] if before.get('note') else ''}):"
                 "\n\n" + before_after(before["cases"], results))
    print(text)
    if args.json:
        from ..files.atomic import atomic_write_text
        atomic_write_text(args.json, json.dumps({"summary": summary, "shared": shared,
                                                 "cases": results}, indent=1, default=str)
                          + "\n", overwrite=True)
    if args.page:
        write_page(args.page, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
