"""EMVA 1288 Release 4.0 spatial nonuniformity of the two stacks (one dark, one light, L frames
each): the figures, their split into row, column and pixel parts, the spectrograms and the
defect-pixel histograms. Inputs are the stacks' sum images and their mean temporal variance
per pixel group (:func:`hsiffc.emva1288.stream.reduce_frames`); numbers only.

*Spatial variance.* ``s2 = var(mean image, ddof=1) - mean(temporal variance) / L`` (the
temporal noise left in a mean of L frames taken out).

*Row, column and pixel parts* (M rows, N columns). With ``u`` the mean of the mean image, the
column means' variance ``s2_cav = 1/N sum_n (u[n] - u)^2 - sigma2 / (L M)`` and the row means'
``s2_rav = 1/M sum_m (u[m] - u)^2 - sigma2 / (L N)`` (temporal part out), then
``s2_col = (MN - M)/(MN - M - N) s2_cav - N/(MN - M - N) (s2 - s2_rav)``,
``s2_row = (MN - N)/(MN - M - N) s2_rav - M/(MN - M - N) (s2 - s2_cav)`` and
``s2_pixel = MN/(MN - M - N) (s2 - s2_cav - s2_rav)``: the row means also carry 1/N of the
pixel variance, and so on, which these solve for. ``DSNU1288_row = sqrt(s2_row.dark) / K``
(e-), ``PRNU1288_row = 100 sqrt(s2_row - s2_row.dark) / (u - u_dark)`` (%), the same for
columns and pixels; undefined (None) where the variance under the root is negative.

*PRNU and the high-pass filter.* Release 4.0 takes the PRNU's spatial variance after a 5 x 5
box high-pass filter (``y - box5(y)``) so that a smooth illumination fall-off does not count as
nonuniformity. The reference implementation (``emva1288`` 1.0.2) does not filter the variance
(it filters only the defect-pixel histogram). ``PRNU1288`` here is the reference's, so that
the figure under that name agrees with what users of the reference report;
``PRNU1288_highpass`` is the standard's: the variance of the filtered (light - dark) mean
image over its valid interior, less the filtered temporal part, divided by the filter's gain
for white noise ``(1 - 1/25)^2 + 24/25^2 = 24/25`` so that a pure pixel pattern gives the
unfiltered value.

*Spectrograms* (horizontal: along each row, vertical: along each column). The mean image less
its mean, the discrete Fourier transform of every line divided by sqrt(line length), the
squared magnitude averaged over the lines, frequencies ``0 .. 1/2`` cycles per pixel. The
DSNU's in DN (dark mean image), the PRNU's in percent of the mean signal ((light - dark) mean
image, ``100 sqrt(power) / mean``). The reference plots ``sqrt(power / mean)`` for the PRNU
and a frequency axis ``k / (2 (N/2 + 1))``; hsiffc gives the standard's percent and ``k / N``
(the power arrays themselves agree with the reference's). Beside each, the level of a white
pattern with the figure's variance (the standard's horizontal line) and the temporal noise
left in the mean image.

*Defect-pixel histograms* of the stack sums (integers, so that every bin holds whole codes): a
sum image ``y`` of integer values gets bins of integer width ``W`` (1 while there are at most
256 values, else the smallest width giving at most 256 bins), counts per bin (logarithmic
plot), bins scaled back to DN by ``L`` (and for the PRNU the filter's 25). DSNU: the dark sum,
bins centred on its mean. PRNU: the high-pass filtered (light - dark) sum. Accumulated: the
same of ``|y - int(mean y)|``, counted from the top (the share of pixels, in percent, deviating
by at least each bin's value), as the standard's "accumulated histogram" is read.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["spatial_group", "nonuniformity_parts", "spectrograms", "defect_histograms",
           "highpass5", "HISTOGRAM_BINS"]

HISTOGRAM_BINS = 256  # at most this many bins (the reference's Qmax)
HIGHPASS = 5  # box size of the high-pass filter
WHITE_GAIN = 1.0 - 1.0 / HIGHPASS ** 2  # variance gain of y - box(y) for white noise


def spatial_group(img: dict, mask=None, group: int = 0) -> dict:
    """Statistics of one stack over pixel group ``group`` (0: all pixels, ``mask`` None; else
    band ``group - 1``, its pixels ``mask``, flat bool): ``L``, ``avg_mean``, ``avg_var``
    (spatial variance of the mean image, ddof=1), ``var_mean`` (mean temporal variance) and
    ``s2`` (fixed-pattern variance)."""
    L = int(img["L"])
    avg = img["sum"].ravel() / L
    if mask is not None:
        avg = avg[mask]
    avg_var = float(avg.var(ddof=1))
    var_mean = float(img["var_mean"][group])
    return {"L": L, "avg_mean": float(avg.mean()), "avg_var": avg_var, "var_mean": var_mean,
            "s2": avg_var - var_mean / L}


def _row_col(img: dict, s2: float, var_mean: float) -> dict:
    """Row, column and pixel parts of one stack's spatial variance (DN^2)."""
    L = int(img["L"])
    avg = img["sum"] / L
    m, n = avg.shape
    u = avg.mean()
    cav = float(np.square(avg.mean(axis=0) - u).sum() / n - var_mean / (L * m))
    rav = float(np.square(avg.mean(axis=1) - u).sum() / m - var_mean / (L * n))
    den = m * n - m - n
    if den <= 0:  # a single row or column: no split
        return {"s2_cav": cav, "s2_rav": rav, "s2_col": None, "s2_row": None, "s2_pixel": None}
    return {"s2_cav": cav, "s2_rav": rav,
            "s2_col": (m * n - m) / den * cav - n / den * (s2 - rav),
            "s2_row": (m * n - n) / den * rav - m / den * (s2 - cav),
            "s2_pixel": m * n / den * (s2 - cav - rav)}


def highpass5(y: np.ndarray) -> np.ndarray:
    """``25 y - box5sum(y)`` over the interior (edges of 2 pixels cut): the standard's high-pass
    filter times 25, exact on integer images (box sums from a summed-area table, which the
    interior needs no edge rule for)."""
    y = np.asarray(y, np.float64)
    k, h = HIGHPASS, HIGHPASS // 2
    c = np.zeros((y.shape[0] + 1, y.shape[1] + 1))
    np.cumsum(np.cumsum(y, axis=0), axis=1, out=c[1:, 1:])
    box = c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]
    return k * k * y[h:-h, h:-h] - box


def nonuniformity_parts(images: dict, K: float) -> tuple[dict, dict]:
    """Figures and variances of the split, and the standard's high-pass PRNU.

    Parameters
    ----------
    images : dict
        ``light`` and ``dark``: ``sum`` (H, W), ``var_mean`` (DN^2, per pixel group, all
        pixels first) and ``L`` of each stack.
    K : float, DN/e-
        System gain.

    Returns
    -------
    figures : dict
        ``DSNU1288_row``, ``DSNU1288_col``, ``DSNU1288_pixel`` (e-), their ``_DN``, and
        ``PRNU1288_row``, ``PRNU1288_col``, ``PRNU1288_pixel``, ``PRNU1288_highpass`` (%):
        values, None where undefined.
    variances : dict
        ``light`` and ``dark``: ``s2``, ``s2_cav``, ``s2_rav``, ``s2_col``, ``s2_row``,
        ``s2_pixel`` (DN^2).
    """
    li, da = images["light"], images["dark"]
    gl, gd = spatial_group(li), spatial_group(da)
    pl = {"s2": gl["s2"], **_row_col(li, gl["s2"], gl["var_mean"])}
    pd = {"s2": gd["s2"], **_row_col(da, gd["s2"], gd["var_mean"])}
    dy = gl["avg_mean"] - gd["avg_mean"]
    out = {}
    for part in ("row", "col", "pixel"):
        d = pd[f"s2_{part}"]
        ok = d is not None and d >= 0
        out[f"DSNU1288_{part}"] = math.sqrt(d) / K if ok else None
        out[f"DSNU1288_{part}_DN"] = math.sqrt(d) if ok else None
        lv = pl[f"s2_{part}"]
        out[f"PRNU1288_{part}"] = (100 * math.sqrt(lv - d) / dy
                                   if d is not None and lv is not None and lv >= d and dy
                                   else None)
    # the standard's PRNU: high-pass filtered (light - dark) mean image
    diff = li["sum"] / li["L"] - da["sum"] / da["L"]
    hp = highpass5(diff) / HIGHPASS ** 2
    tvar = gl["var_mean"] / gl["L"] + gd["var_mean"] / gd["L"]
    s2_hp = (float(hp.var(ddof=1)) - WHITE_GAIN * tvar) / WHITE_GAIN if hp.size > 1 else None
    out["PRNU1288_highpass"] = (100 * math.sqrt(s2_hp) / dy if s2_hp is not None and s2_hp >= 0
                                and dy else None)
    return out, {"light": pl, "dark": pd}


def _spectrum(img: np.ndarray, vertical: bool) -> np.ndarray:
    """Power per frequency: every line's |DFT|^2 / length of the image less its mean, averaged
    over the lines; frequencies 0 .. length // 2."""
    m = np.asarray(img, np.float64)
    m = m - m.mean()
    if vertical:
        m = m.T
    n = m.shape[1]
    f = np.fft.rfft(m, axis=1)
    return (f.real ** 2 + f.imag ** 2).mean(axis=0) / n


def spectrograms(images: dict, figures: dict) -> dict:
    """Horizontal and vertical spectrograms of DSNU (DN) and PRNU (percent).

    Returns
    -------
    dict
        ``DSNU`` and ``PRNU``, each with ``horizontal`` and ``vertical``: ``frequency``
        (cycles/pixel), ``power`` (DN^2, the reference's array), ``amplitude`` (DN or %);
        ``figure_level`` (the DSNU1288_DN or PRNU1288 line) and ``temporal_level`` (the
        temporal noise left in the mean image, same unit); ``unit``.
    """
    li, da = images["light"], images["dark"]
    dark = da["sum"] / da["L"]
    diff = li["sum"] / li["L"] - dark
    mean = float(diff.mean())
    out = {}
    for name, img, scale, unit, fig, tvar in (
            ("DSNU", dark, 1.0, "DN", figures.get("DSNU1288_DN"),
             float(da["var_mean"][0]) / da["L"]),
            ("PRNU", diff, 100.0 / mean if mean else float("nan"), "%",
             figures.get("PRNU1288"), float(li["var_mean"][0]) / li["L"])):
        d = {"unit": unit, "figure_level": fig,
             "temporal_level": math.sqrt(tvar) * (scale if name == "PRNU" else 1.0)}
        for lab, vert in (("horizontal", False), ("vertical", True)):
            p = _spectrum(img, vert)
            n = img.shape[0] if vert else img.shape[1]
            d[lab] = {"frequency": np.arange(p.size) / n, "power": p,
                      "amplitude": np.sqrt(p) * scale}
        out[name] = d
    return out


def _histogram(y: np.ndarray, qmax: int = HISTOGRAM_BINS) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
    """Integer-width bins over the values of ``y`` (whole numbers): lower bin edges, counts,
    and the normal curve with the data's mean and standard deviation."""
    y = np.rint(np.ravel(y)).astype(np.int64)
    lo, hi = int(y.min()), int(y.max())
    q = hi - lo
    width, nb = 1, q + 1
    if nb > qmax:
        width = q // qmax + 1
        nb = q // width + 1
    edges = lo + width * np.arange(nb + 1)
    counts = np.bincount(np.minimum((y - lo) // width, nb - 1), minlength=nb)
    mu, sd = float(y.mean()), float(y.std())
    model = (q / nb * y.size / (math.sqrt(2 * math.pi) * sd)
             * np.exp(-0.5 * ((edges[:-1] - mu) / sd) ** 2)) if sd > 0 else np.zeros(nb)
    return edges[:-1].astype(np.float64), counts, model


def defect_histograms(images: dict) -> dict:
    """The defect-pixel histograms (logarithmic and accumulated) of DSNU and PRNU.

    Returns
    -------
    dict
        ``DSNU``, ``PRNU``, ``DSNU_accumulated``, ``PRNU_accumulated``: ``bins`` (DN, lower
        edges), ``values`` (pixels per bin; accumulated: percent of pixels at or above the
        bin), and for the plain histograms ``model`` (the normal curve, pixels per bin).
    """
    li, da = images["light"], images["dark"]
    ld, ll = int(da["L"]), int(li["L"])
    sum_dark = np.rint(da["sum"])
    if ll == ld:
        diff = np.rint(li["sum"]) - sum_dark
    else:  # unequal stacks: the light sum less the dark mean scaled to L frames
        diff = np.rint(li["sum"] - da["sum"] * (ll / ld))
    out = {}
    b, v, m = _histogram(sum_dark)
    out["DSNU"] = {"bins": b / ld - sum_dark.mean() / ld, "values": v, "model": m}
    acc = np.abs(sum_dark - int(sum_dark.mean()))
    b, v, _ = _histogram(acc)
    out["DSNU_accumulated"] = {"bins": b / ld, "values": 100 * np.cumsum(v[::-1])[::-1]
                               / acc.size}
    hp = highpass5(diff)
    b, v, m = _histogram(hp)
    out["PRNU"] = {"bins": b / (ll * HIGHPASS ** 2), "values": v, "model": m}
    acc = np.abs(hp - int(hp.mean()))
    b, v, _ = _histogram(acc)
    out["PRNU_accumulated"] = {"bins": b / (ll * HIGHPASS ** 2),
                               "values": 100 * np.cumsum(v[::-1])[::-1] / acc.size}
    return out
