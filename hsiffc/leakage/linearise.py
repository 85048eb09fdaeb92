"""Leakage linearisation (array function): the light rate behind each leaking response.

Beyond the paper: the calibrated model ``dY/dt = k - a e^{bY}`` is inverted per pixel, so a
response bent by leakage still gives its light rate k. The closer to dynamic saturation, the
more noise is amplified (the error of k grows like ``1 / (1 - alpha)`` with the model alpha),
so responses over an alpha limit are flagged LEAKAGE (their value is still the best estimate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import model
from ..data.dq import DQ, DQ_DTYPE
from .validity import alpha_model


@dataclass(frozen=True)
class Linearised:
    """Result of :func:`linearise`.

    Attributes
    ----------
    light_rate : (H, W) float64, DN/ms
        Light rate k less the dark current (>= 0).
    dq : (H, W) uint32
        Inversion flags (BELOW_DARK, SATURATED, UNREACHABLE, NOT_CONVERGED) and LEAKAGE where
        the model alpha is over the limit or undefined.
    alpha : (H, W) float32, percent
        Model alpha (:func:`hsiffc.leakage.validity.alpha_model`).
    """

    light_rate: np.ndarray
    dq: np.ndarray
    alpha: np.ndarray


def linearise(response, exposure_ms: float, a, b, dark_dn, dark_current, *,
              full_scale_dn=None, alpha_limit_percent: float = 90.0) -> Linearised:
    """Invert the leakage model per pixel.

    Parameters
    ----------
    response : (H, W) array_like, DN
        Raw response Y.
    exposure_ms : float, ms
    a, b, dark_dn, dark_current : (H, W) array_like
        Calibrated leakage amplitude (DN/ms), exponent (1/DN), dark level at zero exposure (DN)
        and dark current (DN/ms).
    full_scale_dn : float, optional
    alpha_limit_percent : float

    Returns
    -------
    Linearised
        ``light_rate * exposure_ms`` is the response without leakage above the dark.
    """
    if not (np.isfinite(exposure_ms) and exposure_ms > 0):
        raise ValueError(f"exposure_ms must be a finite time > 0 ms to linearise, got "
                         f"{exposure_ms!r}: at 0 ms no light is integrated, so there is no "
                         "light rate to recover; leave such frames (bias frames) out")
    y = np.asarray(response, np.float64)
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    inv = model.invert_response(y, exposure_ms, a64, b64, np.asarray(dark_dn, np.float64),
                                full_scale=full_scale_dn)
    alpha = alpha_model(y, exposure_ms, a64, b64, dark_dn, inversion=inv)
    dq = inv.flags.astype(DQ_DTYPE)
    dq[~(alpha <= alpha_limit_percent)] |= DQ_DTYPE(DQ.LEAKAGE)
    k_light = np.maximum(inv.k - np.asarray(dark_current, np.float64), 0.0)
    return Linearised(np.where(np.isfinite(k_light), k_light, 0.0), dq, alpha)
