"""Linear model against leakage model on a real EMVA 1288 exposure sweep.

The linear model is the paper's eq. (1), ``Y = d + g * photons`` per pixel (``k t`` with
``k = g * photons / t``). The leakage model is the joint per-pixel calibration of
:mod:`hsiffc.calibrate`, ``Y = response(t, responsivity * rate + dark_current, a, b, dark)``.
Both are compared on exactly the same samples: the step means the leakage fit used (no frame of
the step at full scale, exposure > 0, a known light rate), light and dark steps alike. The
linear fit uses the same weights as the leakage fit (frames per step over the photon-transfer
variance of the step mean). Residuals are model minus data, in DN.

A pixel *levels off below full scale* when all three hold:

1. no frame of any usable step reaches full scale (it is never clipped);
2. its highest step mean stays below full scale minus ``FULL_SCALE_MARGIN_DN``;
3. over the ``N_TOP_STEPS`` light steps with the most photons, its rise (least-squares slope of
   the step means against photons times the photon span of those steps) is less than
   ``ROLL_OFF_RATIO`` of the rise its own linear fit predicts.

Condition 3 separates a roll-off from a pixel that is merely too insensitive to reach 255.
"""

from __future__ import annotations

import json
from pathlib import Path

from ...files.atomic import atomic_write_text
from ...calibrate import Calibration
from ..figures import save_figure
from .analysis import analyse_emva_leakage, fit_linear, sweep_steps_only
from .render import leakage_figure, render_markdown

__all__ = ["analyse_emva_leakage", "fit_linear", "leakage_figure", "render_markdown",
           "sweep_steps_only", "write_emva_leakage_report"]


def write_emva_leakage_report(sweep, outdir, calibration: Calibration | None = None) -> dict:
    """Run :func:`analyse_emva_leakage` and write its JSON, Markdown and figure atomically.

    Parameters
    ----------
    sweep : Sweep
        EMVA 1288 sweep (see :func:`analyse_emva_leakage`).
    outdir : path-like
        Folder for ``emva_leakage.json``, ``emva_leakage.md`` and ``emva_leakage_pixels.png``
        (created if missing; existing files are replaced).
    calibration : Calibration, optional
        Default: a joint calibration of the sweep steps.

    Returns
    -------
    dict
        The analysis, with ``"files"`` naming the written files.
    """
    outdir = Path(outdir)
    res = analyse_emva_leakage(sweep, calibration)
    files = {"json": outdir / "emva_leakage.json", "markdown": outdir / "emva_leakage.md",
             "figure": outdir / "emva_leakage_pixels.png"}
    save_figure(leakage_figure(res), files["figure"], dpi=100)
    atomic_write_text(files["markdown"], render_markdown(res))
    res["files"] = {k: str(v) for k, v in files.items()}
    atomic_write_text(files["json"], json.dumps(res, indent=1, allow_nan=False) + "\n")
    return res
