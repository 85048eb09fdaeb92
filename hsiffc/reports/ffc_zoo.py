"""A zoo of sensors for the flat-field correction: does model_ffc hold on every one of them?

The FFC study (:mod:`hsiffc.reports.ffc_study`) runs on any EMVA 1288-style sweep. The zoo runs
it on

* every EMVA 1288 set in ``../shared/data`` (the real 8-bit CMOS, the two sets of the
  EMVA 1288 reference implementation's simulator, and the two sets of an independent
  generator with an exposure offset and a common nonlinearity), each its own row,
* a seeded grid of hsiffc's simulated sensors (:func:`zoo_case`): linear or strongly leaking,
  8/10/12/16 bit, read noise 0.5-5 DN, with or without dark current, full well at or below the
  ADC's full scale, exposure or light sweeps. Seeds split the grid into a development half
  (:data:`DEV_SEEDS`: tune on these) and an evaluation half (:data:`EVAL_SEEDS`: publish these),
  and
* independent sensors (:mod:`hsiffc.reports.indep_sensors`), generated with numpy alone, not with
  hsiffc's simulator, from physics the leakage model leaves out: exposure offsets of either
  sign, frame-transfer smear, a dark signal outside the photodiode, a readout nonlinearity
  common to all pixels, CCD-like linear sensors with a large dark level; 2 or 4 frames per
  step, with or without a flat stack. The simulator shares the model's assumptions (a dark
  level equal to the light response's intercept, leakage as the only bend), so it cannot show
  what the model gets wrong; these sensors can. Their seeds split into halves too
  (:data:`~hsiffc.reports.indep_sensors.INDEP_DEV_SEEDS`,
  :data:`~hsiffc.reports.indep_sensors.INDEP_EVAL_SEEDS`); ``--half`` picks both grids' half.
  Two independent sensors of fixed design, rows in both halves
  (:data:`~hsiffc.reports.indep_sensors.DESIGN_CASES`), have the designs of the two sensors
  issue 50 judges by: a 12-bit CCD's exposure sweep with an exposure offset and 50-frame
  stacks, and a 12-bit light sweep with a 2 % common nonlinearity.

Every sensor gets one table (raw, 2-frame and stack two-point, model_ffc, per range of
saturation) and the rule of :func:`hsiffc.reports.ffc_study.check_rule`; the page's summary
gives each shared set its own row and the simulated and the independent sensors one row each
(the median over the group's sensors).

    python3 -m hsiffc.reports.ffc_zoo OUTDIR [--half eval|dev] [--shared ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..simulate import MosaicSensor
from ..simulate.params import SensorParams
from ..data.sweep import Sweep
from .ffc_study import (RANGES_FRACTION, FFCStudy, cell, method_names, range_label,
                        run_ffc_study)
from .indep_sensors import DESIGN_CASES, INDEP_DEV_SEEDS, INDEP_EVAL_SEEDS, indep_case, indep_sweep

__all__ = ["RANGES_FRACTION", "ZooCase", "zoo_case", "zoo_sweep", "run_zoo", "render_zoo",
           "zoo_json", "DEV_SEEDS", "EVAL_SEEDS", "SHARED_SETS", "GROUPS", "HALF_NAMES",
           "sensor_group", "range_figures", "median_figures", "format_figures", "rule_verdict",
           "main"]

log = logging.getLogger(__name__)

#: seeds of the simulated grid: tune on DEV_SEEDS, publish EVAL_SEEDS (each covers the grid)
DEV_SEEDS = tuple(range(0, 16))
EVAL_SEEDS = tuple(range(1000, 1016))
#: the shared EMVA 1288 sets and a sensor-specific goal (percent from 12 % of saturation up)
SHARED_SETS = {"emva1288-cmos8-roi": 0.3, "emva1288-refsim-linear12-exposure": None,
               "emva1288-refsim-linear10-light": None, "indep-ccd12-offset": None,
               "indep-cmos10-light-nonlinear": None}
BIT_DEPTHS = (8, 10, 12, 16)
#: the zoo's groups of seeded sensors, each one summary row (their labels start with the name)
GROUPS = ("simulated", "independent")
#: the halves as the pages name them
HALF_NAMES = {"eval": "evaluation", "dev": "development"}


@dataclass(frozen=True)
class ZooCase:
    """One simulated sensor and its sweep design (see :func:`zoo_case`)."""

    seed: int
    bit_depth: int
    leaky: bool
    read_noise_dn: float
    dark_current_dn_per_ms: float
    full_well_below_full_scale: bool
    light_sweep: bool
    prnu: float
    shape: tuple = (96, 128)

    @property
    def label(self) -> str:
        """Short description: ``sim 1003: 16-bit, leaky, read 2.3 DN, ...``."""
        parts = [f"{self.bit_depth}-bit", "strong leakage" if self.leaky else "linear",
                 f"read noise {self.read_noise_dn:.1f} DN",
                 f"dark current {self.dark_current_dn_per_ms:g} DN/ms"
                 if self.dark_current_dn_per_ms else "no dark current",
                 "full well below full scale" if self.full_well_below_full_scale
                 else "clips at full scale",
                 "light sweep at one exposure" if self.light_sweep else "exposure sweep"]
        return f"simulated, seed {self.seed}: " + ", ".join(parts)


def zoo_case(seed: int) -> ZooCase:
    """The sensor of one seed: bit depth and leakage cycle through the grid with the seed
    (every 8 consecutive seeds cover 8/10/12/16 bit, linear and leaky), the rest is drawn."""
    rng = np.random.default_rng([36, int(seed)])
    return ZooCase(seed=int(seed), bit_depth=BIT_DEPTHS[seed % 4], leaky=bool((seed // 4) % 2),
                   read_noise_dn=float(np.round(rng.uniform(0.5, 5.0), 2)),
                   dark_current_dn_per_ms=float(rng.choice([0.0, 0.0, 0.02, 0.1])),
                   full_well_below_full_scale=bool(rng.random() < 0.5),
                   light_sweep=bool(rng.random() < 0.3),
                   prnu=float(np.round(rng.uniform(0.004, 0.015), 4)))


def _sensor(case: ZooCase) -> MosaicSensor:
    fs = 2 ** case.bit_depth - 1
    scale = fs / 1023.0  # the default sensor is 10-bit: keep its shape at any depth
    well_dn = 1.3 * fs  # the analog chain clips first (see zoo_sweep), as in EMVA's simulator
    gain = 0.075 * scale * (1.0 if case.bit_depth < 16 else 0.5)  # DN per electron
    params = replace(
        SensorParams(), bit_depth=case.bit_depth, conversion_gain_dn_per_e=gain,
        full_well_e=well_dn / gain, read_noise_dn=case.read_noise_dn,
        dark_level_dn=max(2.0, 0.03 * fs), dsnu_dn=max(0.5, 0.002 * fs), prnu=case.prnu,
        dark_current_dn_per_ms=case.dark_current_dn_per_ms * scale,
        leak_b_per_dn=0.0125 / scale, leak_ref_dn=800.0 * scale,
        leak_rate_dn_per_ms=(2.0 * scale if case.leaky else 0.0))
    return MosaicSensor(case.shape, params=params, seed=case.seed)


def zoo_sweep(case: ZooCase, *, n_steps: int = 32, stack_frames: int = 16) -> Sweep:
    """An EMVA 1288-style sweep of the case's sensor: ``n_steps`` light steps of 2 frames from
    about 2 % to past saturation, each with 2 dark frames at its exposure, then a flat stack
    near half saturation and a dark stack at its exposure (``meta["spatial_steps"]``).

    An exposure sweep changes the exposure at one light; a light sweep changes the light at one
    exposure (``photons`` relative: proportional to light rate x exposure, as EMVA 1288)."""
    sensor = _sensor(case)
    p = sensor.params
    fs = p.full_scale_dn
    # full well below full scale: every pixel clips at one code below the ADC's full scale
    # (the analog chain's limit, as the EMVA 1288 reference simulator does)
    clip = int(round(0.92 * fs)) if case.full_well_below_full_scale else fs
    top = clip - p.dark_level_dn
    illum = sensor.illumination("lamp A", 1.0)
    k1 = float(np.median(sensor.light_rate(illum)))  # DN/ms per W/m^2
    t_top = 100.0  # ms: the longest exposure of an exposure sweep, the light sweep's exposure
    if case.leaky:  # leakage bends the response: the top needs more light than linear
        top *= 1.25
    irr_top = top / (k1 * t_top)
    frac = np.linspace(0.02, 1.08, n_steps)
    rng = np.random.default_rng([36, case.seed, 1])
    frames, exp, kind, photons, steps, illum_lab = [], [], [], [], [], []

    def add(data, t, k, ph, lab):
        steps.extend([_next(steps)] * len(data))
        frames.append(data)
        exp.extend([t] * len(data))
        kind.extend([k] * len(data))
        photons.extend([ph] * len(data))
        illum_lab.extend([lab] * len(data))

    def capture(t, level, n):
        seed = int(rng.integers(2 ** 63))
        if level <= 0:
            return np.minimum(sensor.capture(t, None, n_frames=n, seed=seed).frames, clip)
        return np.minimum(sensor.capture(t, "lamp A", irradiance_w_m2=irr_top * level,
                                         n_frames=n, seed=seed, label="lamp A").frames, clip)

    for f in frac:
        t, level = (t_top, f) if case.light_sweep else (t_top * f, 1.0)
        add(capture(t, level, 2), t, "light", level * t, "lamp A")
        add(capture(t, 0, 2), t, "dark", np.nan, "")
    n_sweep = len(set(steps))
    t, level = (t_top, 0.5) if case.light_sweep else (t_top * 0.5, 1.0)
    add(capture(t, level, stack_frames), t, "light", level * t, "lamp A")
    add(capture(t, 0, stack_frames), t, "dark", np.nan, "")
    return Sweep(np.concatenate(frames), exp, kind, p.bit_depth, step=steps, photons=photons,
                 illumination=illum_lab, mosaic=sensor.mosaic, source=case.label,
                 meta={"sweep_steps": list(range(n_sweep)),
                       "spatial_steps": [n_sweep, n_sweep + 1]})


def _next(steps) -> int:
    return (steps[-1] + 1) if steps else 0


def run_zoo(*, seeds=EVAL_SEEDS, indep_seeds=INDEP_EVAL_SEEDS, designs=tuple(DESIGN_CASES),
            shared: Path | None = None, progress=None) -> list:
    """The study on every shared set found under ``shared``, every simulated seed, every
    independent seed and every independent design.

    Parameters
    ----------
    seeds : sequence of int
        Seeds of hsiffc's simulated sensors (:func:`zoo_case`).
    indep_seeds : sequence of int
        Seeds of the independent sensors (:func:`hsiffc.reports.indep_sensors.indep_case`).
    designs : sequence of str
        Names of the independent sensors of fixed design
        (:data:`hsiffc.reports.indep_sensors.DESIGN_CASES`; in both halves).
    shared : Path, optional
        Folder of the shared EMVA 1288 sets; a set that is missing is left out (with a log
        line).
    progress : callable, optional
        Called with ``(name, seconds)`` after each sensor.

    Returns
    -------
    list
        ``(name, FFCStudy)`` per sensor: the shared sets, the simulated, the independent.
    """
    sources = []
    if shared is not None:
        for name, goal in SHARED_SETS.items():
            folder = Path(shared) / name
            if folder.exists():
                sources.append((name, folder, goal))
            else:
                log.warning("%s not found: left out of the zoo", folder)
    sources += [(c.label, lambda c=c: zoo_sweep(c), None) for c in map(zoo_case, seeds)]
    sources += [(c.label, lambda c=c: indep_sweep(c), None)
                for c in [indep_case(s) for s in indep_seeds] + [DESIGN_CASES[d] for d in designs]]
    out = []
    for name, source, goal in sources:
        t0 = time.perf_counter()
        out.append((name, run_ffc_study(source() if callable(source) else source,
                                        goal_percent=goal)))
        if progress:
            progress(name, time.perf_counter() - t0)
    return out


def sensor_group(name: str) -> str:
    """The group of a zoo sensor: one of :data:`GROUPS`, or ``"shared"`` (a shared set)."""
    return next((g for g in GROUPS if name.startswith(g)), "shared")


def rule_verdict(res: FFCStudy) -> str:
    """The rule on one sensor as a table cell: ``**met**`` (with the ranges where model_ffc is
    higher within twice the standard error) or ``**broken**: `` and the failures."""
    g = res.goals
    ok = g["model_at_most_raw"] and g["model_within_10_percent_of_stack_two_point"] and all(
        v for k, v in g.items() if k.startswith("model_at_most_") and isinstance(v, bool))
    if not ok:
        return "**broken**: " + "; ".join(g["failures"])
    unresolved = sorted({u.split(":")[0] for u in g.get("unresolved", [])},
                        key=lambda x: float(x.split()[0]))
    return "**met**" + (f" (not resolved at {', '.join(unresolved)}: model_ffc higher within "
                        "twice the standard error)" if unresolved else "")


def range_figures(summary, method: str) -> list:
    """Per row of a study's summary: the median percent of ``method``, ``"below noise"``, or
    None where the method is not in the row."""
    out = []
    for row in summary:
        m = row["methods"].get(method)
        out.append(None if m is None else ("below noise" if m.get("below_noise") else
                                           m["fpn_percent_median"]))
    return out


def median_figures(summaries, method: str) -> list:
    """Per range: the median over the sensors' :func:`range_figures` that are numbers (None
    where no sensor has one); ``summaries``: one summary (list of rows) per sensor."""
    cols = [[v for v in c if isinstance(v, float)]
            for c in zip(*[range_figures(s, method) for s in summaries])]
    return [float(np.median(c)) if c else None for c in cols]


def format_figures(values) -> str:
    """``0.31 / below noise / - %``: figures of the ranges in one cell."""
    return " / ".join("-" if v is None else v if isinstance(v, str) else f"{v:.2f}"
                      for v in values) + " %"


def _summary_table(results, half: str) -> list[str]:
    """The page's summary: each shared set its own row, each group of :data:`GROUPS` one row
    (the median over its sensors), raw / stack two-point / model_ffc per range."""
    ranges = " / ".join(f"{100 * lo:g}-{100 * hi:g}" for lo, hi in RANGES_FRACTION)
    lines = [f"| sensors | raw ({ranges} % of saturation) | two-point, flat = stack | "
             "model_ffc | rule met |", "|---|---|---|---|---|"]
    methods = ("raw", "two_point_stack", "model_ffc")
    for name, res in results:
        if sensor_group(name) == "shared":
            lines.append(f"| {name} | " + " | ".join(format_figures(range_figures(
                res.summary, m)) for m in methods) + f" | {rule_verdict(res)} |")
    for group in GROUPS:
        members = [res for name, res in results if sensor_group(name) == group]
        if not members:
            continue
        n_met = sum(rule_verdict(r).startswith("**met**") for r in members)
        lines.append(f"| {group}, {len(members)} sensors ({HALF_NAMES[half]} half; median) | "
                     + " | ".join(format_figures(median_figures([r.summary for r in members],
                                                                m)) for m in methods)
                     + f" | {n_met} of {len(members)} |")
    return lines


def render_zoo(results, *, half: str = "eval") -> str:
    """The zoo as Markdown: a summary per group of sensors and the rule per sensor, then one
    table per sensor."""
    cols = ("raw", "two_point_2frame", "two_point_stack", "model_ffc", "model_ffc_calibration")
    lines = ["# Flat-field correction on a zoo of sensors (held out)", "",
             "Every sensor: calibrated on the even light steps and the darks of its sweep, "
             "model_ffc trained also on the flat stack, every figure measured on the odd light "
             "steps (fixed-pattern non-uniformity, EMVA 1288 way: temporal noise of the light "
             "and the dark frames removed; median over the steps of each range of saturation, "
             "± standard error). Rule: model_ffc at or below raw in every range, within 10 % of "
             "the stack two-point from 12 % of saturation up (a difference within twice the "
             "standard error does not count: the frames cannot resolve it); on the real CMOS "
             "also at or below 0.3 % from 12 % up. The simulated sensors are the "
             f"**{half}** half of the seeded grid of hsiffc's simulator "
             "(`hsiffc.reports.ffc_zoo`); the independent sensors the same half of a generator "
             "that does not use hsiffc's simulator, with physics the leakage model leaves out "
             "(exposure offsets, frame-transfer smear, a dark signal outside the photodiode, a "
             "common readout nonlinearity, CCD-like sensors with a large dark level; "
             "`hsiffc.reports.indep_sensors`). A sensor without a flat stack has no stack "
             "two-point: the rule compares it with raw only.", ""]
    lines += _summary_table(results, half) + ["", "| sensor | rule |", "|---|---|"]
    for name, res in results:
        lines.append(f"| {name} | {rule_verdict(res)} |")
    counts = []
    for group in ("shared",) + GROUPS:
        verdicts = [rule_verdict(r) for n, r in results if sensor_group(n) == group]
        if verdicts:
            counts.append(f"{sum(v.startswith('**met**') for v in verdicts)} of "
                          f"{len(verdicts)} {group} sensors (on "
                          f"{sum(v == '**met**' for v in verdicts)} of them resolved everywhere)")
    lines += ["", "Rule met on " + ", ".join(counts) + ". Resolved everywhere: no range where "
              "model_ffc is higher than raw or 1.1 x the stack two-point even within the noise. "
              "Where it is higher within the noise (mostly 2-12 % of saturation on "
              "8- and 10-bit sensors with read noise of several DN), the held-out steps (one "
              "per range there, 12 288 pixels, two frames) cannot resolve the difference: the "
              "raw figure subtracts the dark frames of the step's exposure and removes their "
              "noise statistically, while a correction subtracts an estimated dark whose error "
              "(0.4-0.8 DN on these sensors) is a large share of a 5-30 DN signal.", ""]
    for name, res in results:
        names = method_names(res)
        lines += [f"## {name}", "",
                  f"Saturation {res.saturation['signal_dn']:.0f} DN above dark "
                  f"({res.saturation['bit_depth']}-bit, clip code "
                  f"{res.saturation['clip_code_dn']:.0f} DN); 2-frame flat at "
                  f"{res.flat_2frame['signal_dn']:.0f} DN"
                  + (f", flat stack of {res.flat_stack['n_frames']} frames at "
                     f"{res.flat_stack['signal_dn']:.0f} DN" if res.flat_stack else "") + ".", "",
                  "| signal (of saturation) | steps | "
                  + " | ".join(names.get(c, c) for c in cols if c in names) + " |",
                  "|---|---|" + "---|" * sum(c in names for c in cols)]
        for row in res.summary:
            cells = [cell(row["methods"].get(c), se=True) for c in cols if c in names]
            lines.append(f"| {range_label(row)} | {row['n_steps']} | " + " | ".join(cells)
                         + " |")
        lines += ["", f"Rule: {rule_verdict(res)}.", ""]
    return "\n".join(lines) + "\n"


def zoo_json(results, *, half: str = "eval") -> dict:
    """JSON-safe: the half, and per sensor its group, summary rows, saturation and rule."""
    return {"half": half,
            "sensors": [{"name": name, "group": sensor_group(name), "summary": res.summary,
                         "saturation": res.saturation, "goals": res.goals,
                         "flat_2frame": res.flat_2frame, "flat_stack": res.flat_stack,
                         "goal_percent": res.goal_percent}
                        for name, res in results]}


def main(argv=None) -> int:
    """Command line: run the zoo and write ``ffc_zoo.md`` and ``ffc_zoo.json`` into OUTDIR."""
    from ..files.atomic import atomic_write_text
    from ..files.jsonsafe import json_safe

    ap = argparse.ArgumentParser(prog="python3 -m hsiffc.reports.ffc_zoo",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("outdir", type=Path)
    ap.add_argument("--half", choices=("eval", "dev"), default="eval",
                    help="which half of the simulated and the independent sensors (publish "
                    "eval; tune on dev)")
    ap.add_argument("--shared", type=Path, default=Path("../shared/data"),
                    help="folder of the shared EMVA 1288 sets (missing sets are left out)")
    ap.add_argument("--seeds", type=int, default=None,
                    help="only the first N seeds of each grid's half (a quick look)")
    args = ap.parse_args(argv)
    seeds, indep = ((EVAL_SEEDS, INDEP_EVAL_SEEDS) if args.half == "eval"
                    else (DEV_SEEDS, INDEP_DEV_SEEDS))
    if args.seeds:
        seeds, indep = seeds[:args.seeds], indep[:args.seeds]
    results = run_zoo(seeds=seeds, indep_seeds=indep, shared=args.shared,
                      progress=lambda n, s: print(f"{n}: {s:.1f} s", flush=True))
    args.outdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.outdir / "ffc_zoo.md", render_zoo(results, half=args.half))
    atomic_write_text(args.outdir / "ffc_zoo.json",
                      json.dumps(json_safe(zoo_json(results, half=args.half)), indent=1) + "\n")
    for name, res in results:
        print(f"{name}: {rule_verdict(res)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
