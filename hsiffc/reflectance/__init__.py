"""Reflectance factor from a white reference panel, dark frames and, optionally, the leakage model.

What most users of a snapshot-mosaic camera want from a frame is the scene's reflectance: the
scene divided by a white panel of known reflectance, both less the dark, band by band. On a
leaky sensor the response is not linear in the light, so a bright panel and a darker scene are
not related by one gain per pixel: the reflectance is computed from the light rates recovered
through the calibrated leakage model (``method="model"``), or, without a calibration, from DN
less dark per ms (``method="ratio"``); ``"auto"`` is the model with a calibration, else the
ratio. The methods are registered in :data:`REFLECTANCE_METHODS` (what each divides, whether it
needs a calibration; :func:`resolve_method` says what ``"auto"`` runs as). The
:class:`~hsiffc.stages.reflectance.Reflectance` stage wraps these functions.

The checks (:func:`reference_warnings`, :func:`scene_brightness` and the warnings) catch what a
field campaign gets wrong with a white reference. Every check returns its figures per band
(kept in the fitted stage and in each frame's history) and, when the data break it, issues one
warning that says what was measured, what it costs and what to do. Good data give no warning.

Reference (at fit):

- too dark: the panel's signal is a small part of the sensor's range, or its single-frame
  signal-to-noise ratio is low. One DN of scene noise becomes ``R_panel / level`` of
  reflectance, so a reference at 12 DN turns every DN of noise into 8 % reflectance;
- saturated (at the ADC's full scale, or at a full well below it: no shot noise left), or in
  strong leakage (median model alpha over a threshold): its response is no
  longer linear in the light, so a plain ratio overestimates every target darker than it
  (by the charge the panel's response lost to leakage);
- too few frames for the requested precision: the reference's own noise, ``1 / (SNR sqrt(N))``,
  is printed into every reflectance as a fixed pattern.

Scene (at transform):

- brighter than the reference: most good pixels above ``max_reflectance``: the scene was
  probably recorded at another exposure, gain or light than the panel;
- exposure or gain different from the reference's: the rate is scaled by the exposure (said so),
  a gain difference is not corrected.
"""

from ._checks import (ExposureMismatchWarning, GainMismatchWarning, ReferenceLeakageWarning,
                      ReferenceSaturatedWarning, ReflectanceWarning,
                      SceneBrighterThanReferenceWarning, TooFewReferenceFramesWarning,
                      WhiteReferenceTooDarkWarning, reference_warnings, scene_brightness)
from ._maths import (WhiteReference, band_fraction, band_median, reflectance_factor,
                     white_reference)
from ._methods import REFLECTANCE_METHODS, Rates, ReflectanceMethod, resolve_method
from ._panel import panel_per_band, read_panel_spectrum
from ._target import TargetReport, target_report

__all__ = ["REFLECTANCE_METHODS", "ReflectanceMethod", "Rates", "resolve_method",
           "WhiteReference", "white_reference", "reflectance_factor", "band_median",
           "band_fraction", "panel_per_band", "read_panel_spectrum", "TargetReport",
           "target_report", "reference_warnings", "scene_brightness", "ReflectanceWarning",
           "WhiteReferenceTooDarkWarning", "ReferenceSaturatedWarning",
           "ReferenceLeakageWarning", "TooFewReferenceFramesWarning",
           "SceneBrighterThanReferenceWarning", "ExposureMismatchWarning",
           "GainMismatchWarning"]
