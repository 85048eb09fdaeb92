"""Structure left in the held-out residual: binned tests against what noise alone leaves."""

from __future__ import annotations

import numpy as np
from scipy import stats

UNEXPLAINED_P = 1e-6
UNEXPLAINED_OF_NOISE = 0.2  # structure counts when its RMS exceeds this fraction of the noise
SIGNAL_BINS = 50
LOW_RANK = "pixels x steps (one pattern over the pixels times one over the steps)"


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


def structure(res, valid, groups, noise, null=None, sd=None):
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
        Grouping -> ``null_statistic`` of the same finding on data simulated from the model
        and refitted (a floor: the structured RMS of a binning, the leading singular value
        squared of the pixels x steps pattern).
    sd : ndarray, (P, S) or (S,), DN, optional
        Temporal noise of each held-out sample: the pixels x steps pattern
        (:func:`low_rank`) is tested too.

    Returns
    -------
    findings : list of dict
        Per grouping: bins, chi2, p-value, structured RMS (DN), significance and
        ``null_statistic`` (what a run on simulated data contributes to ``null``).
    flag : bool
        Some grouping shows significant structure.
    """
    findings, flag = [], False

    def judge(structured_rms, p, floor=0.0):
        return bool(p < UNEXPLAINED_P and structured_rms > UNEXPLAINED_OF_NOISE * noise
                    and structured_rms > floor)
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
        significant = judge(structured_rms, p, 1.5 * null.get(name, 0.0) if null else 0.0)
        flag |= significant
        findings.append({"grouping": name, "bins": dof, "chi2": chi2, "p_value": p,
                         "structured_rms_dn": structured_rms,
                         "null_structured_rms_dn": (null or {}).get(name),
                         "significant": significant, "null_statistic": structured_rms})
    if sd is not None:
        null_chi2 = (null or {}).get(LOW_RANK)
        lr = low_rank(res, valid, sd, null_chi2)
        significant = judge(lr["structured_rms_dn"], lr["p_value"],
                            1.5 * lr["reference_rms_dn"])
        flag |= significant
        findings.append({
            "grouping": LOW_RANK, "bins": f"{lr['rank_pixels']} x {lr['rank_steps']}",
            "chi2": lr["chi2"], "p_value": lr["p_value"],
            "structured_rms_dn": lr["structured_rms_dn"],
            "null_structured_rms_dn": None if null_chi2 is None else lr["reference_rms_dn"],
            "significant": significant, "null_statistic": lr["chi2"]})
    return findings, flag


def low_rank(res, valid, sd, null_chi2=None):
    """Structure of the held-out residual that no binning sees: the strongest pattern over the
    pixels times a pattern over the steps (the leading singular value of the residual in units
    of its noise), e.g. a gain step on every other group of columns halfway through the
    acquisition, whose column bins and step means both average out.

    A residual of noise alone (``P`` pixels by ``S`` steps, a fraction ``f`` of them valid) has a
    leading singular value near ``sqrt(f) (sqrt(P) + sqrt(S))`` (Marchenko-Pastur); a pattern of
    energy ``E`` (noise units) adds about ``E`` to its square. A fitted model's own parameter
    errors leave such patterns too (an error of each pixel's gain times the signal over the
    steps): ``null_chi2``, the leading singular value squared of data simulated from the model
    and refitted, is the reference then, and the pattern's energy what exceeds it. The p-value
    is an approximation, a screen beside the rules of :func:`structure`: the Tracy-Widom tail
    ``exp(-2/3 x^1.5)`` of the largest eigenvalue of a noise matrix (Johnstone's scale), with
    the fluctuation of the reference's own pattern (``sqrt(2 E)``) added to the scale.

    Parameters
    ----------
    res : ndarray, (P, S), DN
        Held-out residual.
    valid : ndarray of bool, (P, S)
        Held-out samples.
    sd : ndarray, (P, S) or (S,), DN
        Temporal noise of each held-out sample.
    null_chi2 : float, optional
        Reference leading singular value squared (noise units) of data simulated from the
        model; default: noise alone.

    Returns
    -------
    dict
        ``chi2`` (the leading singular value squared, noise units), ``p_value``,
        ``structured_rms_dn`` (the pattern's RMS over the valid samples: its energy above the
        reference, in units of the RMS noise), ``reference_rms_dn`` (the same of the
        reference's pattern above noise alone), ``rank_pixels`` and ``rank_steps`` (the
        matrix's size).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> valid = np.ones((400, 40), bool)
    >>> noise = low_rank(rng.standard_normal((400, 40)), valid, np.ones(40))
    >>> pattern = np.outer(np.where(np.arange(400) % 8 < 4, 1.0, -1.0), np.linspace(0, 1, 40))
    >>> found = low_rank(rng.standard_normal((400, 40)) + 0.3 * pattern, valid, np.ones(40))
    >>> noise["structured_rms_dn"] < 0.05 < found["structured_rms_dn"], found["p_value"] < 1e-6
    (True, True)
    """
    sd = np.broadcast_to(sd, res.shape)
    ok = valid & (sd > 0)
    rows, cols = ok.any(axis=1), ok.any(axis=0)
    z = np.where(ok, res / np.where(ok, sd, 1.0), 0.0)[rows][:, cols]
    n = int(ok.sum())
    if min(z.shape) < 2 or n == 0:
        return {"chi2": 0.0, "p_value": 1.0, "structured_rms_dn": 0.0, "reference_rms_dn": 0.0,
                "rank_pixels": 0, "rank_steps": 0}
    p_, s_ = z.shape
    fill = n / z.size
    s2 = float(np.linalg.svd(z, compute_uv=False)[0]) ** 2
    edge2 = fill * (np.sqrt(p_) + np.sqrt(s_)) ** 2
    ref = max(edge2, null_chi2 or 0.0)
    rms_sd = float(np.sqrt(np.mean(sd[ok] ** 2)))
    scale = (fill * (np.sqrt(p_) + np.sqrt(s_)) * (1 / np.sqrt(p_) + 1 / np.sqrt(s_)) ** (1 / 3)
             + np.sqrt(2.0 * (ref - edge2)))
    x = (s2 - ref) / scale
    return {"chi2": s2, "p_value": float(np.exp(-2.0 / 3.0 * x ** 1.5)) if x > 0 else 1.0,
            "structured_rms_dn": float(np.sqrt(max(s2 - ref, 0.0) / n)) * rms_sd,
            "reference_rms_dn": float(np.sqrt((ref - edge2) / n)) * rms_sd,
            "rank_pixels": p_, "rank_steps": s_}
