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
import logging
from pathlib import Path

from ...files.atomic import OutputError, atomic_write_text, check_output_folder
from ..figures import save_figure
from .compute import (SAMPLE_NAMES, SWEEP_NAME, DemoResult, check_samples, compute_demo,
                      demo_pipeline, fit_curve)
from .render import demo_figure, render_text

__all__ = ["DEMO_FILES", "DEMO_MARKER", "SAMPLE_NAMES", "SWEEP_NAME", "DemoResult",
           "check_samples", "compute_demo", "demo_figure", "demo_pipeline", "fit_curve",
           "is_demo_folder", "render_text", "run_demo"]

log = logging.getLogger(__name__)


#: marker file of a folder the demo wrote: the demo replaces its own files there on a rerun
DEMO_MARKER = ".hsiffc-demo"
#: the files the demo writes into its folder
DEMO_FILES = ("dynamic_saturation.png", "calibration.npz", "pipeline.npz", "demo_summary.json")


def is_demo_folder(folder) -> bool:
    """Whether ``folder`` is one the demo wrote (it holds the demo's marker file, a plain file).

    Parameters
    ----------
    folder : path-like

    Returns
    -------
    bool
    """
    marker = Path(folder) / DEMO_MARKER
    return (Path(folder).is_dir() and not Path(folder).is_symlink() and marker.is_file()
            and not marker.is_symlink())


def run_demo(samples, outdir, *, overwrite: bool | None = None) -> DemoResult:
    """Run the demo and write its files into ``outdir``.

    The sample folder is checked first, then the output folder, both before any work. A
    folder an earlier demo wrote (it holds the marker file :data:`DEMO_MARKER`) is the demo's
    own: a rerun replaces its files there (:data:`DEMO_FILES`, nothing else), so the demo can
    be run again and again. Any other folder that holds files is refused unless ``overwrite``.

    Parameters
    ----------
    samples : path-like
        The sample folder (see :func:`compute_demo`).
    outdir : path-like
        Receives ``dynamic_saturation.png``, ``demo_summary.json``, ``calibration.npz``,
        ``pipeline.npz`` and the marker (created if missing).
    overwrite : bool, optional
        Replace files in a folder that is not the demo's own (None: as the write policy in
        force says).

    Returns
    -------
    DemoResult
        With ``files`` (name -> path) added to ``result.correction``.

    Raises
    ------
    DataFormatError
        A sample file is missing.
    OutputError
        ``outdir`` cannot be written (e.g. it holds other files and ``overwrite`` is false).
    """
    check_samples(samples)
    outdir = Path(outdir)
    own = is_demo_folder(outdir)
    if own:
        overwrite = True
        for name in DEMO_FILES:  # the demo's own names: refuse to write through a link
            if (outdir / name).is_symlink():
                raise OutputError(f"{outdir / name}: is a symbolic link; remove it or choose "
                                  "another folder (hsiffc demo -o FOLDER)")
    check_output_folder(outdir, overwrite=overwrite)
    log.info("running the demo on %s", samples)
    res = compute_demo(samples)
    outdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(outdir / DEMO_MARKER, "written by hsiffc demo: a rerun replaces "
                      f"{', '.join(DEMO_FILES)} in this folder\n", overwrite=True)
    files = {"figure": save_figure(demo_figure(res), outdir / DEMO_FILES[0], dpi=110,
                                   tight=False, overwrite=overwrite),
             "calibration": res.calibration.save(outdir / DEMO_FILES[1], overwrite=overwrite),
             "pipeline": res.pipeline.save(outdir / DEMO_FILES[2], overwrite=overwrite),
             "summary": outdir / DEMO_FILES[3]}
    res.correction["files"] = {k: str(v) for k, v in files.items()}
    atomic_write_text(files["summary"], json.dumps(res.summary(), indent=2) + "\n",
                      overwrite=overwrite)
    return res
