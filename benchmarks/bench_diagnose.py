"""Diagnose benchmark: ``hsiffc diagnose`` on a 100-step sweep, 2 frames per step, 128 x 256 px
(issue 14 target: under 10 s).

The sweep is simulated (the EMVA 1288-like "mixed" design of :mod:`hsiffc.diagnose.simulated`:
50 light steps with shuffled exposures 2-200 ms and changing light, each followed by a dark
step) and written as an hsiffc TIFF sweep; the command reads it and diagnoses 2048 pixels
(the default). Reported: median wall time of the whole command (read + diagnose) and of
``diagnose()`` alone. Baseline, measured in the same run: one joint base-model fit
(``hsiffc.calibrate.fit_pixels``, 40 iterations) on the same 2048 pixels' samples, so the ratio
says how many base fits a diagnosis costs.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchutil import figure, median_time, row
from hsiffc.calibrate import fit_pixels, initial_guess
from hsiffc.calibrate.samples import collect_samples
from hsiffc.cli import main as cli
from hsiffc.diagnose import diagnose
from hsiffc.diagnose.simulated import simulated_sweep
from hsiffc.io import read_sweep, write_sweep

SHAPE = (128, 256)
N_LIGHT_STEPS = 50  # + one dark step each: 100 steps
TARGET_S = 10.0


def main(quick: bool = False) -> dict:
    repeat = 1 if quick else 3
    sweep = simulated_sweep("mixed", shape=SHAPE, n_steps=N_LIGHT_STEPS, seed=5)
    n_steps = len(sweep.steps())
    print(f"diagnose: {n_steps} steps x 2 frames x {SHAPE[0]} x {SHAPE[1]} px (simulated, "
          f"mixed design), 2048 pixels analysed, median of {repeat}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sweep.tif"
        write_sweep(path, replace(sweep, meta={}))

        def command():
            with contextlib.redirect_stdout(io.StringIO()):
                assert cli(["diagnose", str(path)]) == 0
        t_cli = median_time(command, repeat=repeat, warmup=1)
        t_read = median_time(lambda: read_sweep(path), repeat=repeat, warmup=0)
    t_lib = median_time(lambda: diagnose(sweep), repeat=repeat, warmup=0)
    # baseline: one base-model fit on the same pixels' step means
    sub = replace(sweep, data=sweep.data.reshape(sweep.n_frames, 1, -1)[:, :, :2048], meta={},
                  mosaic=None)
    smp = collect_samples(sub)
    y, valid = smp.y.T.astype(np.float64), smp.valid.T
    w = np.ones_like(y)
    t = np.where(smp.usable_step, smp.exposure_ms, 1.0)
    r = np.nan_to_num(smp.rate)
    theta0 = initial_guess(y, t, r, valid, w)
    t_fit = median_time(lambda: fit_pixels(y, t, r, valid, w, theta0, max_iter=40),
                        repeat=repeat, warmup=1)
    print(row("hsiffc diagnose SWEEP (read + diagnose)", t_cli, "s",
              f"target < {TARGET_S:g} s: {'met' if t_cli < TARGET_S else 'NOT met'}"))
    print(row("  of which reading the sweep", t_read, "s"))
    print(row("diagnose() alone", t_lib, "s"))
    print(row("baseline: one base-model fit, same 2048 pixels", t_fit, "s"))
    print(row("diagnose / one base fit", t_lib / t_fit, "x"))
    return {"command_s": t_cli, "read_s": t_read, "diagnose_s": t_lib, "base_fit_s": t_fit,
            "ratio_to_base_fit": t_lib / t_fit, "target_s": TARGET_S,
            "steps": n_steps, "shape": list(SHAPE),
            "figures": [figure("hsiffc diagnose SWEEP (read + diagnose)", t_cli, "s",
                               baseline=t_fit,
                               baseline_name="one base-model fit, same 2048 pixels",
                               ratio=t_lib / t_fit, target=f"< {TARGET_S:g} s",
                               met=t_cli < TARGET_S,
                               note="ratio = diagnose() alone / one base-model fit")]}
