"""Regenerate the sample cubes from the default simulated sensor (reproducible from seeds).

    python sample_cubes/make_samples.py [OUTDIR]      # default: this folder

Writes hsiffc TIFF sweeps (format: docs/reference/formats.md) and MANIFEST.sha256
(check with ``sha256sum -c MANIFEST.sha256`` in the folder):

- ``darks.tif``          dark frames, 4 per exposure, at the candidate and test exposures;
- ``sweep_2900K.tif``    lamp A (2900 K) at a quarter of the paper's training level (k near
                         7.5 DN/ms), 20 exposures from 2 to 400 ms into dynamic saturation
                         (near 900 DN, below the 1023 DN full scale), 2 light + 2 dark frames
                         each;
- ``training_2900K.tif`` lamp A, 10 frames at each of the paper's candidate training exposures
                         6.45, 12.9, 19.35, 25.8 and 32.25 ms (Table I);
- ``test_2200K.tif``     lamp B (2200 K) at the test level, 4 frames at 16.125 ms (Table II) and
                         2 at 32.25 ms.

The sensor is the paper's 8-band sensor (2 x 4 mosaic tile), 96 x 128 pixels, seed 2026.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from hsiffc.io import write_sweep
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.data.sweep import Sweep

SHAPE = (96, 128)
SEED = 2026
CANDIDATES_MS = [6.45, 12.9, 19.35, 25.8, 32.25]
TEST_MS = 16.125
SWEEP_MS = np.round(np.geomspace(2.0, 400.0, 20), 3)
SWEEP_LEVEL = 0.25  # of the training irradiance


def _clean(sweep: Sweep, **meta) -> Sweep:
    m = {k: v for k, v in sweep.meta.items() if k != "truth"}
    m.update(meta)
    return replace(sweep, meta=m)


def make(outdir: Path) -> list[Path]:
    outdir.mkdir(parents=True, exist_ok=True)
    sensor = MosaicSensor(SHAPE, seed=SEED)
    train = PAPER_LIGHT_W_M2["training"]
    test = PAPER_LIGHT_W_M2["test"]
    written = []

    def save(name, sweep, **meta):
        path = outdir / name
        write_sweep(path, _clean(sweep, generator="sample_cubes/make_samples.py", **meta),
                    overwrite=True)
        written.append(path)

    darks = sensor.sweep(sorted(set(CANDIDATES_MS + [TEST_MS, 64.5])), None, n_frames=4,
                         darks=False, seed=1)
    save("darks.tif", darks)
    sweep = sensor.sweep(SWEEP_MS, "lamp A", irradiance_w_m2=train * SWEEP_LEVEL, n_frames=2,
                         seed=2)
    save("sweep_2900K.tif", sweep, irradiance_w_m2=train * SWEEP_LEVEL)
    training = sensor.sweep(CANDIDATES_MS, "lamp A", irradiance_w_m2=train, n_frames=10,
                            darks=False, seed=3)
    save("training_2900K.tif", training, irradiance_w_m2=train)
    t1 = sensor.sweep([TEST_MS], "lamp B", irradiance_w_m2=test, n_frames=4, darks=False, seed=4)
    t2 = sensor.sweep([32.25], "lamp B", irradiance_w_m2=test, n_frames=2, darks=False, seed=5)
    both = Sweep(np.concatenate([t1.data, t2.data]),
                 np.concatenate([t1.exposure_ms, t2.exposure_ms]),
                 np.concatenate([t1.kind, t2.kind]), t1.bit_depth,
                 illumination=np.concatenate([t1.illumination, t2.illumination]),
                 mosaic=t1.mosaic, source="simulated", meta=t1.meta)
    save("test_2200K.tif", both, irradiance_w_m2=test)

    lines = []
    for p in sorted(written):
        digest = hashlib.sha256(p.read_bytes()).hexdigest()
        lines.append(f"{digest}  {p.name}\n")
    (outdir / "MANIFEST.sha256").write_text("".join(lines))
    return written


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent
    for p in make(out):
        print(f"{p}  {p.stat().st_size / 1e6:.2f} MB")
