"""Reflectance factor from a white reference panel, dark frames and, optionally, the leakage model.

What most users of a snapshot-mosaic camera want from a frame is the scene's reflectance: the
scene divided by a white panel of known reflectance, both less the dark, band by band. On a
leaky sensor the response is not linear in the light, so a bright panel and a darker scene are
not related by one gain per pixel: the reflectance is computed from the light rates recovered
through the calibrated leakage model (``method="model"``), or, without a calibration, from DN
less dark per ms (``method="ratio"``). The :class:`~hsiffc.stages.reflectance.Reflectance`
stage wraps these functions; the checks a field campaign needs are in :mod:`._checks`.
"""

from ._checks import (ExposureMismatchWarning, GainMismatchWarning, ReferenceLeakageWarning,
                      ReferenceSaturatedWarning, ReflectanceWarning,
                      SceneBrighterThanReferenceWarning, TooFewReferenceFramesWarning,
                      WhiteReferenceTooDarkWarning, reference_warnings, scene_brightness)
from ._maths import (WhiteReference, band_fraction, band_median, reflectance_factor,
                     white_reference)
from ._panel import panel_per_band, read_panel_spectrum
from ._target import TargetReport, target_report

__all__ = ["WhiteReference", "white_reference", "reflectance_factor", "band_median",
           "band_fraction", "panel_per_band", "read_panel_spectrum", "TargetReport",
           "target_report", "reference_warnings", "scene_brightness", "ReflectanceWarning",
           "WhiteReferenceTooDarkWarning", "ReferenceSaturatedWarning",
           "ReferenceLeakageWarning", "TooFewReferenceFramesWarning",
           "SceneBrighterThanReferenceWarning", "ExposureMismatchWarning",
           "GainMismatchWarning"]
