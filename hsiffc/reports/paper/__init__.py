"""The paper's section V as a report: Tables I and II, Figures 2, 4, 5 and 6, the alpha-threshold
trade-off of its future work, and the same flat-field questions on the real EMVA 1288 sweep.

:func:`run_paper_report` runs everything on the simulated 8-band sensor of
:mod:`hsiffc.simulate` and writes ``report.md`` (tables with the paper's values beside ours),
PNG figures and one CSV per table or figure into a folder. Every file is written atomically.
It is three steps a notebook can also take one by one: :func:`compute_paper_report` returns a
:class:`PaperResult` (numbers only), :func:`render_markdown` turns it into text and
:func:`paper_figures` into matplotlib figures (no backend switching, no pyplot state).

Table II runs the shipped stages (``create("dark")`` then ``create("two_point_ffc")`` in a
:class:`~hsiffc.stages.Pipeline`), so its numbers certify the code users run.

The experiment, as in the paper (Liu et al., section V):

* lamp A (2900 K blackbody, colour-science) for training, lamp B (2200 K) for testing, uniform
  light (an integrating sphere: no vignetting), every training image the mean of 10 frames;
* calibration by the paper's procedure (section III.C): exposure sweeps into dynamic
  saturation under 16 levels of lamp A, k from the linear part, a and b from the 16 (saturated
  level, k) pairs of every pixel (Fig. 4);
* Fig. 5 / Fig. 2: one pixel of band 1 under lamp B at the light of Fig. 5 (k about 2 DN/ms),
  10 frames per exposure up to 1000 ms, against the leakage model (eq. 3) and the linear model
  (eq. 1), with k estimated from the linear part of that pixel's own data;
* Table I: alpha (eq. 4, k ~ signal / exposure, median over a band's pixels) of the 10-frame
  training images at 6.45-32.25 ms, the longest under 12 % selected;
* Table II: improvement of eq. (6) by two-point FFC (eq. 5) trained at each candidate, on raw
  test frames at 16.125 ms under lamp B (several independent frames: mean and standard error);
* Fig. 6: lamp B spectra (band means of the dark-subtracted frame, no flat-field) at the 11
  exposures 3.225-35.475 ms, normalised by their maximum; a spectrum is invalid when any band's
  alpha exceeds the threshold;
* the trade-off: for every threshold 1-100 %, SNR of the selected training flats, uniformity
  improvement (Table II metric) and spectral correctness, normalised to [0, 1] and combined with
  user weights.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from ... import __version__
from ...files.jsonsafe import json_safe
from ...files.atomic import atomic_write_text
from ..figures import save_figure
from .config import (CANDIDATES_MS, N_TEST_FRAMES, PAPER_VALUES, TEST_MS, THRESHOLD_PERCENT,
                     THRESHOLDS, find_emva_dir, parse_weights, spectral_angle_deg)
from .csvs import report_csvs
from .emva import emva_ffc_levels
from .experiment import simulate_paper_experiment
from .markdown import render_markdown
from .plots import paper_figures

__all__ = ["CANDIDATES_MS", "PAPER_VALUES", "TEST_MS", "THRESHOLDS", "THRESHOLD_PERCENT",
           "PaperResult", "compute_paper_report", "emva_ffc_levels", "find_emva_dir",
           "paper_figures", "parse_weights", "render_markdown", "run_paper_report",
           "simulate_paper_experiment", "spectral_angle_deg", "write_paper_report"]

log = logging.getLogger(__name__)


@dataclass
class PaperResult:
    """Every number of the paper report.

    Attributes
    ----------
    simulated : dict
        The simulated experiment (:func:`simulate_paper_experiment`).
    emva : dict or None
        The real EMVA 1288 part (:func:`emva_ffc_levels`), None when skipped.
    emva_note : str
        Why the real-data part was skipped (empty when it ran).
    timing : dict
        Seconds per part (``*_s``) and ``total_s``.
    files : dict
        File name -> path, filled by :func:`write_paper_report`.
    """

    simulated: dict
    emva: dict | None
    emva_note: str
    timing: dict
    files: dict = field(default_factory=dict)


def compute_paper_report(*, seed: int = 0, shape=(128, 128), emva_dir=None, weights=None,
                         threshold: float = THRESHOLD_PERCENT,
                         n_test_frames: int = N_TEST_FRAMES) -> PaperResult:
    """Run the paper's experiments and return their numbers (no files written).

    Parameters
    ----------
    seed : int
        Seeds the simulated sensor's fixed pattern and every capture.
    shape : (H, W)
        Simulated sensor size in pixels (a multiple of the 2 x 4 tile).
    emva_dir : path-like, None or False
        The real EMVA 1288 sweep folder. None: look for ``shared/data/emva1288-cmos8-roi``
        (:func:`find_emva_dir`); False: skip the real-data part.
    weights : dict or str, optional
        Trade-off weights, e.g. ``"snr=1,sc=1,ru=1"`` (see :func:`parse_weights`).
    threshold : float
        alpha threshold (percent) of Tables I and II and Fig. 6 (the paper's 12 %).
    n_test_frames : int
        Independent test frames of Table II (mean and standard error over them).

    Returns
    -------
    PaperResult
    """
    t0 = time.perf_counter()
    weights = parse_weights(weights)
    log.info("simulating the paper's experiment on a %s sensor (seed %s)", tuple(shape), seed)
    sim = simulate_paper_experiment(seed=seed, shape=shape, threshold=threshold,
                                    weights=weights, n_test_frames=n_test_frames)
    em, note = None, ""
    if emva_dir is False:
        note = "Skipped (real-data part switched off)."
    else:
        found = Path(emva_dir) if emva_dir is not None else find_emva_dir()
        if emva_dir is not None and not found.exists():
            raise FileNotFoundError(f"EMVA 1288 data folder {found} does not exist")
        if found is None:
            note = ("Skipped: the EMVA 1288 sweep was not found (no "
                    "shared/data/emva1288-cmos8-roi beside the repository or the working "
                    "directory, and HSIFFC_SHARED_DATA not set); pass its folder (`hsiffc paper "
                    "OUTDIR --emva DIR`) to run this part.")
        else:
            log.info("flat-field levels on the real EMVA 1288 sweep %s", found)
            em = emva_ffc_levels(found, threshold=threshold)
    timing = {**sim["timing"], **({f"emva_{k}": v for k, v in em["timing"].items()} if em else {})}
    timing["compute_total_s"] = time.perf_counter() - t0
    return PaperResult(sim, em, note, timing)


def write_paper_report(result: PaperResult, outdir, *, overwrite: bool | None = None) -> dict:
    """Write ``report.md``, the figures, the CSV files and ``summary.json`` into ``outdir``.

    Parameters
    ----------
    result : PaperResult
    outdir : path-like
        Created if missing. Every file is written atomically.
    overwrite : bool, optional
        Replace files of an earlier report (None: as the write policy in force says).

    Returns
    -------
    dict
        File name -> path (also stored in ``result.files``).
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    files = {}
    for name, fig in paper_figures(result.simulated, result.emva).items():
        files[name] = str(save_figure(fig, outdir / name, overwrite=overwrite))
    for name, text in report_csvs(result.simulated, result.emva).items():
        atomic_write_text(outdir / name, text, overwrite=overwrite)
        files[name] = str(outdir / name)
    result.timing["figures_s"] = time.perf_counter() - t0
    result.timing["total_s"] = result.timing["compute_total_s"] + result.timing["figures_s"]
    atomic_write_text(outdir / "report.md", render_markdown(result), overwrite=overwrite)
    files["report.md"] = str(outdir / "report.md")
    result.files = files
    files["summary.json"] = str(outdir / "summary.json")
    atomic_write_text(outdir / "summary.json",
                      json.dumps(json_safe(summary_dict(result)), indent=1) + "\n",
                      overwrite=overwrite)
    return files


def run_paper_report(outdir, *, overwrite: bool | None = None, **options) -> PaperResult:
    """:func:`compute_paper_report` with ``options``, then :func:`write_paper_report` into
    ``outdir``; returns the result with ``files`` filled in."""
    result = compute_paper_report(**options)
    write_paper_report(result, outdir, overwrite=overwrite)
    return result


def summary_dict(result: PaperResult) -> dict:
    """JSON-safe digest of a result (arrays of the figures dropped: they are in the CSVs)."""
    sim = result.simulated
    drop5 = {"frames", "t_fine_ms", "leakage_fine_dn", "linear_fine_dn"}
    return {"hsiffc_version": __version__, "seed": sim["seed"], "shape": sim["shape"],
            "threshold_percent": sim["threshold_percent"], "light_w_m2": sim["light_w_m2"],
            "paper": PAPER_VALUES, "table1": sim["table1"].to_dict(),
            "table2": sim["table2"], "fig2": sim["fig2"], "fig4": sim["fig4"],
            "fig5": {k: v for k, v in sim["fig5"].items() if k not in drop5},
            "fig6": sim["fig6"],
            "tradeoff": {k: v for k, v in sim["tradeoff"].items() if k != "rows"},
            "emva": result.emva, "emva_note": result.emva_note,
            "timing": result.timing, "files": result.files}
