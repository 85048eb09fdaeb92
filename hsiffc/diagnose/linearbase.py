"""The linear base model of diagnose and what both base models share.

:class:`LinearBase` is ``Y = dark + (g r + dc) t`` per pixel, solved in closed form by
:func:`weighted_line`. :class:`BaseModel` is the interface part both base models have in common
(the dark-current column and its measurement by :func:`dark_current_from_darks`); the leakage
base and the overview of the two are in :mod:`hsiffc.diagnose.bases`, which also re-exports
everything here. Arrays are (P, S): P pixels, S steps.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BaseModel", "LinearBase", "dark_current_from_darks", "weighted_line"]


def weighted_line(x, z, w):
    """Per row, the weighted least-squares line ``z = intercept + slope x``; arrays (P, S).

    Parameters
    ----------
    x, z, w : ndarray, (P, S)
        Abscissae, values and weights (0 leaves a sample out).

    Returns
    -------
    slope, intercept : ndarray of float64, (P,)
        0 where the line is undefined.
    ok : ndarray of bool, (P,)
        False where x does not vary.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.array([[0.0, 1.0, 2.0]])
    >>> slope, icpt, ok = weighted_line(x, 3 + 2 * x, np.ones_like(x))
    >>> slope.round(12).tolist(), icpt.round(12).tolist(), ok.tolist()
    ([2.0], [3.0], [True])
    """
    sw, sx, sz = w.sum(1), (w * x).sum(1), (w * z).sum(1)
    sxx, sxz = (w * x * x).sum(1), (w * x * z).sum(1)
    det = sw * sxx - sx ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (sw * sxz - sx * sz) / det
        icpt = (sz - slope * sx) / sw
    ok = np.isfinite(slope) & np.isfinite(icpt) & (det > 1e-12 * np.maximum(sw * sxx, 1e-300))
    return np.where(ok, slope, 0.0), np.where(ok, icpt, 0.0), ok


def dark_current_from_darks(y, t, r, valid, w):
    """Per-pixel dark current (P,) in DN/ms: the weighted slope of the dark samples (r = 0)
    against exposure; 0 where they do not span two exposures.

    Parameters
    ----------
    y : ndarray, (P, S), DN
        Step means.
    t : ndarray, (S,), ms
        Exposures.
    r : ndarray, (S,)
        Relative light rates (0 marks the dark samples).
    valid : ndarray of bool, (P, S)
        Samples to use.
    w : ndarray, (P, S)
        Weights.

    Returns
    -------
    ndarray of float64, (P,), DN/ms
    """
    wd = np.where(valid & (np.broadcast_to(r, y.shape) == 0), w, 0.0)
    return weighted_line(np.broadcast_to(t, y.shape), np.where(wd > 0, y, 0.0), wd)[0]


class BaseModel:
    """What the two base models share: the dark-current column and its measurement.

    Subclasses set ``name``, ``n_core`` (parameters besides the dark current) and
    ``describe``, and keep the dark current ``dc`` (DN/ms) in the last column of theta.

    Parameters
    ----------
    dark_current : bool
        Whether the dark current ``dc`` (DN/ms) is fitted (from the dark samples) or held.
    """

    n_core = 0

    def __init__(self, dark_current: bool):
        self.dark_current = bool(dark_current)

    @property
    def n_params(self):
        """Parameters fitted per pixel: ``n_core``, plus 1 with the dark current."""
        return self.n_core + int(self.dark_current)

    def dc(self, theta):
        """Dark current (P, 1) in DN/ms: the last column of theta.

        Parameters
        ----------
        theta : ndarray, (P, n)
            Parameters per pixel.

        Returns
        -------
        ndarray, (P, 1), DN/ms
        """
        return theta[:, -1:]

    def with_dc(self, jac, t):
        """Append the dark-current column dY/d(dc) ~ t when it is part of the base.

        Parameters
        ----------
        jac : ndarray, (P, S, m)
            Jacobian of the other parameters.
        t : ndarray, (S,), ms
            Exposures.

        Returns
        -------
        ndarray, (P, S, m) or (P, S, m + 1)
        """
        if not self.dark_current:
            return jac
        return np.concatenate([jac, np.broadcast_to(t, jac.shape[:2])[..., None]], axis=-1)

    def measure_dc(self, y, t, r, valid, w, theta0):
        """Dark current per pixel: measured from the dark samples (clipped at 0) when it is
        part of the base, otherwise the one held in ``theta0``.

        Parameters
        ----------
        y : ndarray, (P, S), DN
            Step means.
        t : ndarray, (S,), ms
            Exposures.
        r : ndarray, (S,)
            Relative light rates (0 marks the dark samples).
        valid : ndarray of bool, (P, S)
            Samples to use.
        w : ndarray, (P, S)
            Weights.
        theta0 : ndarray, (P, n)
            Current parameters (last column: the dark current held).

        Returns
        -------
        ndarray of float64, (P,), DN/ms
        """
        if not self.dark_current:
            return theta0[:, -1]
        return np.clip(dark_current_from_darks(y, t, r, valid, w), 0.0, None)


class LinearBase(BaseModel):
    """``Y = dark + (g r + dc) t`` per pixel; theta (P, 3) = (g, dark, dc).

    Parameters
    ----------
    dark_current : bool
        Whether the dark current ``dc`` (DN/ms) is fitted (from the dark samples) or held.
    """

    name = "linear"
    n_core = 2
    describe = "linear response with a dark level (no leakage), per pixel (k, d)"

    def evaluate(self, theta, t, r):
        """Model (P, S), Jacobian (P, S, n), light rate k (P, S), dY/dt (P, S), dY/dln g.

        Parameters
        ----------
        theta : ndarray, (P, 3)
            (g, dark DN, dark current DN/ms) per pixel.
        t : ndarray, (S,), ms
            Exposures.
        r : ndarray, (S,)
            Relative light rates (0 for darks).

        Returns
        -------
        model, jac, k, dydt, dydlng : ndarrays
            (P, S) DN, (P, S, n), (P, S) DN/ms, (P, S) DN/ms, (P, S) DN.
        """
        g, d, dc = theta[:, 0:1], theta[:, 1:2], theta[:, 2:3]
        u = np.broadcast_to(r * t, (theta.shape[0], np.size(t)))
        m = d + g * u + dc * t
        jac = self.with_dc(np.stack([u, np.ones_like(m)], axis=-1), t)
        k = np.broadcast_to(g * r, m.shape)
        return m, jac, k, k + dc, g * u

    def predict(self, theta, t, r):
        """Model response (P, S) in DN.

        Parameters
        ----------
        theta : ndarray, (P, 3)
            (g, dark DN, dark current DN/ms) per pixel.
        t : ndarray, (S,), ms
            Exposures.
        r : ndarray, (S,)
            Relative light rates (0 for darks).

        Returns
        -------
        ndarray, (P, S), DN
        """
        return self.evaluate(theta, t, r)[0]

    def dark(self, theta):
        """Dark level (P, 1) in DN.

        Parameters
        ----------
        theta : ndarray, (P, 3)
            (g, dark DN, dark current DN/ms) per pixel.

        Returns
        -------
        ndarray, (P, 1), DN
        """
        return theta[:, 1:2]

    def fit(self, y, t, r, valid, w, theta0=None, max_iter=None):
        """Weighted least squares per pixel (closed form).

        Parameters
        ----------
        y : ndarray, (P, S), DN
            Step means of P pixels at S samples.
        t : ndarray, (S,), ms
            Exposure of each sample.
        r : ndarray, (S,)
            Relative light rate of each sample (0 for darks).
        valid : ndarray of bool, (P, S)
            Samples to use.
        w : ndarray, (P, S)
            Weights (inverse variances, 1/DN^2).
        theta0 : ndarray, (P, 3), optional
            Kept where the line is undefined (default zeros).
        max_iter : None
            Unused (closed form); accepted for the common interface.

        Returns
        -------
        ndarray, (P, 3)
        """
        if theta0 is None:
            theta0 = np.zeros((y.shape[0], 3))
        dc = self.measure_dc(y, t, r, valid, w, theta0)
        ww = np.where(valid, w, 0.0)
        g, d, ok = weighted_line(np.broadcast_to(r * t, y.shape),
                                 np.where(valid, y - dc[:, None] * t, 0.0), ww)
        new = np.column_stack([g, d, dc])
        return np.where(ok[:, None], new, theta0)

    def start(self, y, t, r, valid, w, dc0=None):
        """The fit from zeros (the linear model needs no start).

        Parameters
        ----------
        y : ndarray, (P, S), DN
            Step means of P pixels at S samples.
        t : ndarray, (S,), ms
            Exposure of each sample.
        r : ndarray, (S,)
            Relative light rate of each sample (0 for darks).
        valid : ndarray of bool, (P, S)
            Samples to use.
        w : ndarray, (P, S)
            Weights (inverse variances, 1/DN^2).
        dc0 : ndarray, (P,), optional
            Dark current (DN/ms) to hold when it is not fitted.

        Returns
        -------
        ndarray, (P, 3)
        """
        theta0 = np.zeros((y.shape[0], 3))
        if dc0 is not None:
            theta0[:, 2] = dc0
        return self.fit(y, t, r, valid, w, theta0)

    def restart(self, y, t, r, valid, w, theta_warm, max_iter=None):
        """The fit again (closed form: no start to improve).

        Parameters
        ----------
        y : ndarray, (P, S), DN
            Step means of P pixels at S samples.
        t : ndarray, (S,), ms
            Exposure of each sample.
        r : ndarray, (S,)
            Relative light rate of each sample (0 for darks).
        valid : ndarray of bool, (P, S)
            Samples to use.
        w : ndarray, (P, S)
            Weights (inverse variances, 1/DN^2).
        theta_warm : ndarray, (P, 3)
            Previous parameters.
        max_iter : None
            Unused.

        Returns
        -------
        ndarray, (P, 3)
        """
        return self.fit(y, t, r, valid, w, theta_warm)  # closed form: no start to improve
