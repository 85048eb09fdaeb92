"""Sensors built from physics the leakage model leaves out, for the FFC zoo.

hsiffc's simulator (:mod:`hsiffc.simulate`) shares the model's assumptions: the dark level is
the light response's intercept, and leakage is the only bend. A zoo made only from it cannot
show what the model gets wrong (``../shared/DESIGN.md``, "Measure on data you did not tune
on"). This module is a second, independent generator of EMVA 1288-style sweeps, written with
numpy alone: it imports nothing of hsiffc's simulator, model or leakage code (only
:class:`hsiffc.data.sweep.Sweep` and :class:`hsiffc.data.mosaic.Mosaic`, to hand the frames
over), and none of its sensors leaks.

The signal chain of one pixel, in order:

1. **Light.** The photo-electrons a frame collects have the mean
   ``k x level x r x (t + t0)``: ``level`` the relative light, ``t`` the nominal exposure,
   ``r`` the pixel's response (its mosaic band's responsivity, 0.5-1 of the brightest band,
   x a smooth fall-off of the light of 0-2 % at the corners, as EMVA 1288's uniform
   illumination allows, x 1 + PRNU of 0.3-1.5 %, normal).
2. **Exposure offset** ``t0`` (exposure sweeps only): the light is collected for the nominal
   exposure plus ``t0`` of either sign (0.02-0.15 ms on a sweep whose longest exposure is
   10-17 ms), as a mechanical or global shutter or a CCD's transfer does. The light response
   no longer starts at the dark level: it extrapolates to ``k x level x r x t0`` at ``t = 0``.
3. **Frame-transfer smear.** While a frame-transfer CCD shifts the frame to its store, every
   pixel passes under the whole of its column, lit: it gains the mean light of its column for
   the transfer time ``t_s`` (0.03-0.3 ms), independent of the exposure. A column pattern
   proportional to the column's light, constant down the column.
4. **Shot noise.** Poisson in electrons, converted to DN through the gain (DN per electron, a
   full well of 2 500-60 000 electrons at the top of the ADC's range).
5. **Readout nonlinearity common to all pixels.** The analog signal ``v`` (DN above the
   offset) becomes ``v (1 - c (v / FS)^p)``: ``c`` = 1-4 % compression at full scale ``FS``,
   ``p`` = 2 (cubic) or 4 (a late, soft knee). Every pixel shares it; on light sweeps and
   exposure sweeps.
6. **Offset.** A dark level (1-4 % of full scale; 100-500 DN on the CCD-like sensors) with a
   per-pixel spread (DSNU, normal).
7. **Dark signal outside the photodiode.** Dark current collected in a node the light does not
   reach (the sense node, the CCD's store): it adds to the response *after* the compression
   and does not leak. Its rate per pixel is log-normal (spread 0.3-0.8 in log), its mean sets
   0.5-3 % of full scale at the longest exposure; Poisson in electrons.
8. **Read noise** (3-15 electrons, normal; 5-30 on the CCD-like sensors), **quantisation**
   to the bit depth (8, 10, 12 or 14) and **clipping**: at the ADC's full scale, or at one
   code 85-95 % of it (the analog chain's limit, as the EMVA 1288 reference simulator and
   hsiffc's zoo do).

Each seed's sensor (:func:`indep_case`) has a primary effect that cycles with the seed
(:data:`PRIMARY_EFFECTS`: an exposure offset, smear, a dark signal outside the photodiode, a
common nonlinearity, a CCD-like linear sensor with a large dark level), secondary effects
drawn with probability 0.3 each, a bit depth, noise, a mosaic (none on 3 in 5, else 4 x 4 or
5 x 5) and a design: an exposure sweep (one light) or a light sweep (one exposure), 30-40
light steps of 2 or 4 frames from about 2 % of saturation to past it, each with as many dark
frames at its exposure (EMVA 1288), and on half the cases a flat stack of 20-50 frames near
half saturation with a dark stack at its exposure. The seeds split into a development half
(:data:`INDEP_DEV_SEEDS`: tune on these) and an evaluation half (:data:`INDEP_EVAL_SEEDS`:
publish these); both cover every primary effect, both frame counts, with and without stacks.
Two sensors of fixed design (:data:`DESIGN_CASES`) reproduce the designs of the sensors issue
50 judges by, for both halves.

>>> case = indep_case(2003)
>>> case.primary
'common readout nonlinearity'
>>> indep_case(2003) == case                     # one seed, one sensor
True

:func:`rule_table` runs the held-out FFC study (:func:`hsiffc.reports.ffc_study.run_ffc_study`)
on a half and returns each sensor's rule verdict and figures::

    python3 -m hsiffc.reports.indep_sensors [--half dev|eval] [--seeds N]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, replace

import numpy as np

from ..data.mosaic import Mosaic
from ..data.sweep import Sweep

__all__ = ["IndepCase", "indep_case", "indep_sweep", "rule_table", "render_rule_table",
           "PRIMARY_EFFECTS", "INDEP_DEV_SEEDS", "INDEP_EVAL_SEEDS", "DESIGN_CASES", "main"]

#: the primary effect of seed ``s`` is ``PRIMARY_EFFECTS[s % 5]``
PRIMARY_EFFECTS = ("exposure offset", "frame-transfer smear",
                   "dark signal outside the photodiode", "common readout nonlinearity",
                   "CCD-like linear, large dark level")
#: seeds of the independent sensors: tune on the development half, publish the evaluation half
INDEP_DEV_SEEDS = tuple(range(2000, 2016))
INDEP_EVAL_SEEDS = tuple(range(3000, 3016))
#: full well in electrons at the top of the ADC's range, per bit depth (x 0.5-1.5 per sensor)
_FULL_WELL_E = {8: 5000.0, 10: 10000.0, 12: 20000.0, 14: 40000.0}
#: light steps from this fraction of saturation to past it
_STEP_FRACTIONS = (0.02, 1.15)
_SECONDARY_PROBABILITY = 0.3


@dataclass(frozen=True)
class IndepCase:
    """One independent sensor and its sweep design (see :func:`indep_case`; the module
    docstring gives the physics of every field).

    Parameters
    ----------
    seed : int
    primary : str
        The primary effect, one of :data:`PRIMARY_EFFECTS`.
    bit_depth : int
    light_sweep : bool
        True: a light sweep at one exposure; False: an exposure sweep at one light.
    frames_per_step : int
        Light frames per step, and dark frames per step (2 or 4).
    stack_frames : int
        Frames of the flat stack and of its dark stack; 0: no stacks.
    n_steps : int
        Light steps of the sweep (each with a dark step at its exposure).
    exposure_ms : float
        The nominal exposure at which the brightest pixels reach the clip (exposure sweeps), or
        the one exposure of a light sweep.
    exposure_offset_ms : float
        ``t0``: the light is collected for the nominal exposure + ``t0``.
    smear_ms : float
        Frame-transfer time: each pixel gains its column's mean light for this long.
    outside_dark_dn : float
        Mean dark signal collected outside the photodiode at the longest exposure (DN).
    outside_dark_spread : float
        Its per-pixel log-normal spread (standard deviation of the log).
    nonlinearity : float
        Common readout compression at full scale (fraction).
    nonlinearity_power : int
        2: cubic; 4: a late, soft knee.
    dark_level_dn, dsnu_dn : float
        Offset and its per-pixel spread (DN).
    read_noise_e : float
        Read noise in electrons.
    full_well_e : float
        Electrons at the top of the ADC's range (sets the gain).
    prnu : float
        Photo-response non-uniformity (fraction).
    clip_fraction : float
        Clip code as a fraction of full scale (1: the ADC's full scale).
    mosaic_tile : int
        0: no mosaic; 4 or 5: a 4 x 4 or 5 x 5 mosaic.
    shape : tuple
        Frame shape (H, W).
    design : str
        The name of a fixed design (:data:`DESIGN_CASES`); "" for a seed's sensor.
    """

    seed: int
    primary: str
    bit_depth: int
    light_sweep: bool
    frames_per_step: int
    stack_frames: int
    n_steps: int
    exposure_ms: float
    exposure_offset_ms: float = 0.0
    smear_ms: float = 0.0
    outside_dark_dn: float = 0.0
    outside_dark_spread: float = 0.5
    nonlinearity: float = 0.0
    nonlinearity_power: int = 2
    dark_level_dn: float = 10.0
    dsnu_dn: float = 0.5
    read_noise_e: float = 5.0
    full_well_e: float = 10000.0
    prnu: float = 0.008
    clip_fraction: float = 1.0
    mosaic_tile: int = 0
    shape: tuple = (96, 128)
    design: str = ""

    @property
    def full_scale_dn(self) -> int:
        """The ADC's full scale ``2**bit_depth - 1`` (DN)."""
        return 2 ** self.bit_depth - 1

    @property
    def clip_code_dn(self) -> int:
        """The code every pixel clips at (the full scale, or a full well below it)."""
        return int(round(min(self.clip_fraction, 1.0) * self.full_scale_dn))

    @property
    def gain_dn_per_e(self) -> float:
        """DN per electron: the full well fills the range from the offset to the clip."""
        return (self.clip_code_dn - self.dark_level_dn) / self.full_well_e

    @property
    def effects(self) -> list[str]:
        """Every effect of the sensor outside the leakage model, described with its size."""
        shape = "cubic" if self.nonlinearity_power == 2 else "soft knee"
        sizes = {
            PRIMARY_EFFECTS[4]: self.primary == PRIMARY_EFFECTS[4]
            and f"CCD-like linear, dark level {self.dark_level_dn:.0f} DN (spread "
                f"{self.dsnu_dn:.1f} DN)",
            PRIMARY_EFFECTS[0]: self.exposure_offset_ms
            and f"exposure offset {self.exposure_offset_ms:+.3f} ms",
            PRIMARY_EFFECTS[1]: self.smear_ms and f"frame-transfer smear {self.smear_ms:.2f} ms",
            PRIMARY_EFFECTS[2]: self.outside_dark_dn
            and f"dark signal outside the photodiode {self.outside_dark_dn:.1f} DN at the "
                "longest exposure",
            PRIMARY_EFFECTS[3]: self.nonlinearity
            and f"common readout nonlinearity ({shape}, {100 * self.nonlinearity:.1f} % at "
                "full scale)"}
        order = [self.primary] + [e for e in sizes if e != self.primary]
        return [sizes[e] for e in order if sizes[e]]

    @property
    def label(self) -> str:
        """Short description: ``independent, seed 2003: common readout nonlinearity (...),
        10-bit, light sweep at one exposure, ...``."""
        parts = self.effects + [
            f"{self.bit_depth}-bit", f"PRNU {100 * self.prnu:.2g} %",
            "clips at full scale" if self.clip_fraction >= 1 else
            f"clips at {100 * self.clip_fraction:.0f} % of full scale",
            "light sweep at one exposure" if self.light_sweep else "exposure sweep",
            f"{self.frames_per_step} frames per step",
            f"{self.stack_frames}-frame flat stack" if self.stack_frames else "no flat stack"]
        if self.mosaic_tile:
            parts.append(f"{self.mosaic_tile}x{self.mosaic_tile} mosaic")
        which = f"design {self.design}" if self.design else f"seed {self.seed}"
        return f"independent, {which}: " + ", ".join(parts)


#: fixed designs of the two sensors issue 50 judges by (not in ``../shared``), rows of the zoo
#: in both halves: a 12-bit CCD's exposure sweep at one light with a 0.02 ms exposure offset,
#: a flat dark of 14.8 DN (spread 0.3 DN), 50-frame flat and dark stacks; and the EMVA 1288
#: reference simulation's 12-bit light sweep at one exposure with a 2 % common (cubic)
#: nonlinearity and a 100-frame stack. Neither leaks.
DESIGN_CASES = {
    "ccd12-exposure-offset": IndepCase(
        seed=50, primary=PRIMARY_EFFECTS[4], bit_depth=12, light_sweep=False,
        frames_per_step=2, stack_frames=50, n_steps=40, exposure_ms=12.2,
        exposure_offset_ms=0.02, dark_level_dn=14.8, dsnu_dn=0.3, read_noise_e=30.0,
        full_well_e=40800.0, prnu=0.0025, design="ccd12-exposure-offset"),
    "refsim12-light-nonlinear": IndepCase(
        seed=51, primary=PRIMARY_EFFECTS[3], bit_depth=12, light_sweep=True,
        frames_per_step=2, stack_frames=100, n_steps=40, exposure_ms=10.0, nonlinearity=0.02,
        nonlinearity_power=2, dark_level_dn=40.0, dsnu_dn=1.0, read_noise_e=10.0,
        full_well_e=40000.0, prnu=0.0075, design="refsim12-light-nonlinear")}


def _draw_effect(effect: str, rng, case: dict, sign: float = 0.0) -> None:
    """Set the fields of ``effect`` in ``case`` to a drawn size (``sign`` of an offset: drawn
    when 0)."""
    if effect == PRIMARY_EFFECTS[0]:
        sign = sign or float(rng.choice([-1.0, 1.0]))
        case["exposure_offset_ms"] = round(sign * float(rng.uniform(0.02, 0.15)), 4)
    elif effect == PRIMARY_EFFECTS[1]:
        case["smear_ms"] = round(float(rng.uniform(0.03, 0.3)), 3)
    elif effect == PRIMARY_EFFECTS[2]:
        fs = 2 ** case["bit_depth"] - 1
        case["outside_dark_dn"] = round(float(rng.uniform(0.005, 0.03)) * fs, 2)
        case["outside_dark_spread"] = round(float(rng.uniform(0.3, 0.8)), 2)
    elif effect == PRIMARY_EFFECTS[3]:
        case["nonlinearity"] = round(float(rng.uniform(0.01, 0.04)), 4)
        case["nonlinearity_power"] = int(rng.choice([2, 4]))


def indep_case(seed: int, *, shape: tuple = (96, 128)) -> IndepCase:
    """The independent sensor of one seed.

    The index ``i = seed % 1000`` cycles the design, so that every 16 consecutive seeds (a
    half) hold every primary effect (``i % 5``), 2 and 4 frames per step (``i % 2``), with and
    without a flat stack (``(i // 2) % 2``), exposure offsets of both signs and the common
    nonlinearity on both kinds of sweep (``(i // 5) % 2``); the rest is drawn from the seed.

    Parameters
    ----------
    seed : int
    shape : tuple
        Frame shape (H, W).

    Returns
    -------
    IndepCase
    """
    i = int(seed) % 1000
    rng = np.random.default_rng([50, int(seed)])
    primary = PRIMARY_EFFECTS[i % 5]
    alternate = (i // 5) % 2 == 0
    ccd = primary == PRIMARY_EFFECTS[4]
    if primary == PRIMARY_EFFECTS[0]:
        light_sweep = False  # an offset shows on exposure sweeps only
    elif primary == PRIMARY_EFFECTS[3]:
        light_sweep = alternate
    else:
        light_sweep = bool(rng.random() < (0.2 if ccd else 0.3))
    bits = int(rng.choice([12, 14])) if ccd else int(rng.choice([8, 10, 12, 14]))
    fs = 2 ** bits - 1
    case = dict(
        seed=int(seed), primary=primary, bit_depth=bits, light_sweep=light_sweep,
        frames_per_step=(2, 4)[i % 2],
        stack_frames=int(rng.integers(20, 51)) if (i // 2) % 2 == 0 else 0,
        n_steps=int(rng.integers(30, 41)),
        exposure_ms=round(float(rng.uniform(2.0, 20.0) if light_sweep
                                else rng.uniform(10.0, 15.0)), 2),
        dark_level_dn=round(float(rng.uniform(100.0, 500.0) if ccd
                                  else max(2.0, rng.uniform(0.01, 0.04) * fs)), 1),
        dsnu_dn=round(float(rng.uniform(0.5, 3.0) if ccd
                            else max(0.3, rng.uniform(0.001, 0.003) * fs)), 2),
        read_noise_e=round(float(rng.uniform(5.0, 30.0) if ccd else rng.uniform(3.0, 15.0)), 1),
        full_well_e=round(_FULL_WELL_E[bits] * float(rng.uniform(0.5, 1.5)), -1),
        prnu=round(float(rng.uniform(0.003, 0.015)), 4),
        clip_fraction=(1.0 if rng.random() < 0.5 else round(float(rng.uniform(0.85, 0.95)), 3)),
        mosaic_tile=int(rng.choice([0, 0, 0, 4, 5])), shape=tuple(shape))
    _draw_effect(primary, rng, case, sign=1.0 if alternate else -1.0)
    # secondary effects: a CCD-like sensor stays linear (offset and smear only)
    secondary = PRIMARY_EFFECTS[:2] if ccd else PRIMARY_EFFECTS[:4]
    for effect in secondary:
        drawn = rng.random() < _SECONDARY_PROBABILITY
        if drawn and effect != primary and not (effect == PRIMARY_EFFECTS[0] and light_sweep):
            _draw_effect(effect, rng, case)
    return IndepCase(**case)


def _compress(v, case: IndepCase):
    """The common readout nonlinearity: ``v (1 - c (v / FS)^p)`` (DN above the offset)."""
    if not case.nonlinearity:
        return v
    x = np.minimum(v / case.full_scale_dn, 1.5)
    return v * (1.0 - case.nonlinearity * x ** case.nonlinearity_power)


def _response_map(case: IndepCase, rng) -> np.ndarray:
    """Each pixel's relative response: band responsivity x fall-off x (1 + PRNU)."""
    h, w = case.shape
    band = np.ones(case.shape)
    if case.mosaic_tile:
        bands = Mosaic.square(case.mosaic_tile).band_map(case.shape)
        band = rng.uniform(0.5, 1.0, case.mosaic_tile ** 2)[bands]
        band /= band.max()
    y, x = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    falloff = 1.0 - rng.uniform(0.0, 0.02) * (x ** 2 + y ** 2) / 2.0
    return band * falloff * (1.0 + case.prnu * rng.standard_normal(case.shape))


def _light_scale(case: IndepCase, response, t_eff: float) -> float:
    """Electrons per ms per unit light that bring the brightest pixels (99th percentile of the
    response) to the clip at ``t_eff`` (ms), the compression included."""
    headroom = case.clip_code_dn - case.dark_level_dn
    v = headroom
    for _ in range(20):  # solve v (1 - c (v/FS)^p) = headroom
        v = headroom * v / float(_compress(np.asarray(v, float), case))
    return v / (case.gain_dn_per_e * float(np.percentile(response, 99)) * t_eff)


def indep_sweep(case: IndepCase) -> Sweep:
    """An EMVA 1288-style sweep of the case's sensor.

    ``case.n_steps`` light steps of ``case.frames_per_step`` frames from about 2 % of
    saturation to past it (saturation of the brightest pixels, the 99th percentile of the
    response: on a mosaic the dimmer bands stay below the clip), each followed by as many dark frames at its exposure; then, with
    ``case.stack_frames``, a flat stack near half saturation and a dark stack at its exposure
    (``meta["spatial_steps"]``; the others in ``meta["sweep_steps"]``). ``photons`` of a light
    frame is its relative light dose, light level x nominal exposure (EMVA 1288's photons per
    pixel up to a constant); darks have NaN.

    Parameters
    ----------
    case : IndepCase

    Returns
    -------
    Sweep
        Frames as uint16, ``source`` = the case's label, ``meta["indep_case"]`` its fields.
    """
    pattern_rng = np.random.default_rng([50, case.seed, 0])
    response = _response_map(case, pattern_rng)
    offset = case.dark_level_dn + case.dsnu_dn * pattern_rng.standard_normal(case.shape)
    s = case.outside_dark_spread
    outside_rate = pattern_rng.lognormal(-s * s / 2.0, s, case.shape)  # mean 1
    rng = np.random.default_rng([50, case.seed, 1])
    g = case.gain_dn_per_e
    t_top = case.exposure_ms
    t_max = t_top * _STEP_FRACTIONS[1] + abs(case.exposure_offset_ms)
    k = _light_scale(case, response, t_top)
    column_light = response.mean(axis=0, keepdims=True)

    def frames(t: float, level: float, n: int) -> np.ndarray:
        """``n`` frames of nominal exposure ``t`` (ms) at relative light ``level``."""
        v = np.zeros((n,) + case.shape)
        if level > 0:
            mean_e = k * level * (response * max(t + case.exposure_offset_ms, 0.0)
                                  + column_light * case.smear_ms)
            v = _compress(rng.poisson(np.broadcast_to(mean_e, v.shape)) * g, case)
        if case.outside_dark_dn:
            dark_e = case.outside_dark_dn / g * outside_rate * t / t_max
            v = v + rng.poisson(np.broadcast_to(dark_e, v.shape)) * g
        v = v + offset + rng.normal(0.0, case.read_noise_e * g, v.shape)
        return np.clip(np.round(v), 0, case.clip_code_dn).astype(np.uint16)

    def nominal(fraction: float) -> tuple[float, float]:
        """(exposure, level) of a step at ``fraction`` of saturation."""
        if case.light_sweep:
            return t_top, fraction
        return fraction * t_top - case.exposure_offset_ms, 1.0

    blocks, exposure, kind, photons = [], [], [], []

    def add(t: float, level: float, n: int) -> None:
        for what, lvl in (("light", level), ("dark", 0.0)):
            blocks.append(frames(t, lvl, n))
            exposure.extend([t] * n)
            kind.extend([what] * n)
            photons.extend([lvl * t if lvl else np.nan] * n)

    for fraction in np.linspace(*_STEP_FRACTIONS, case.n_steps):
        add(*nominal(float(fraction)), case.frames_per_step)
    n_sweep = 2 * case.n_steps
    if case.stack_frames:
        add(*nominal(0.5), case.stack_frames)
    counts = [len(b) for b in blocks]
    steps = np.repeat(np.arange(len(blocks)), counts)
    return Sweep(np.concatenate(blocks), exposure, kind, case.bit_depth, step=steps,
                 photons=photons, illumination=np.where(np.array(kind) == "light", "lamp", ""),
                 mosaic=Mosaic.square(case.mosaic_tile) if case.mosaic_tile else None,
                 source=case.label,
                 meta={"sweep_steps": list(range(n_sweep)),
                       "spatial_steps": list(range(n_sweep, len(blocks))),
                       "indep_case": {f: getattr(case, f) for f in case.__dataclass_fields__}})


def rule_table(half: str = "dev", *, seeds=None, designs: bool = True,
               shape: tuple | None = None, progress=None) -> list[dict]:
    """The FFC rule on the independent sensors of one half: one dict per sensor.

    Runs :func:`hsiffc.reports.ffc_study.run_ffc_study` on every sensor (calibrated on the
    even steps, measured on the odd ones) and reports the rule of
    :func:`hsiffc.reports.ffc_study.check_rule`.

    Parameters
    ----------
    half : {"dev", "eval"}
        :data:`INDEP_DEV_SEEDS` or :data:`INDEP_EVAL_SEEDS`.
    seeds : sequence of int, optional
        These seeds instead of the half's.
    designs : bool
        Also the fixed designs of :data:`DESIGN_CASES` (after the seeds).
    shape : tuple, optional
        A frame shape other than the default (smaller: quicker).
    progress : callable, optional
        Called with ``(label, seconds)`` after each sensor.

    Returns
    -------
    list of dict
        ``seed``, ``design``, ``label``, ``met`` (no failure), ``goals`` (failures and
        unresolved ranges as listed by ``check_rule``), ``ranges``: per range label, the
        ``cell`` of every method (median ± standard error), and ``study``: the
        :class:`FFCStudy`.
    """
    import time

    from .ffc_study import cell, range_label, run_ffc_study

    if seeds is None:
        seeds = INDEP_DEV_SEEDS if half == "dev" else INDEP_EVAL_SEEDS
    cases = [indep_case(s) for s in seeds] + (list(DESIGN_CASES.values()) if designs else [])
    rows = []
    for case in cases:
        case = case if shape is None else replace(case, shape=tuple(shape))
        t0 = time.perf_counter()
        res = run_ffc_study(indep_sweep(case))
        rows.append({"seed": case.seed, "design": case.design, "label": case.label,
                     "met": not res.goals["failures"], "goals": res.goals, "study": res,
                     "ranges": {range_label(r): {m: cell(v, se=True)
                                                 for m, v in r["methods"].items()}
                                for r in res.summary}})
        if progress:
            progress(case.label, time.perf_counter() - t0)
    return rows


def render_rule_table(rows) -> str:
    """:func:`rule_table`'s rows as Markdown: the verdict, then raw, stack two-point and
    model_ffc per range of saturation."""
    methods = ("raw", "two_point_stack", "model_ffc")
    lines = []
    for row in rows:
        g = row["goals"]
        verdict = "met" if row["met"] else "broken: " + "; ".join(g["failures"])
        if g.get("unresolved"):
            verdict += " (unresolved: " + "; ".join(g["unresolved"]) + ")"
        lines += [f"### {row['label']}", "", f"Rule: {verdict}", "",
                  "| range | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
        for rng, cells in row["ranges"].items():
            lines.append(f"| {rng} | " + " | ".join(cells.get(m, "-") for m in methods) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Command line: print the rule table of a half of the independent sensors."""
    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.reports.indep_sensors",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--half", choices=("dev", "eval"), default="dev")
    ap.add_argument("--seeds", type=int, default=None,
                    help="only the first N seeds of the half (a quick look)")
    args = ap.parse_args(argv)
    seeds = INDEP_DEV_SEEDS if args.half == "dev" else INDEP_EVAL_SEEDS
    rows = rule_table(args.half, seeds=seeds[:args.seeds] if args.seeds else seeds,
                      progress=lambda n, s: print(f"{n}: {s:.1f} s", file=sys.stderr,
                                                  flush=True))
    print(render_rule_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
