"""The fixed-pattern floor a calibration sweep sets for the model-based flat field.

A model-based correction (:mod:`hsiffc.flatfield.model_based`) divides each pixel's linearised response by
its fitted responsivity g after inverting the fitted leakage (a, b) from the fitted dark level.
All of them come from one joint fit per pixel over the sweep, so their errors are correlated:
on a typical sweep ln a and ln b are anticorrelated at -0.99 and more, since the bent samples
fix the response where they are, not a and b separately. The calibration stores each
parameter's sigma but not these correlations, and without them the error where leakage bends
the response cannot be propagated (the sigmas alone overstate it many times, and leaving a and
b out, as :func:`hsiffc.flatfield.model_based.correction_uncertainty` does, understates it).

This module computes that floor from the sweep's *design* instead: the Fisher information of
the per-pixel model ``Y = response(t, g r + dc, a, b, d)`` over the sweep's steps (exposure t,
relative light r, frames per step) with the sensor's noise (read noise, shot noise through the
conversion gain, quantisation; clipped samples carry no information). Its inverse is the
Cramer-Rao bound of the parameters (ln g, ln a, ln b, d, dc); propagated through the inversion
at a response Y it is the smallest relative error of a corrected pixel any fit of that sweep can
reach: the fixed-pattern floor, per pixel, where the correction rests on the sweep alone (model
alpha above ``flat_alpha_percent``; below it a flat stack can lower it further).

On a simulated sensor model_ffc's fixed pattern reaches this floor and does not beat it
(``tests/flatfield/test_model_ffc.py`` checks both), where a two-point FFC stays well above it;
the floor
rises with alpha because the sweep pins a and b only through its few bent samples.

The arrays are (H, W, 5, 5) float64: use a crop or a pixel subset of large sensors.
"""

from __future__ import annotations

import numpy as np

from ..leakage import model

__all__ = ["PARAMETERS", "parameter_covariance", "sweep_floor"]

#: the parameters of the covariance, in its order
PARAMETERS = ("ln_g", "ln_a", "ln_b", "dark_dn", "dark_current_dn_per_ms")


def parameter_covariance(exposure_ms, light_level, responsivity, a, b, dark, dark_current, *,
                         n_frames=2, read_noise_dn: float, conversion_gain_dn_per_e: float,
                         full_scale_dn: float, full_well_dn=None) -> np.ndarray:
    """Cramer-Rao covariance of (ln g, ln a, ln b, dark, dark current) per pixel from a sweep.

    Parameters
    ----------
    exposure_ms, light_level : (S,) array_like
        Every step of the sweep: exposure (ms) and relative light rate r (the light rate is
        ``responsivity * r``; 0 for a dark step).
    responsivity, a, b, dark, dark_current : (H, W) array_like
        The pixel model where the bound is taken (a calibration's arrays, or the truth).
    n_frames : int or (S,) array_like
        Frames per step (the step mean has ``1 / n_frames`` of a frame's noise variance).
    read_noise_dn, conversion_gain_dn_per_e : float
        Temporal noise of one frame: ``read^2 + 1/12 + gain * (Y - dark)`` DN^2.
    full_scale_dn : float
        Samples at or above it (clipped) carry no information.
    full_well_dn : float, optional
        Signal above dark at which the pixel's well is full (no information above either).

    Returns
    -------
    (H, W, 5, 5) float64
        Covariance in the order of :data:`PARAMETERS` (NaN where the design does not
        determine the parameters).
    """
    t_s = np.atleast_1d(np.asarray(exposure_ms, np.float64))
    r_s = np.broadcast_to(np.asarray(light_level, np.float64), t_s.shape)
    n_s = np.broadcast_to(np.asarray(n_frames, np.float64), t_s.shape)
    g, a64, b64, d, dc = (np.asarray(v, np.float64) for v in (responsivity, a, b, dark,
                                                            dark_current))
    fisher = np.zeros(g.shape + (5, 5))
    for t, r, n in zip(t_s, r_s, n_s):
        if not t > 0:
            continue
        k = g * r + dc
        y, yk, ya, yb, yd = model.response_and_gradient(t, np.maximum(k, 1e-300), a64, b64, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            dk = np.where(k > 0, yk / k, t)  # dY/dk (DN per DN/ms): t at zero rate
        jac = np.stack([dk * g * r, ya, yb, yd, dk], axis=-1)
        signal = np.clip(y - d, 0.0, None)
        ok = np.isfinite(y) & (y < full_scale_dn)
        if full_well_dn is not None:
            ok &= signal < full_well_dn
        var = read_noise_dn ** 2 + 1.0 / 12.0 + conversion_gain_dn_per_e * signal
        w = np.where(ok, n / var, 0.0)
        fisher += w[..., None, None] * jac[..., :, None] * jac[..., None, :]
    # scale to unit diagonal before inverting (the parameters differ by orders of magnitude)
    scale = np.sqrt(np.einsum("...ii->...i", fisher))
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = fisher / (scale[..., :, None] * scale[..., None, :])
    bad = ~np.isfinite(unit).all(axis=(-2, -1)) | (np.linalg.cond(
        np.where(np.isfinite(unit), unit, np.eye(5))) > 1e12)
    inv = np.linalg.inv(np.where(bad[..., None, None], np.eye(5), unit))
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = inv / (scale[..., :, None] * scale[..., None, :])
    return np.where(bad[..., None, None], np.nan, cov)


def sweep_floor(response, exposure_ms: float, covariance, a, b, dark, dark_current):
    """Smallest relative error (fraction, 1 sigma) of each pixel corrected from the sweep alone.

    The corrected value is ``k(Y; a, b, dark + dc t) t / g`` (:func:`hsiffc.flatfield.model_based.
    model_ffc_apply` with the sweep's factor); its gradient in (ln g, ln a, ln b, dark, dc)
    at the response Y, through the covariance of :func:`parameter_covariance`.

    Parameters
    ----------
    response : (H, W) array_like, DN
        Raw response Y (a uniform scene's, or any frame's).
    exposure_ms : float, ms (> 0)
    covariance : (H, W, 5, 5) array_like
    a, b, dark, dark_current : (H, W) array_like
        The calibration's (the parameters the correction inverts with).

    Returns
    -------
    (H, W) float64 (NaN where the response cannot be inverted or the covariance is unknown)
    """
    y = np.asarray(response, np.float64)
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    start = np.asarray(dark, np.float64) + np.asarray(dark_current, np.float64) * exposure_ms
    inv = model.invert_response(y, exposure_ms, a64, b64, start)
    _, yk, ya, yb, yd = model.response_and_gradient(exposure_ms, np.maximum(inv.k, 1e-300),
                                                    a64, b64, start)
    with np.errstate(divide="ignore", invalid="ignore"):
        grad = np.stack([-np.ones_like(y), -ya / yk, -yb / yk, -yd / yk,
                         -exposure_ms * yd / yk], axis=-1)
        var = np.einsum("...i,...ij,...j->...", grad, np.asarray(covariance, np.float64), grad)
    ok = (inv.k > 0) & (inv.flags == 0) & np.isfinite(var) & (var >= 0)
    return np.where(ok, np.sqrt(np.where(ok, var, 0.0)), np.nan)
