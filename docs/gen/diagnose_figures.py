"""Measure the figures of docs/diagnose.md and write them into it (between the
``<!-- BEGIN generated -->`` and ``<!-- END generated -->`` markers).

    python3 docs/gen/diagnose_figures.py [--quick]

Detection limits: each library effect is injected into the simulated EMVA 1288-like sweep
(``hsiffc.diagnose.simulated.simulated_sweep("mixed")``, seeds 1 and 2; dark_current into the
same design without dark frames, since with darks it is part of the base) at a ladder of sizes;
the limit is the smallest size at which diagnose selects that effect first on both seeds.
Designs: clean data of every design (what is selected, what is skipped and why). Real data:
the EMVA 1288 sweep in ../shared/data when present. Takes ~10 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np

from hsiffc.files.atomic import atomic_write_text
from hsiffc.diagnose import diagnose
from hsiffc.diagnose.simulated import simulated_sweep
from hsiffc.diagnose.effects import add_effect

DOC = Path(__file__).resolve().parents[1] / "diagnose.md"
EMVA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "emva1288-cmos8-roi"
LADDERS = {
    "dark_current": ("DN/ms, no dark frames", [0.02, 0.04, 0.1, 0.2, 0.5]),
    "exposure_offset": ("ms", [0.0125, 0.025, 0.05, 0.1]),
    "readout_nonlinearity": ("DN at full scale", [5.0, 10.0, 20.0, 40.0]),
    "pixel_nonlinearity": ("DN spread at full scale", [20.0, 40.0, 80.0]),
    "offset_drift": ("DN peak", [0.25, 0.5, 1.0, 2.0]),
    "illumination_error": ("relative RMS per step", [0.001, 0.002, 0.004, 0.008]),
    "image_lag": ("fraction", [0.0005, 0.001, 0.002, 0.004]),
    "frame_light_change": ("relative per frame", [0.001, 0.002, 0.004, 0.008]),
}
DESIGNS = {
    "mixed (EMVA-like, shuffled exposures and light)": dict(design="mixed"),
    "exposure sweep, one light level": dict(design="exposure"),
    "light sweep at one exposure (20 ms)": dict(design="light"),
    "mixed, one frame per step (60 steps)": dict(design="mixed", n_frames=1, n_steps=60),
    "mixed, no dark frames": dict(design="mixed", darks=False),
    "mixed, 10 light steps": dict(design="mixed", n_steps=10),
}


def limits(quick):
    rows = []
    for name, (unit, ladder) in LADDERS.items():
        found = None
        for size in ladder[-2:] if quick else ladder:
            ok = True
            for seed in (1, 2):
                sw = simulated_sweep("mixed", seed=seed, darks=name != "dark_current")
                out = diagnose(add_effect(sw, name, size, seed=7))
                ok &= out["selected_effects"][:1] == [name]
            if ok:
                found = size
                break
        rows.append(f"| `{name}` | {found if found is not None else '> ' + str(ladder[-1])} | "
                    f"{unit} |")
    return ["| effect | detected from (both seeds) | unit |", "|---|---|---|"] + rows


def designs():
    rows = ["| design | selected | skipped (reason) | noise floor (DN) | systematic before "
            "(DN) | leakage | time (s) |", "|---|---|---|---|---|---|---|"]
    for label, kw in DESIGNS.items():
        out = diagnose(simulated_sweep(seed=4, **kw))
        skipped = "; ".join(f"`{s['name']}`: {s['reason']}" for s in out["skipped"]) or "-"
        rows.append(f"| {label} | {', '.join(out['selected_effects']) or 'nothing'} | "
                    f"{skipped} | {out['noise_floor_dn']:.3g} | "
                    f"{out['before']['systematic_rms_dn']:.3g} | {out['leakage']['verdict']} | "
                    f"{out['runtime_s']:.1f} |")
    return rows


def real():
    if not EMVA.exists():
        return [f"(real data not found at {EMVA})"]
    from hsiffc.io import read_sweep

    out = diagnose(read_sweep(EMVA))
    lines = [f"`hsiffc diagnose ../shared/data/emva1288-cmos8-roi` ({out['n_pixels']} pixels, "
             f"{out['n_samples']} held-out samples, {out['runtime_s']:.1f} s): noise floor "
             f"{out['noise_floor_dn']:.4g} DN; systematic {out['before']['systematic_rms_dn']:.3g}"
             f" DN with the base model, {out['after']['systematic_rms_dn']:.3g} DN with "
             f"{', '.join(out['selected_effects']) or 'nothing'}; unexplained structure: "
             f"{'yes' if out['unexplained'] else 'no'}; leakage: {out['leakage']['verdict']}.", ""]
    lines += [f"- `{e['name']}`: {e['interpretation']}." for e in out["effects"]]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two sizes per effect only")
    args = ap.parse_args()
    t0 = time.time()
    body = ["", f"Measured by `python3 docs/gen/diagnose_figures.py` on "
            f"{platform.machine()}, {__import__('os').cpu_count()} cores, python "
            f"{platform.python_version()}.", "", "### Detection limits (mixed design, 768 px, 40 "
            "light steps, 2 frames per step)", ""] + limits(args.quick)
    body += ["", "### Clean data on every design (seed 4)", ""] + designs()
    body += ["", "### The real EMVA 1288 sweep", ""] + real() + [""]
    text = DOC.read_text()
    new = re.sub(r"(<!-- BEGIN generated -->\n).*?(<!-- END generated -->)",
                 lambda m: m.group(1) + "\n".join(body) + "\n" + m.group(2), text, flags=re.S)
    atomic_write_text(DOC, new, overwrite=True)
    print(f"wrote {DOC} in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
