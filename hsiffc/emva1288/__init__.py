"""EMVA 1288 Release 4.0 characterisation of a sweep, as the standard's reference
implementation computes it, plus what the leakage model says about the figures.

- :func:`characterise` (:mod:`.compute`): the standard's figures under the reference
  implementation's names (``K``, ``R``, ``QE``, ``sigma_y_dark``, ..., ``u_I_var``), with units,
  fit ranges and standard errors; per band of a mosaic.
- :func:`leakage_effects` (:mod:`.leakage`): beyond the standard, what a per-pixel leakage
  calibration says about them (share of the linearity error it explains, dynamic saturation
  against light rate, alpha at the standard's saturation point, leakage in the saturation
  capacity).
- :func:`write_report` (:mod:`.render`, :mod:`.plot`): the standard's plots as PNG and a
  Markdown page with the figures table.
- :func:`hsiffc.emva1288.general.general_figures` (:mod:`.general`): Release 4.0 General, the
  application figures without the linear model (differential responsivity, SNR, saturation,
  threshold, dynamic range), measured and as the leakage model predicts them.
- :func:`run_characterisation`: all of it for one measurement.
- :mod:`.agreement`: the figures of the shared EMVA 1288 sets beside the reference
  implementation's (``python3 -m hsiffc.emva1288 DATA OUTDIR``).
"""

from __future__ import annotations

from .compute import FIGURES, characterise, saturation_index, step_statistics
from .render import render_markdown, to_json, write_report  # matplotlib loads when plotting

__all__ = ["FIGURES", "characterise", "leakage_effects", "render_markdown",
           "run_characterisation", "saturation_index", "step_mean_sweep", "step_statistics",
           "to_json", "write_report"]


def __getattr__(name):
    """:func:`leakage_effects` loads the leakage model (and numba) when first named: the
    figures alone (``hsiffc emva1288 --no-leakage``) of a small set never load numba."""
    if name == "leakage_effects":
        from .leakage import leakage_effects

        return leakage_effects
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def step_mean_sweep(stats: dict, source) -> tuple:
    """The sweep steps of :func:`step_statistics` (``keep_step_means=True``) as a Sweep of one
    float32 frame per step (its per-pixel mean; full scale where some frame of the step was,
    so that the calibration sees it clipped), each standing for the step's frames
    (``meta["frames_averaged"]``), and the photon transfer of the raw frames' first pairs.

    Returns
    -------
    sweep : Sweep
        What :func:`hsiffc.calibrate.calibrate` fits the leakage model on.
    ptc : PhotonTransfer or None
        Its ``ptc`` argument.
    """
    import numpy as np

    from ..calibrate.samples import photon_transfer_from_pairs
    from ..data.sweep import Sweep

    info = stats["sweep_step_info"]
    pairs = [(k, p[0], p[1] / p[0] if p[0] else np.nan, 0.5 * p[2] / p[0] if p[0] else np.nan)
             for k, p, n in zip(info["kind"], stats["pairs"], info["n_frames"]) if n >= 2]
    ptc = photon_transfer_from_pairs(pairs, stats["n_pixels"], stats["full_scale_dn"])
    label = getattr(source, "source", None) or getattr(source, "label", "") or ""
    sweep = Sweep(stats["step_means"], info["exposure_ms"], info["kind"].astype(str),
                  stats["bit_depth"], step=info["step"], photons=info["photons"],
                  mosaic=getattr(source, "mosaic", None), source=str(label),
                  meta={"frames_averaged": info["n_frames"]})
    return sweep, ptc


def run_characterisation(sweep, *, pixel_area_um2=None, wavelength_nm=None, leakage=True,
                         calibration=None) -> tuple[dict, dict | None, str | None]:
    """The EMVA 1288 figures of ``sweep`` and, with ``leakage``, the leakage model's account.

    The frames are read once, one at a time (:mod:`.stream`): memory holds a few frames, the
    stacks' images and, for the leakage calibration, one mean image per sweep step.

    Parameters
    ----------
    sweep : Sweep or FrameSource
        An EMVA 1288 measurement (:func:`hsiffc.io.read_emva1288`, or
        :func:`hsiffc.io.open_source` on its descriptor to stream it).
    pixel_area_um2, wavelength_nm : float, optional
        See :func:`characterise`.
    leakage : bool
        Also :func:`leakage_effects` (calibrates the sweep steps' means with
        :func:`hsiffc.calibrate.calibrate` unless ``calibration`` is given).
    calibration : Calibration, optional
        Leakage-model calibration of this measurement.

    Returns
    -------
    res : dict
        :func:`characterise`.
    leak : dict or None
        :func:`leakage_effects`, or None.
    note : str or None
        Why ``leak`` is None when ``leakage`` was asked for (the sweep cannot be calibrated).
    """
    from ..errors import DataFormatError

    stats = step_statistics(sweep, keep_step_means=leakage and calibration is None)
    res = characterise(sweep, pixel_area_um2=pixel_area_um2, wavelength_nm=wavelength_nm,
                       statistics=stats)
    if not leakage:
        return res, None, None
    from .general import general_figures

    means = None
    if calibration is None:
        from ..calibrate import LEAKAGE_ACCOUNT, calibrate

        means, ptc = step_mean_sweep(stats, sweep)
        del stats
        try:
            # the leakage model's own account (no held-out choice of a simpler model)
            calibration = calibrate(means, method="joint", ptc=ptc, **LEAKAGE_ACCOUNT)
        except DataFormatError as exc:
            return res, None, f"not computed: the sweep cannot calibrate the leakage model ({exc})"

    from .leakage import leakage_effects

    leak = leakage_effects(means if means is not None else sweep, res, calibration)
    res["general"] = general_figures(res, leak)  # the model's General figures beside
    return res, leak, None
