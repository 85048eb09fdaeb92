"""The numpy implementations of the leakage model that hsiffc used before its numba kernels.

Kept here only as the baselines the benchmarks measure the kernels against (same run, same
data); the package does not use them. Vectorised numpy: whole-frame temporaries, a
safeguarded Newton iteration in ln k over the pixels still active.
"""

from __future__ import annotations

import numpy as np

from hsiffc.data.dq import DQ, DQ_DTYPE


def f64(*arrays):
    return [np.asarray(a, dtype=np.float64) for a in arrays]


def log_(x):
    """log that maps 0 to -inf without a warning."""
    with np.errstate(divide="ignore"):
        return np.log(x)


def log_phi(x):
    """log((1 - exp(-x)) / x) for x >= 0, with the limit 0 at x = 0.

    ``-expm1(-x)`` is accurate for every x > 0, so one log suffices; below 1e-8 the series
    ``-x/2`` avoids 0/0. The absolute error is at the level of double rounding everywhere, which
    is what the response (a sum of logs) needs.
    """
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.log(-np.expm1(-x) / x)
    tiny = x < 1e-8
    if np.any(tiny):
        out = np.where(tiny, -0.5 * x, out)
    return out


def neg_b_y(t_ms, k, a, b, dark):
    """-b*Y(t) of the model, computed in the log domain."""
    x = b * k * t_ms
    with np.errstate(divide="ignore", invalid="ignore"):
        leak = log_(a) + np.log(b) + log_(t_ms) + log_phi(x)
    return np.logaddexp(-b * dark - x, leak)


def response(t_ms, k, a, b, dark):
    """The former numpy closed form (float64 inputs, no argument checks)."""
    return -neg_b_y(t_ms, k, a, b, dark) / b


def dy_dlogk(t_ms, k, a, b, dark, y_model):
    """dY/d(ln k) of the model, in a form that cannot overflow for physical responses."""
    x = b * k * t_ms
    with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
        term1 = x * np.exp(b * (y_model - dark) - x)
        # (a/k)(1 - (1 + x) e^{-x}) e^{bY}; 1 - (1+x)e^{-x} computed without cancellation
        g = np.where(x < 1e-3, x * x / 2 - x ** 3 / 3, -np.expm1(-x) - x * np.exp(-x))
        term2 = np.exp(log_(a) - log_(k) + b * y_model) * g
    return np.nan_to_num((term1 + term2) / b, nan=0.0, posinf=np.finfo(float).max)


def invert_response(y, t_ms, a, b, dark, *, full_scale=None, k_max=None, tol_dn=1e-9,
                    max_iter=60) :
    """k, flags and iterations of the former numpy inversion (see hsiffc.leakage.model.invert_response)."""
    y, t_ms, a, b, dark = np.broadcast_arrays(*f64(y, t_ms, a, b, dark))
    if np.any(t_ms <= 0):
        raise ValueError("t_ms must be > 0 to invert a response (at t = 0 no light is measured)")
    shape = y.shape
    y, t_ms, a, b, dark = (v.ravel() for v in (y, t_ms, a, b, dark))
    flags = np.zeros(y.shape, dtype=DQ_DTYPE)
    k = np.zeros(y.shape)

    finite = np.isfinite(y) & np.isfinite(a) & np.isfinite(b) & np.isfinite(dark)
    flags[~finite] |= DQ_DTYPE(DQ.NONFINITE)
    target = y.copy()
    if full_scale is not None:
        clipped = finite & (y >= full_scale)
        flags[clipped] |= DQ_DTYPE(DQ.SATURATED)
        target[clipped] = full_scale
    y_zero = response(t_ms, 0.0, a, b, dark)
    below = finite & (target <= y_zero)
    flags[below & (target < y_zero)] |= DQ_DTYPE(DQ.BELOW_DARK)
    work = np.flatnonzero(finite & ~below)

    iterations = 0
    if work.size:
        yt, tt, aa, bb, dd = (v[work] for v in (target, t_ms, a, b, dark))
        # Bracket in u = ln k: leakage only lowers the response, so k >= (Y - d)/t and
        # Y <= ln(k/a)/b gives k >= a e^{bY}.
        with np.errstate(divide="ignore", over="ignore"):
            k_lin = np.maximum(yt - dd, 0.0) / tt
            k_sat = np.exp(log_(aa) + bb * yt)
        # Above the dark level both bounds hold (the curve started below saturation). At or
        # below it the curve may start above saturation, where a e^{bY} bounds k from above.
        above = yt > dd
        lo = np.log(np.maximum(np.where(above, np.maximum(k_lin, k_sat), k_sat), 1e-300))
        hi = np.where(above, np.inf, lo + 1e-9)  # +inf: found by the iteration
        lo = np.where(above, lo, lo - 50.0)
        u = lo.copy()
        active = np.arange(work.size)  # pixels still iterating (compacted every iteration)
        for iterations in range(1, max_iter + 1):
            ua, la, ha = u[active], lo[active], hi[active]
            ta, aa_, ba, da, ya = tt[active], aa[active], bb[active], dd[active], yt[active]
            kk = np.exp(ua)
            ym = response(ta, kk, aa_, ba, da)
            err = ym - ya
            done = np.abs(err) <= tol_dn + 8 * np.finfo(float).eps * np.abs(ya)
            keep = ~done
            if not keep.any():
                active = active[:0]
                break
            la = np.where(err < 0, ua, la)
            ha = np.where(err > 0, ua, ha)
            slope = dy_dlogk(ta, kk, aa_, ba, da, ym)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = ua - err / slope
            # with no upper bound yet, never step more than 5 e-folds up
            step = np.where(np.isfinite(ha), step, np.minimum(step, ua + 5.0))
            inside = np.isfinite(step) & (step > la) & (step < ha)
            new_u = np.where(inside, step, 0.5 * (la + ha))
            sel = active[keep]
            u[sel], lo[sel], hi[sel] = new_u[keep], la[keep], ha[keep]
            active = sel
        k[work] = np.exp(u)
        flags[work[active]] |= DQ_DTYPE(DQ.NOT_CONVERGED)
    if k_max is not None:
        over = k > k_max
        flags[over] |= DQ_DTYPE(DQ.UNREACHABLE)
        k[over] = k_max
    return k.reshape(shape), flags.reshape(shape), iterations
