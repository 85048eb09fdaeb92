"""The base models diagnose fits per pixel before any candidate effect.

Two families share one interface (``start``, ``fit``, ``evaluate``):

- :class:`LeakageBase`, the paper's model ``dY/dt = k - a e^{bY}`` with ``k = g r + dc``:
  per pixel (ln g, ln a, ln b, dark), fitted with the calibration's public fit
  (:func:`hsiffc.calibrate.fit_pixels`) from two starts (the calibration's own and the linear
  model's), keeping the better one per pixel, so the leakage base never fits worse than a
  straight line on the same samples;
- :class:`LinearBase`, ``Y = dark + (g r + dc) t``: per pixel (g, dark), solved in closed form.

The last column of theta is the per-pixel dark current ``dc`` (DN/ms). With ``dark_current``
true it is part of the base: measured from the dark samples of whatever the base is fitted to
(the data less the effects fitted so far, so an effect that also shows in the darks, such as
lag or drift, is not mistaken for dark current) and its column enters the Jacobian; otherwise
it stays 0 (see :func:`hsiffc.diagnose.design.dark_model`). Arrays are (P, S): P pixels, S
steps.
"""

from __future__ import annotations

import numpy as np

from ..calibrate import fit_pixels, initial_guess, model_and_jacobian, predict

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


LINEAR_LN_A = -60.0  # ln a (DN/ms) of a leakage parameter set that is a straight line in practice
LINEAR_LN_B = float(np.log(0.01))


class _Base:
    n_core = 0

    def __init__(self, dark_current: bool):
        self.dark_current = bool(dark_current)

    @property
    def n_params(self):
        return self.n_core + int(self.dark_current)

    def dc(self, theta):
        return theta[:, -1:]

    def with_dc(self, jac, t):
        """Append the dark-current column dY/d(dc) ~ t when it is part of the base."""
        if not self.dark_current:
            return jac
        return np.concatenate([jac, np.broadcast_to(t, jac.shape[:2])[..., None]], axis=-1)

    def measure_dc(self, y, t, r, valid, w, theta0):
        if not self.dark_current:
            return theta0[:, -1]
        return np.clip(dark_current_from_darks(y, t, r, valid, w), 0.0, None)


class LinearBase(_Base):
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


class LeakageBase(_Base):
    """The paper's leakage model per pixel; theta (P, 5) = (ln g, ln a, ln b, dark, dc).

    Parameters
    ----------
    dark_current : bool
        Whether the dark current ``dc`` (DN/ms) is fitted (from the dark samples) or held.
    """

    name = "leakage"
    n_core = 4
    describe = "leakage model dY/dt = k - a exp(bY), per pixel (k, a, b, d)"

    def evaluate(self, theta, t, r):
        """Model (P, S), Jacobian (P, S, n), light rate k (P, S), dY/dt (P, S), dY/dln g.

        Parameters
        ----------
        theta : ndarray, (P, 5)
            (ln g, ln a, ln b, dark DN, dark current DN/ms) per pixel.
        t : ndarray, (S,), ms
            Exposures.
        r : ndarray, (S,)
            Relative light rates (0 for darks).

        Returns
        -------
        model, jac, k, dydt, dydlng : ndarrays
            (P, S) DN, (P, S, n), (P, S) DN/ms, (P, S) DN/ms, (P, S) DN.
        """
        dc = theta[:, 4:5]
        m, jac = model_and_jacobian(theta[:, :4], t, r, dc)
        kl = np.broadcast_to(np.exp(theta[:, 0:1]) * r, m.shape)
        with np.errstate(over="ignore"):
            leak = np.exp(np.minimum(theta[:, 1:2] + np.exp(theta[:, 2:3]) * m, 700.0))
        return m, self.with_dc(jac, t), kl, kl + dc - leak, jac[..., 0]

    def predict(self, theta, t, r):
        """Model response (P, S) in DN.

        Parameters
        ----------
        theta : ndarray, (P, 5)
            (ln g, ln a, ln b, dark DN, dark current DN/ms) per pixel.
        t : ndarray, (S,), ms
            Exposures.
        r : ndarray, (S,)
            Relative light rates (0 for darks).

        Returns
        -------
        ndarray, (P, S), DN
        """
        return predict(theta[:, :4], t, r, theta[:, 4:5])

    def dark(self, theta):
        """Dark level (P, 1) in DN.

        Parameters
        ----------
        theta : ndarray, (P, 5)
            (ln g, ln a, ln b, dark DN, dark current DN/ms) per pixel.

        Returns
        -------
        ndarray, (P, 1), DN
        """
        return theta[:, 3:4]

    def _cost(self, theta, y, t, r, valid, w):
        res = np.where(valid, y - self.predict(theta, t, r), 0.0)
        c = (w * res * res).sum(axis=1)
        return np.where(np.isfinite(c), c, np.inf)

    def from_linear(self, lin):
        """Leakage parameters that reproduce a linear fit (leakage switched off).

        Parameters
        ----------
        lin : ndarray, (P, 3)
            :class:`LinearBase` parameters (g, dark, dc).

        Returns
        -------
        ndarray, (P, 5)
        """
        g = np.clip(lin[:, 0], 1e-9, None)
        return np.column_stack([np.log(g), np.full(len(g), LINEAR_LN_A),
                                np.full(len(g), LINEAR_LN_B), lin[:, 1], lin[:, 2]])

    def fit(self, y, t, r, valid, w, theta0, max_iter=15):
        """Levenberg-Marquardt per pixel from ``theta0``; a pixel never ends worse than it
        started.

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
        theta0 : ndarray, (P, 5)
            Start.
        max_iter : int
            Iterations per pixel.

        Returns
        -------
        ndarray, (P, 5)
        """
        dc = self.measure_dc(y, t, r, valid, w, theta0)
        fit = fit_pixels(y, t, r, valid, w, theta0[:, :4], dark_current=dc, max_iter=max_iter)
        with np.errstate(divide="ignore", invalid="ignore"):
            theta = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark, dc])
        theta = np.where(np.all(np.isfinite(theta), axis=1)[:, None], theta, theta0)
        # never worse than where it started (a diverging pixel keeps its start)
        worse = self._cost(theta, y, t, r, valid, w) > self._cost(theta0, y, t, r, valid, w)
        return np.where(worse[:, None], theta0, theta)

    def restart(self, y, t, r, valid, w, theta_warm, max_iter=15):
        """Refit from the warm parameters and from fresh starts; per pixel the best. Used when
        an effect removed from the data is large enough to have distorted the warm start.

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
        theta_warm : ndarray, (P, 5)
            Previous parameters.
        max_iter : int
            Iterations per pixel.

        Returns
        -------
        ndarray, (P, 5)
        """
        warm = self.fit(y, t, r, valid, w, theta_warm, max_iter=max_iter)
        fresh = self.start(y, t, r, valid, w, theta_warm[:, -1])
        better = self._cost(fresh, y, t, r, valid, w) < self._cost(warm, y, t, r, valid, w)
        return np.where(better[:, None], fresh, warm)

    def start(self, y, t, r, valid, w, dc0=None, max_iter=40):
        """Fit from the calibration's start and from the linear model; per pixel the better.

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
        max_iter : int
            Iterations per pixel.

        Returns
        -------
        ndarray, (P, 5)
        """
        lin = LinearBase(self.dark_current).start(y, t, r, valid, w, dc0)
        from_lin = self.from_linear(lin)
        try:
            guess = initial_guess(y, t, r, valid, w, lin[:, 2])
            guess = np.column_stack([guess, lin[:, 2]])
        except (FloatingPointError, ValueError):
            guess = from_lin
        guess = np.where(np.all(np.isfinite(guess), axis=1)[:, None], guess, from_lin)
        a = self.fit(y, t, r, valid, w, guess, max_iter=max_iter)
        b = self.fit(y, t, r, valid, w, from_lin, max_iter=max_iter)
        better_b = self._cost(b, y, t, r, valid, w) < self._cost(a, y, t, r, valid, w)
        return np.where(better_b[:, None], b, a)


BASES = {"leakage": LeakageBase, "linear": LinearBase}
