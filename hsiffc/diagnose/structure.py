"""Structure left in the held-out residual: binned tests against what noise alone leaves."""

from __future__ import annotations

import numpy as np
from scipy import stats

UNEXPLAINED_P = 1e-6
UNEXPLAINED_OF_NOISE = 0.2  # structure counts when its RMS exceeds this fraction of the noise
SIGNAL_BINS = 50


def bin_index(x, mask, bins):
    """Bin of every element of ``x`` (-1 outside ``mask``): quantile bins, or one bin per
    distinct value where the quantiles collapse (fewer distinct values than bins).

    Parameters
    ----------
    x : ndarray
        What to bin by.
    mask : ndarray of bool, shape of ``x``
        Elements to bin.
    bins : int
        Number of bins at most.

    Returns
    -------
    ndarray of int, shape of ``x``

    Examples
    --------
    >>> import numpy as np
    >>> bin_index(np.array([1.0, 2.0, 2.0, 5.0]), np.array([True, True, True, False]), 4).tolist()
    [0, 1, 1, -1]
    """
    xv = x[mask]
    if xv.size == 0:
        return np.full(x.shape, -1)
    values = np.unique(xv)
    if values.size <= bins:
        idx = np.searchsorted(values, x)
    else:
        edges = np.unique(np.nanpercentile(xv, np.linspace(0, 100, bins + 1)))
        idx = np.searchsorted(edges[1:-1], x) if edges.size > 2 else np.zeros(x.shape, int)
    return np.where(mask, np.clip(idx, 0, max(values.size, 1) - 1), -1)


def groupings(valid, signal, light, rows, cols, band):
    """The groupings the held-out residual is binned by: step, signal level, row, column and
    mosaic phase.

    Parameters
    ----------
    valid : ndarray of bool, (P, S)
        Held-out samples.
    signal : ndarray, (P, S), DN
        Model signal above dark.
    light : ndarray of bool, (S,)
        Light steps.
    rows, cols, band : ndarray of int, (P,)
        Position and band of each pixel.

    Returns
    -------
    dict
        Grouping name -> (P, S) bin index (-1: not binned).
    """
    shape = valid.shape
    g = {"step (exposure, acquisition order)": np.broadcast_to(np.arange(shape[1]), shape)}
    lmask = valid & light[None, :]
    if lmask.any():
        g[f"signal level ({SIGNAL_BINS} quantile bins)"] = bin_index(signal, lmask, SIGNAL_BINS)
    g["row"] = np.broadcast_to((rows * 8 // max(rows.max() + 1, 1))[:, None], shape)
    g["column"] = np.broadcast_to((cols * 8 // max(cols.max() + 1, 1))[:, None], shape)
    if band.max() > 0:
        g["mosaic phase (band)"] = np.broadcast_to(band[:, None], shape)
    return g


def structure(res, valid, groups, noise, null=None):
    """Binned held-out residual: is there structure beyond noise?

    Parameters
    ----------
    res : ndarray, (P, S), DN
        Held-out residual.
    valid : ndarray of bool, (P, S)
        Held-out samples.
    groups : dict
        From :func:`groupings`.
    noise : float, DN
        Temporal noise of one held-out sample.
    null : dict, optional
        Grouping -> structured RMS (DN) of data simulated from the model (a floor).

    Returns
    -------
    findings : list of dict
        Per grouping: bins, chi2, p-value, structured RMS (DN), significance.
    flag : bool
        Some grouping shows significant structure.
    """
    findings, flag = [], False
    for name, g in groups.items():
        ok = valid & (g >= 0)
        gv, rv = g[ok].astype(int), res[ok]
        if gv.size == 0:
            continue
        n = np.bincount(gv)
        keep = n >= 10
        s1 = np.bincount(gv, weights=rv)
        s2 = np.bincount(gv, weights=rv * rv)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / n
            se = np.sqrt((s2 / n - mean ** 2) / np.maximum(n - 1, 1))
        mean, se = mean[keep], se[keep]
        good = se > 0
        chi2 = float(np.sum((mean[good] / se[good]) ** 2))
        dof = int(good.sum())
        p = float(stats.chi2.sf(chi2, dof)) if dof else 1.0
        structured_rms = (float(np.sqrt(np.mean(np.maximum(mean ** 2 - se ** 2, 0.0))))
                          if mean.size else 0.0)
        floor = 1.5 * null.get(name, 0.0) if null else 0.0
        significant = bool(p < UNEXPLAINED_P and structured_rms > UNEXPLAINED_OF_NOISE * noise
                           and structured_rms > floor)
        flag |= significant
        findings.append({"grouping": name, "bins": dof, "chi2": chi2, "p_value": p,
                         "structured_rms_dn": structured_rms,
                         "null_structured_rms_dn": (null or {}).get(name),
                         "significant": significant})
    return findings, flag
