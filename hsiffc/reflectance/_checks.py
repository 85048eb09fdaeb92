"""The checks of a white reference and of a scene, with numbers (described in
:mod:`hsiffc.reflectance`)."""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..data.mosaic import band_labels
from ..errors import HsiffcWarning, band_figures
from ._methods import REFLECTANCE_METHODS

__all__ = ["ReflectanceWarning", "WhiteReferenceTooDarkWarning", "ReferenceSaturatedWarning",
           "ReferenceLeakageWarning", "TooFewReferenceFramesWarning",
           "SceneBrighterThanReferenceWarning", "ExposureMismatchWarning",
           "GainMismatchWarning", "reference_warnings", "scene_brightness"]


class ReflectanceWarning(HsiffcWarning):
    """Base class of the reflectance checks' warnings."""


class WhiteReferenceTooDarkWarning(ReflectanceWarning):
    """The white reference's signal is low: its noise and the scene's are amplified."""


class ReferenceSaturatedWarning(ReflectanceWarning):
    """Part of the white reference is at full scale: those reflectances are wrong."""


class ReferenceLeakageWarning(ReflectanceWarning):
    """The white reference is in strong leakage (model alpha over the threshold)."""


class TooFewReferenceFramesWarning(ReflectanceWarning):
    """The reference's averaged noise exceeds the requested precision."""


class SceneBrighterThanReferenceWarning(ReflectanceWarning):
    """Most of a scene is brighter than the white panel."""


class ExposureMismatchWarning(ReflectanceWarning):
    """Scene and reference exposures differ: the reflectance was scaled by the exposure."""


class GainMismatchWarning(ReflectanceWarning):
    """Scene and reference were recorded at different gains (not corrected)."""


def _worst(values, idx, *, lowest: bool):
    """``idx`` ordered worst first."""
    return sorted(idx, key=lambda i: values[i], reverse=not lowest)


def reference_warnings(report: dict, *, min_level_fraction: float, min_snr: float,
                       precision_percent: float, max_saturated_percent: float,
                       reference_alpha_percent: float, method: str,
                       stacklevel: int = 3) -> list[str]:
    """Issue the reference's warnings from its per-band figures; returns their texts.

    Parameters
    ----------
    report : dict
        Per-band lists (NaN or None where not measured): ``level_dn`` (median signal above
        dark), ``range_dn`` (full scale less dark), ``snr_frame`` (single-frame SNR of the
        rate), ``saturated_percent``, ``alpha_percent`` (median model alpha; None without a
        calibration), ``loss_percent`` (charge the response lost to leakage), ``panel``; and
        ``n_frames``, ``exposure_ms``; optionally ``temporal_var_dn2`` and ``dark_var_dn2``
        (median temporal variance of the panel's and the dark's frames, DN^2) and
        ``band_labels`` (each band's label, :meth:`hsiffc.data.frame.Frame.band_labels`).
    min_level_fraction, min_snr, precision_percent, max_saturated_percent,
    reference_alpha_percent : float
        Thresholds (the stage's parameters).
    method : str
        The method that ran (:func:`hsiffc.reflectance.resolve_method`), e.g. "model".

    Returns
    -------
    list of str
    """
    out = []

    def warn(category, text):
        out.append(text)
        warnings.warn(text, category, stacklevel=stacklevel + 1)

    t = report["exposure_ms"]
    n = int(report["n_frames"])
    level = np.asarray(report["level_dn"], float)
    rng = np.asarray([np.nan if v is None else v for v in report["range_dn"]], float)
    snr = np.asarray([np.nan if v is None else v for v in report["snr_frame"]], float)
    panel = np.asarray(report["panel"], float)
    nb = len(level)
    labels = report.get("band_labels") or band_labels(nb)

    def bands(idx, values, fmt):
        return band_figures(idx, values, fmt, labels=labels)

    frac = level / rng  # NaN where the values are not the sensor's DN (no level check)
    # a low SNR at a high level comes from leakage or saturation (their own checks), not darkness
    dark = [i for i in range(nb) if (frac[i] < min_level_fraction)
            or (snr[i] < min_snr and not frac[i] >= 0.5)]
    if dark:
        dark = _worst(frac, dark, lowest=True)
        gain = panel / np.maximum(level, 1e-9)
        amp = 0.5 * rng / np.maximum(level, 1e-9)
        snr_txt = ("not measured (one frame)" if n < 2 else
                   "single-frame SNR " + ", ".join(f"{snr[i]:.1f}" for i in dark[:6]))
        of_range = (", ".join(f"{100 * frac[i]:.1f} %" for i in dark[:6]) + " of the range"
                    if np.isfinite(frac[dark[0]]) else "virtual bands: not the sensor's DN")
        half = (f" ({amp[dark[0]]:.1f} x what a reference at half the range gives)"
                if np.isfinite(amp[dark[0]]) else "")
        cost = (f"Each DN of scene noise becomes {gain[dark[0]]:.3g} in reflectance{half} in "
                f"{labels[dark[0]]}" if level[dark[0]] > 0 else
                f"{labels[dark[0]]} has no signal above dark: its reflectance is meaningless")
        warn(WhiteReferenceTooDarkWarning,
             f"white reference ({t:g} ms) too dark in {len(dark)} of {nb} bands: "
             f"{bands(dark, level, '.1f')} DN above dark "
             f"({of_range}; asked for >= {100 * min_level_fraction:g} % and SNR >= "
             f"{min_snr:g}); {snr_txt}. "
             f"{cost}: lengthen the reference's exposure, light the panel better or "
             "open the aperture (same settings for the scenes)")
    sat = np.asarray(report["saturated_percent"], float)
    hit = [i for i in range(nb) if sat[i] > max_saturated_percent]
    if hit:
        hit = _worst(sat, hit, lowest=False)
        warn(ReferenceSaturatedWarning,
             f"white reference ({t:g} ms) saturated: {bands(hit, sat, '.2g')} % of the "
             f"pixels at full scale (allowed {max_saturated_percent:g} %); their reflectances "
             "are wrong and flagged SATURATED: shorten the reference's exposure or dim the "
             "light (and record the scenes at settings the panel does not saturate)")
    var_w, var_d = report.get("temporal_var_dn2"), report.get("dark_var_dn2")
    if var_w is not None and var_d is not None:
        var_w, var_d = (np.asarray([np.nan if v is None else v for v in x], float)
                        for x in (var_w, var_d))
        # at a full well the shot noise is gone: the panel is as quiet as the dark
        hit = [i for i in range(nb) if frac[i] > 0.3 and var_w[i] <= 2 * var_d[i]]
        if hit:
            warn(ReferenceSaturatedWarning,
                 f"white reference ({t:g} ms) stopped responding below full scale: "
                 f"{bands(hit, level, '.0f')} DN above dark with a temporal noise of "
                 f"{', '.join(f'{var_w[i]:.2g}' for i in hit[:6])} DN^2, no more than the "
                 f"dark's ({', '.join(f'{var_d[i]:.2g}' for i in hit[:6])} DN^2): no shot "
                 "noise, the pixels sit at a full well below the ADC's full scale (not flagged "
                 "SATURATED); every reflectance is overestimated: shorten the reference's "
                 "exposure or dim the light")
    alpha = report.get("alpha_percent")
    if alpha is not None:
        alpha = np.asarray([np.nan if v is None else v for v in alpha], float)
        loss = np.asarray([np.nan if v is None else v for v in report.get("loss_percent")
                           or [None] * nb], float)
        hit = [i for i in range(nb) if alpha[i] > reference_alpha_percent]
        if hit:
            hit = _worst(alpha, hit, lowest=False)
            i0 = hit[0]
            if not REFLECTANCE_METHODS[method].leakage_aware:  # a plain ratio
                cost = (f"its response lost {loss[i0]:.1f} % of its charge to leakage in "
                        f"{labels[i0]}, so a plain ratio overestimates dark targets by up to "
                        f"{100 * loss[i0] / max(100 - loss[i0], 1e-9):.1f} %: use the "
                        "leakage-aware method (method='model' with the calibration) or a "
                        "shorter reference exposure")
            else:
                cost = (f"the leakage model recovers its light rate (the response lost "
                        f"{loss[i0]:.1f} % of its charge in {labels[i0]}), with noise "
                        f"amplified about {1 / max(1 - alpha[i0] / 100, 1e-3):.2g} x: a shorter "
                        "reference exposure gives a more precise reference")
            warn(ReferenceLeakageWarning,
                 f"white reference ({t:g} ms) in strong leakage: median alpha "
                 f"{bands(hit, alpha, '.1f')} % (threshold {reference_alpha_percent:g} "
                 f"%); {cost}")
    if n < 2:
        warn(TooFewReferenceFramesWarning,
             f"one white-reference frame ({t:g} ms): its noise cannot be measured and is "
             "printed into every reflectance as a fixed pattern; record 10 or more frames of "
             "the panel")
    else:
        err = 100.0 / (snr * math.sqrt(n))
        hit = [i for i in range(nb) if err[i] > precision_percent]
        if hit:
            hit = _worst(err, hit, lowest=False)
            need = int(math.ceil(n * (err[hit[0]] / precision_percent) ** 2))
            warn(TooFewReferenceFramesWarning,
                 f"{n} white-reference frames ({t:g} ms) give a reference error of "
                 f"{bands(hit, err, '.2f')} % per pixel, above the requested "
                 f"{precision_percent:g} %; it is printed into every reflectance as a fixed "
                 f"pattern: record about {need} frames (or a brighter reference)")
    return out


def scene_brightness(reflectance, good, *, max_reflectance: float) -> tuple[float, float]:
    """Fraction of the good values above ``max_reflectance`` and their median reflectance.

    Returns
    -------
    fraction : float
        In [0, 1]; NaN when no value is good.
    median : float
        Median reflectance of the good values (NaN when none).
    """
    v = np.asarray(reflectance)[np.asarray(good, bool)]
    if not v.size:
        return math.nan, math.nan
    return float(np.count_nonzero(v > max_reflectance) / v.size), float(np.median(v))
