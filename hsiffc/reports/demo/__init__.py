"""``hsiffc demo``: the main job shown on the bundled sample cubes.

The demo reads the 2900 K exposure sweep, fits the leakage model to each band's mean response
and shows that every band levels off *below* full scale at a level that depends on its light
(dynamic saturation), with the leakage percentage alpha of every exposure. Then it corrects
the 2200 K test frames with the paper's pipeline (dark, alpha mask, two-point FFC trained at
the exposure alpha selects, PPID reconstruction) and with the model-based flat field that
``hsiffc correct`` applies by default (dark, alpha mask, ``model_ffc`` from the calibration
alone), and measures uniformity before and after: eq. (6) and the fixed-pattern
non-uniformity (EMVA 1288, temporal noise taken out).

As every report: :func:`compute_demo` returns a :class:`DemoResult`, :func:`render_text` and
:func:`demo_figure` present it, :func:`run_demo` writes the files. The library prints nothing.
"""

from __future__ import annotations

import json
from pathlib import Path

from ...atomic import atomic_write_text
from ..figures import save_figure
from .compute import SWEEP_NAME, DemoResult, compute_demo, demo_pipeline, fit_curve
from .render import demo_figure, render_text

__all__ = ["SWEEP_NAME", "DemoResult", "compute_demo", "demo_figure", "demo_pipeline",
           "fit_curve", "render_text", "run_demo"]


def run_demo(samples, outdir, *, overwrite: bool | None = None) -> DemoResult:
    """Run the demo and write its files into ``outdir``.

    Parameters
    ----------
    samples : path-like
        The sample folder (see :func:`compute_demo`).
    outdir : path-like
        Receives ``dynamic_saturation.png``, ``demo_summary.json``, ``calibration.npz`` and
        ``pipeline.npz`` (created if missing).
    overwrite : bool, optional
        Replace the files of an earlier demo (None: as the write policy in force says).

    Returns
    -------
    DemoResult
        With ``files`` (name -> path) added to ``result.correction``.
    """
    res = compute_demo(samples)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    files = {"figure": save_figure(demo_figure(res), outdir / "dynamic_saturation.png", dpi=110,
                                   tight=False, overwrite=overwrite),
             "calibration": res.calibration.save(outdir / "calibration.npz", overwrite=overwrite),
             "pipeline": res.pipeline.save(outdir / "pipeline.npz", overwrite=overwrite),
             "summary": outdir / "demo_summary.json"}
    res.correction["files"] = {k: str(v) for k, v in files.items()}
    atomic_write_text(files["summary"], json.dumps(res.summary(), indent=2) + "\n",
                      overwrite=overwrite)
    return res
