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
- :func:`run_characterisation`: all of it for one measurement.
- :mod:`.agreement`: the figures of the shared EMVA 1288 sets beside the reference
  implementation's (``python3 -m hsiffc.emva1288 DATA OUTDIR``).
"""

from __future__ import annotations

from .compute import FIGURES, characterise, saturation_index, step_statistics
from .leakage import leakage_effects
from .render import render_markdown, to_json, write_report

__all__ = ["FIGURES", "characterise", "leakage_effects", "render_markdown",
           "run_characterisation", "saturation_index", "step_statistics", "to_json",
           "write_report"]


def run_characterisation(sweep, *, pixel_area_um2=None, wavelength_nm=None, leakage=True,
                         calibration=None) -> tuple[dict, dict | None, str | None]:
    """The EMVA 1288 figures of ``sweep`` and, with ``leakage``, the leakage model's account.

    Parameters
    ----------
    sweep : Sweep
        An EMVA 1288 measurement (:func:`hsiffc.io.read_emva1288`).
    pixel_area_um2, wavelength_nm : float, optional
        See :func:`characterise`.
    leakage : bool
        Also :func:`leakage_effects` (calibrates the sweep steps with
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

    res = characterise(sweep, pixel_area_um2=pixel_area_um2, wavelength_nm=wavelength_nm)
    if not leakage:
        return res, None, None
    if calibration is None:
        from ..calibrate import LEAKAGE_ACCOUNT, calibrate
        from ..reports.emva_leakage import sweep_steps_only

        try:
            # the leakage model's own account (no held-out choice of a simpler model)
            calibration = calibrate(sweep_steps_only(sweep), method="joint", **LEAKAGE_ACCOUNT)
        except DataFormatError as exc:
            return res, None, f"not computed: the sweep cannot calibrate the leakage model ({exc})"
    return res, leakage_effects(sweep, res, calibration), None
