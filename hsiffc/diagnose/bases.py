"""The base models diagnose fits per pixel before any candidate effect.

Three share one interface (``start``, ``fit``, ``evaluate``):

- :class:`LeakageBase`, the paper's model ``dY/dt = k - a e^{bY}`` with ``k = g r + dc``
  (or, with ``dark_leaks=False``, ``k = g r`` and the dark signal ``dc t`` added after the
  leakage: charge collected outside the photodiode, which does not leak):
  per pixel (ln g, ln a, ln b, dark), fitted with the calibration's public fit
  (:func:`hsiffc.calibrate.fit_pixels`) from two starts (the calibration's own and the linear
  model's), keeping the better one per pixel, so the leakage base never fits worse than a
  straight line on the same samples;
- :class:`SharedLeakageBase`, the same model with one leakage shape for the sensor: a and b
  shared by every pixel, (ln g, dark) per pixel, fitted jointly (Levenberg-Marquardt on the
  Schur complement of the per-pixel blocks): as many parameters as a linear response with a
  readout nonlinearity shared by the sensor, the alternative it is compared with;
- :class:`LinearBase`, ``Y = dark + (g r + dc) t``: per pixel (g, dark), solved in closed form
  by :func:`weighted_line`.

:class:`BaseModel` is what both have in common (the dark-current column and its measurement by
:func:`dark_current_from_darks`).

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

__all__ = [
    "BASES",
    "LINEAR_LN_A",
    "LINEAR_LN_B",
    "BaseModel",
    "LeakageBase",
    "LinearBase",
    "SharedLeakageBase",
    "dark_current_from_darks",
    "weighted_line",
]

SHARED_MAX_ITER = 12  # accepted steps of one shared fit at most (it starts warm in the search)
SHARED_TOL = 1e-2  # fall of the weighted cost (chi-square units) that ends the shared fit
REFINE_ITER = 8  # Levenberg-Marquardt steps on the model that stays above the dark level
LINEAR_LN_A = -60.0  # ln a (DN/ms) of a leakage parameter set that is a straight line in practice
LINEAR_LN_B = float(np.log(0.01))


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
    dark_leaks : bool
        Whether the dark signal is collected in the photodiode and leaks with the light's
        charge (``k = g r + dc``, the default) or outside it (a storage node, amplifier glow:
        ``dc t`` added after the leakage). A linear base does not tell the two apart.
    """

    n_core = 0
    n_shared = 0  # parameters shared by all pixels

    def __init__(self, dark_current: bool, dark_leaks: bool = True):
        self.dark_current = bool(dark_current)
        self.dark_leaks = bool(dark_leaks)

    def leaking_dc(self, dc):
        """The dark current that enters the light rate ``k``: ``dc`` where the dark signal
        leaks, 0 where it is collected outside the photodiode.

        Parameters
        ----------
        dc : ndarray, DN/ms

        Returns
        -------
        ndarray, DN/ms
        """
        return dc if self.dark_leaks else np.zeros_like(dc)

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


class LeakageBase(BaseModel):
    """The paper's leakage model per pixel; theta (P, 5) = (ln g, ln a, ln b, dark, dc).

    Parameters
    ----------
    dark_current : bool
        Whether the dark current ``dc`` (DN/ms) is fitted (from the dark samples) or held.
    """

    name = "leakage"
    n_core = 4
    full_scale = None  # DN, set by diagnose: scales the start values of b (:func:`b_grid`)
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
        m, jac, well, low = self.response_and_jacobian(theta, t, r)
        kl = np.broadcast_to(np.exp(theta[:, 0:1]) * r, m.shape)
        with np.errstate(over="ignore"):
            leak = np.exp(np.minimum(theta[:, 1:2] + np.exp(theta[:, 2:3]) * well, 700.0))
        dydt = np.where(low, 0.0 if self.dark_leaks else dc, kl + dc - leak)
        return m, jac, kl, dydt, jac[..., 0]

    def response_and_jacobian(self, theta, t, r):
        """Model (P, S) and Jacobian (P, S, n) alone (what a fit step needs of
        :meth:`evaluate`), with the response in the photodiode and the samples held at the
        dark level.

        Parameters
        ----------
        theta : ndarray, (P, 5)
        t : ndarray, (S,), ms
        r : ndarray, (S,)

        Returns
        -------
        model, jac, well, low : ndarrays
            (P, S) DN, (P, S, n), (P, S) DN (the charge in the photodiode, the model less the
            dark signal collected outside it) and (P, S) bool (held at the dark level).
        """
        dc = theta[:, 4:5]
        m, jac = model_and_jacobian(theta[:, :4], t, r, self.leaking_dc(dc))
        if self.dark_leaks:
            well, jac, low = _at_least_dark(theta, m, self.with_dc(jac, t))
            return well, jac, well, low
        # the dark signal outside the photodiode is added after the leakage
        well, jac, low = _at_least_dark(theta, m, jac)
        return well + dc * t, self.with_dc(jac, t), well, low

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
        dc = theta[:, 4:5]
        m = np.maximum(predict(theta[:, :4], t, r, self.leaking_dc(dc)), theta[:, 3:4])
        return m if self.dark_leaks else m + dc * t

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

    def measure_dc(self, y, t, r, valid, w, theta0):
        """Dark current per pixel (P,) in DN/ms: the straight-line slope of the dark samples,
        then refined (Gauss-Newton, the other parameters of ``theta0`` held) so that the dark
        samples follow the leakage model too: a dark current strong enough to fill the well
        leaks like the light's charge, and its darks bend (not where the dark signal is
        collected outside the photodiode: its darks are a straight line).

        Parameters and result as
        :meth:`BaseModel.measure_dc`; ``theta0`` (P, 5) also gives
        the leakage and dark level held during the refinement.
        """
        dc = super().measure_dc(y, t, r, valid, w, theta0)
        if not self.dark_current or not self.dark_leaks or theta0[:, 1].max() <= LINEAR_LN_A + 1:
            return dc
        from ..leakage import model as leakage_model

        wd = np.where(valid & (np.broadcast_to(r, y.shape) == 0), w, 0.0)
        a, b = np.exp(theta0[:, 1:2]), np.exp(theta0[:, 2:3])
        d = theta0[:, 3:4]
        tt = t[None, :]

        def cost_and_model(rate):
            with np.errstate(over="ignore", invalid="ignore"):
                m = np.maximum(leakage_model.response(tt, rate[:, None], a, b, d), d)
            c = (wd * np.where(wd > 0, y - m, 0.0) ** 2).sum(axis=1)
            return np.where(np.isfinite(c), c, np.inf), m

        best, (c_best, m) = dc, cost_and_model(dc)
        for _ in range(4):
            h = 1e-4 * np.maximum(best, 1e-2)
            m_h = cost_and_model(best + h)[1]
            jac = np.where(wd > 0, (m_h - m) / h[:, None], 0.0)
            num = (wd * jac * np.where(wd > 0, y - m, 0.0)).sum(axis=1)
            den = (wd * jac * jac).sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                trial = np.clip(best + np.where(den > 0, num / den, 0.0), 0.0, None)
            trial = np.where(np.isfinite(trial), trial, best)
            c_trial, m_trial = cost_and_model(trial)
            better = c_trial < c_best
            best = np.where(better, trial, best)
            c_best = np.where(better, c_trial, c_best)
            m = np.where(better[:, None], m_trial, m)
        return best

    def _cost(self, theta, y, t, r, valid, w):
        res = np.where(valid, y - self.predict(theta, t, r), 0.0)
        c = (w * res * res).sum(axis=1)
        return np.where(np.isfinite(c), c, np.inf)

    def _refine(self, theta, y, t, r, valid, w, n_iter=REFINE_ITER):
        """Levenberg-Marquardt steps (all pixels at once) on the model that never falls below
        the dark level, from the calibration kernel's fit (whose model lets a dark sample leak
        below the level the pixel was reset to)."""
        # only pixels with a fit sample below the dark level: elsewhere the kernel's model is
        # this one, and its fit already the optimum
        raw = predict(theta[:, :4], t, r, self.leaking_dc(theta[:, 4:5]))
        rows = np.flatnonzero((valid & (raw < theta[:, 3:4])).any(axis=1))
        if rows.size == 0:
            return theta
        if rows.size < len(theta):
            out = theta.copy()
            out[rows] = self._refine(theta[rows], y[rows], t, r, valid[rows], w[rows], n_iter)
            return out
        th = theta.copy()
        ww = np.where(valid, w, 0.0)
        cost = self._cost(th, y, t, r, valid, w)
        lam = np.full(len(th), 1e-3)
        eye = np.eye(4)
        for _ in range(n_iter):
            m, jac, _, _ = self.response_and_jacobian(th, t, r)
            jac = jac[..., :4]
            res = np.where(valid, y - m, 0.0)
            a = np.matmul((jac * ww[..., None]).transpose(0, 2, 1), jac)
            g = (jac * (ww * res)[..., None]).sum(axis=1)
            diag = np.einsum("pii->pi", a)
            damp = a + lam[:, None, None] * (diag[:, :, None] * eye + 1e-12 * eye)
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                try:
                    step = np.linalg.solve(damp, g[..., None])[..., 0]
                except np.linalg.LinAlgError:
                    break
            trial = th.copy()
            trial[:, :4] += np.where(np.isfinite(step), step, 0.0)
            trial[:, 1] = np.clip(trial[:, 1], 2 * LINEAR_LN_A, 50.0)
            trial[:, 2] = np.clip(trial[:, 2], np.log(1e-6), 0.0)  # b in the kernel's bounds
            c = self._cost(trial, y, t, r, valid, w)
            better = c < cost
            th = np.where(better[:, None], trial, th)
            cost = np.where(better, c, cost)
            lam = np.where(better, lam / 3.0, lam * 5.0)
        return th

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
        # a dark signal outside the photodiode: the leakage is fitted to the data less it
        y_well = y if self.dark_leaks else y - dc[:, None] * t
        fit = fit_pixels(y_well, t, r, valid, w, theta0[:, :4], dark_current=self.leaking_dc(dc),
                         max_iter=max_iter)
        with np.errstate(divide="ignore", invalid="ignore"):
            theta = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark, dc])
        theta = np.where(np.all(np.isfinite(theta), axis=1)[:, None], theta, theta0)
        theta = self._refine(theta, y, t, r, valid, w)
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
            y_well = y if self.dark_leaks else y - lin[:, 2:3] * t
            guess = initial_guess(y_well, t, r, valid, w, self.leaking_dc(lin[:, 2]),
                                  b_grid=b_grid(y, valid, self.full_scale))
            guess = np.column_stack([guess, lin[:, 2]])
        except (FloatingPointError, ValueError):
            guess = from_lin
        guess = np.where(np.all(np.isfinite(guess), axis=1)[:, None], guess, from_lin)
        a = self.fit(y, t, r, valid, w, guess, max_iter=max_iter)
        b = self.fit(y, t, r, valid, w, from_lin, max_iter=max_iter)
        better_b = self._cost(b, y, t, r, valid, w) < self._cost(a, y, t, r, valid, w)
        return np.where(better_b[:, None], b, a)


class SharedLeakageBase(LeakageBase):
    """The leakage model with one leakage shape for the whole sensor: a and b shared by every
    pixel, gain and dark level per pixel; theta (P, 5) as :class:`LeakageBase`, with the
    columns ln a and ln b equal in every row.

    Two parameters a pixel and two in all: as many as a linear response (g, dark per pixel)
    with a readout nonlinearity shared by the sensor, so that the two explanations of a bent
    response are compared on one footing (the per-pixel leakage model pays two parameters a
    pixel more for the same bend). Fitted jointly by Levenberg-Marquardt on the Schur
    complement: the per-pixel (ln g, dark) blocks are eliminated, the shared (ln a, ln b) step
    solved on the reduced 2 x 2 system.

    Parameters
    ----------
    dark_current : bool
        Whether the dark current ``dc`` (DN/ms) is fitted (from the dark samples) or held.
    """

    name = "shared leakage"
    n_core = 2
    n_shared = 2
    describe = ("leakage model dY/dt = k - a exp(bY) with a and b shared by all pixels, per "
                "pixel (k, d)")
    _PIXEL = [0, 3]
    _SHARED = [1, 2]

    def evaluate(self, theta, t, r):
        """As :meth:`LeakageBase.evaluate`, with the Jacobian of the per-pixel parameters only
        (ln g, dark, and the dark current when fitted): the shared ones are two for the whole
        sensor and absorb nothing of one pixel."""
        m, jac, kl, dydt, dydlng = super().evaluate(theta, t, r)
        keep = self._PIXEL + ([4] if self.dark_current else [])
        return m, jac[..., keep], kl, dydt, dydlng

    def _step(self, th, y, t, r, ww, lam, y_ref):
        """One damped Gauss-Newton step of all parameters (Schur complement on the shared).
        The shared step is taken in (ln L, ln b), L = a exp(b y_ref) the leakage rate at the
        level ``y_ref`` of the highest samples: ln a and ln b are nearly collinear there."""
        m, jac, _, _ = self.response_and_jacobian(th, t, r)
        res = np.where(ww > 0, y - m, 0.0)
        jp = jac[..., self._PIXEL]
        b_ref = np.exp(th[0, 2]) * y_ref
        js = np.stack([jac[..., 1], jac[..., 2] - b_ref * jac[..., 1]], axis=-1)
        jpw = (jp * ww[..., None]).transpose(0, 2, 1)
        jsw = js * ww[..., None]
        a, b = np.matmul(jpw, jp), np.matmul(jpw, js)
        c = jsw.reshape(-1, 2).T @ js.reshape(-1, 2)
        gp = np.matmul(jpw, res[..., None])[..., 0]
        gs = res.reshape(-1) @ jsw.reshape(-1, 2)
        eye = np.eye(2)
        a = a + (lam * np.einsum("pii->pi", a) + 1e-12)[:, :, None] * eye
        c = c + (lam * np.diag(c) + 1e-12) * eye
        det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
        det = np.where(np.abs(det) > 0, det, np.inf)  # a pixel without samples does not move
        ainv = np.stack([np.stack([a[:, 1, 1], -a[:, 0, 1]], -1),
                         np.stack([-a[:, 1, 0], a[:, 0, 0]], -1)], 1) / det[:, None, None]
        bt_ainv = np.matmul(b.transpose(0, 2, 1), ainv)
        reduced = c - np.matmul(bt_ainv, b).sum(axis=0)
        rhs = gs - np.matmul(bt_ainv, gp[..., None]).sum(axis=0)[:, 0]
        try:
            ds = np.linalg.solve(reduced, rhs)
        except np.linalg.LinAlgError:
            ds = np.zeros(2)
        dp = np.matmul(ainv, (gp - b @ ds)[..., None])[..., 0]
        trial = th.copy()
        trial[:, self._PIXEL] += np.where(np.isfinite(dp), dp, 0.0)
        if np.all(np.isfinite(ds)):
            ln_l = th[0, 1] + b_ref + ds[0]
            trial[:, 2] = th[0, 2] + ds[1]
            trial[:, 1] = ln_l - np.exp(np.clip(trial[0, 2], -50.0, 0.0)) * y_ref
        trial[:, 1] = np.clip(trial[:, 1], 2 * LINEAR_LN_A, 50.0)
        trial[:, 2] = np.clip(trial[:, 2], np.log(1e-6), 0.0)
        return trial

    def _total(self, theta, y, t, r, valid, w):
        return float(self._cost(theta, y, t, r, valid, w).sum())

    def fit(self, y, t, r, valid, w, theta0, max_iter=15):
        """Joint Levenberg-Marquardt from ``theta0`` (its ln a and ln b columns are replaced by
        their medians); the total cost never ends above where it started.

        Parameters and result as :meth:`LeakageBase.fit`; ``max_iter`` counts accepted steps
        (at most ``SHARED_MAX_ITER``, twice as many tried).
        """
        max_iter = min(max_iter, SHARED_MAX_ITER)
        th = np.array(theta0, float)
        th[:, 1:3] = np.median(th[:, 1:3], axis=0)
        th[:, 4] = self.measure_dc(y, t, r, valid, w, th)
        ww = np.where(valid, w, 0.0)
        y_ref = _top_level(y, valid)
        y_ref = y_ref if np.isfinite(y_ref) else 0.0
        cost, lam, accepted = self._total(th, y, t, r, valid, w), 1e-3, 0
        for _ in range(2 * max_iter):
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                trial = self._step(th, y, t, r, ww, lam, y_ref)
            c = self._total(trial, y, t, r, valid, w)
            if np.isfinite(c) and c < cost:
                done = cost - c < max(1e-7 * cost, SHARED_TOL)
                th, cost, lam, accepted = trial, c, lam / 3.0, accepted + 1
                if done or accepted >= max_iter:
                    break
            else:
                lam *= 5.0
                if lam > 1e8:
                    break
        return th

    def restart(self, y, t, r, valid, w, theta_warm, max_iter=15):
        """Refit from the warm parameters and from fresh starts; the better in total.

        Parameters and result as :meth:`LeakageBase.restart`.
        """
        warm = self.fit(y, t, r, valid, w, theta_warm, max_iter=max_iter)
        fresh = self.start(y, t, r, valid, w, theta_warm[:, -1], per_pixel=theta_warm)
        better = self._total(fresh, y, t, r, valid, w) < self._total(warm, y, t, r, valid, w)
        return fresh if better else warm

    def start(self, y, t, r, valid, w, dc0=None, max_iter=40, per_pixel=None):
        """Fit from the median of the per-pixel leakage fit (over the pixels that leak; where
        none does, from each start value of b of :func:`b_grid`) and from the straight line;
        the best in total.

        Parameters
        ----------
        y, t, r, valid, w, dc0, max_iter
            As :meth:`LeakageBase.start`.
        per_pixel : ndarray, (P, 5), optional
            A per-pixel leakage fit of the same samples (fitted here when not given).

        Returns
        -------
        ndarray, (P, 5)
        """
        if per_pixel is None:
            per_pixel = LeakageBase.start(self, y, t, r, valid, w, dc0, max_iter=max_iter)
        lin = LinearBase(self.dark_current).start(y, t, r, valid, w, dc0)
        base = self.from_linear(lin)
        starts = [base]
        leaks = per_pixel[:, 1] > LINEAR_LN_A + 1
        if leaks.any():
            s = per_pixel.copy()
            s[:, 1:3] = np.median(per_pixel[leaks][:, 1:3], axis=0)
            starts.append(s)
        else:  # a and b that put the leakage at each b's start at the highest samples' level
            top = _top_level(y, valid)
            with np.errstate(invalid="ignore"):
                k_top = float(np.nanmedian(np.exp(per_pixel[:, 0]) * np.nanmax(
                    np.where(valid, np.broadcast_to(r, y.shape), np.nan), axis=1)))
            usable = np.isfinite(top) and np.isfinite(k_top) and k_top > 0
            bvs = b_grid(y, valid, self.full_scale) if usable else ()
            for bv in bvs:
                s = base.copy()
                s[:, 2] = np.log(bv)
                s[:, 1] = np.log(0.3 * k_top) - bv * top
                starts.append(s)
        # a few steps from each start, then the best one to convergence
        fits = [self.fit(y, t, r, valid, w, s, max_iter=4) for s in starts]
        costs = [self._total(f, y, t, r, valid, w) for f in fits]
        return self.fit(y, t, r, valid, w, fits[int(np.argmin(costs))], max_iter=max_iter)


def _top_level(y, valid) -> float:
    """The median pixel's highest valid sample (DN; nan where no pixel has one)."""
    with np.errstate(invalid="ignore"):
        return float(np.nanmedian(np.nanmax(np.where(valid, y, np.nan), axis=1)))


def _at_least_dark(theta, m, jac):
    """A pixel never falls below the level it was reset to: where the leakage at the dark level
    exceeds the light (and dark current) rate, as in the dark frames of a leaky pixel, the
    response stays at the dark level (the model alone would leak below it). Returns the model,
    its Jacobian (only the dark level acts there; ``jac``, a fresh array of the caller's, is
    changed in place) and the mask of those samples."""
    d = theta[:, 3:4]
    low = m < d
    if not low.any():
        return m, jac, low
    jac[low] = 0.0
    jac[..., 3][low] = 1.0
    return np.where(low, d, m), jac, low


def b_grid(y, valid, full_scale=None):
    """Start values of b (1/DN) for the fit, scaled to the sweep's signal span: ``b x span``
    from 2 to 16 (the calibration's own grid is in absolute 1/DN, made for 10-bit data, and
    misses the leakage of a 14-bit sensor by a factor of 10). Sharper bends are left out: a
    bend just above the highest sample is a straight line below it, wins the start on cost and
    leaves the fit where the leakage parameters have no gradient (the linear start covers
    that case).

    Parameters
    ----------
    y : ndarray, (P, S), DN
        Step means.
    valid : ndarray of bool, (P, S)
        Samples to use.
    full_scale : float, optional, DN
        The ADC's full scale: the grid is also scaled to the range from the darkest sample to
        it (a sweep whose light stays low sees the leakage of a pixel far from saturation).

    Returns
    -------
    tuple of float, 1/DN
    """
    yv = np.where(valid, y, np.nan)
    with np.errstate(invalid="ignore"):
        low = np.nanmedian(np.nanmin(yv, axis=1))
        spans = [np.nanmedian(np.nanmax(yv, axis=1)) - low]
    if full_scale is not None:
        spans.append(full_scale - low)
    spans = [float(s) for s in spans if np.isfinite(s) and s > 0] or [1000.0]
    return tuple(sorted({float(v) / s for s in spans for v in B_SPAN_GRID}))


B_SPAN_GRID = (2.0, 4.0, 8.0, 16.0)  # b x signal span tried as start values

BASES = {"leakage": LeakageBase, "shared leakage": SharedLeakageBase, "linear": LinearBase}
