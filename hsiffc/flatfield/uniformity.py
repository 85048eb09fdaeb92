"""Fixed-pattern non-uniformity with the temporal noise taken out (EMVA 1288 way).

Eq. (6) of the paper, ``100 * std / mean`` of one frame (:func:`hsiffc.flatfield.two_point.uniformity`), mixes
the two kinds of non-uniformity a sensor has: the *fixed pattern* (each pixel answers the same
light a little differently, the same in every frame: what a flat-field correction can remove)
and the *temporal noise* (shot and read noise, different in every frame: no correction can
remove it). On a single 8-bit frame at a few tens of DN the temporal noise dominates, so eq. (6)
cannot show what a correction did.

The EMVA Standard 1288 (Release 4.0, section "Spatial nonuniformity": DSNU and PRNU) separates
them from a stack of L frames of one illumination step. With ``mu[m, n]`` the mean of the L
frames at pixel (m, n), ``mu`` the mean over the pixels::

    s2_measured = 1 / (M N - 1) * sum_{m,n} (mu[m, n] - mu)^2      spatial variance of the mean
    sigma2_t    = 1 / (M N - 1) * sum_{m,n} 1 / (L - 1) * sum_l (r_l[m, n] - mean_l r_l[m, n])^2
    s2_fixed    = s2_measured - sigma2_t / L                        fixed-pattern variance

``s2_measured`` holds the fixed pattern plus the temporal variance of a mean of L frames, which
``sigma2_t / L`` removes. ``r_l`` is frame l minus its own spatial mean, so a change of the
light level between frames (flicker) counts neither as pattern nor as noise; with the
``M N - 1`` normalisation, for L = 2 this is exactly the spatial covariance of the two frames. The
fixed-pattern non-uniformity in percent is ``100 * sqrt(s2_fixed) / mean signal``: the PRNU of
EMVA 1288 when the frames are dark-subtracted light frames, the DSNU (in DN) for dark frames.
Here it is computed per band of a mosaic (each band sees different light) over the pixels with
no DQ bit set in any frame.

Reference: EMVA Standard 1288, "Standard for Characterization of Image Sensors and Cameras",
Release 4.0 (2021), section 8 "Spatial nonuniformity" (dark signal nonuniformity DSNU and
photo-response nonuniformity PRNU from the temporal-noise-corrected spatial variance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FixedPattern", "fixed_pattern_variance", "fixed_pattern_nonuniformity",
           "uniformity_before_after"]


@dataclass(frozen=True)
class FixedPattern:
    """Fixed-pattern statistics of one frame set, per band.

    Attributes
    ----------
    mean_dn : (bands,) float
        Mean signal over the used pixels (DN; above dark when a dark was given).
    fpn_var_dn2 : (bands,) float
        Fixed-pattern variance ``s2_measured - sigma2_t / L`` (DN^2; may be slightly negative
        when the fixed pattern is below what the frames can measure).
    fpn_dn, fpn_percent : (bands,) float
        Its square root (0 where the variance is negative), in DN and in percent of ``mean_dn``.
    temporal_dn : (bands,) float
        Temporal noise of one frame (DN).
    eq6_percent : (bands,) float
        The paper's eq. (6) on single frames, averaged over the frames (percent; temporal noise
        included).
    n_pixels : (bands,) int
        Pixels used.
    n_frames : int
    fpn_se_percent : (bands,) float
        Standard error of ``fpn_percent`` from the finite number of pixels and frames (normal
        noise): ``var(s2_fixed) = 2 (s2_fixed + sigma2_t / L)^2 / P + 2 sigma2_t^2 / (P L^2 (L - 1))``,
        propagated to the percentage (at least ``100 sqrt(SE of the variance) / mean``).
    """

    mean_dn: np.ndarray
    fpn_var_dn2: np.ndarray
    fpn_dn: np.ndarray
    fpn_percent: np.ndarray
    temporal_dn: np.ndarray
    eq6_percent: np.ndarray
    n_pixels: np.ndarray
    n_frames: int
    fpn_se_percent: np.ndarray | None = None

    @property
    def pooled_fpn_percent(self) -> float:
        """One figure for all bands: the root mean square of the per-band percentages."""
        v = self.fpn_percent[np.isfinite(self.fpn_percent)]
        return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

    @property
    def pooled_fpn_var_rel(self) -> float:
        """Mean over bands of the fixed-pattern variance relative to the squared mean signal,
        signed: negative where the pattern is below what the frames can measure (its square
        root, in percent, is :attr:`pooled_fpn_percent` where positive)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.asarray(self.fpn_var_dn2) / np.asarray(self.mean_dn) ** 2
        v = v[np.isfinite(v)]
        return float(np.mean(v)) if v.size else float("nan")

    @property
    def below_noise(self) -> bool:
        """The pooled fixed-pattern variance estimate is not positive: the pattern is below
        what the frames can measure (say so; "0.00 %" would claim too much)."""
        return bool(self.pooled_fpn_var_rel <= 0)

    @property
    def pooled_fpn_se_percent(self) -> float:
        """Standard error of :attr:`pooled_fpn_percent`, conservatively the root mean square of
        the per-band errors (pooling bands averages some of it away). Where the fixed pattern
        is below what the frames can measure, the percentage is 0 and this is the resolution:
        the true value is below about twice it."""
        if self.fpn_se_percent is None:
            return float("nan")
        v = np.asarray(self.fpn_se_percent)[np.isfinite(self.fpn_se_percent)]
        return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

    @property
    def pooled_eq6_percent(self) -> float:
        """Eq. (6) of all bands, pooled as :attr:`pooled_fpn_percent`."""
        v = self.eq6_percent[np.isfinite(self.eq6_percent)]
        return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")

    def to_dict(self) -> dict:
        """JSON-safe dict (lists per band, pooled figures)."""
        out = {k: np.asarray(getattr(self, k)).tolist() for k in (
            "mean_dn", "fpn_var_dn2", "fpn_dn", "fpn_percent", "temporal_dn", "eq6_percent",
            "n_pixels", "fpn_se_percent")}
        out.update(n_frames=self.n_frames, pooled_fpn_percent=self.pooled_fpn_percent,
                   pooled_eq6_percent=self.pooled_eq6_percent)
        return out


def fixed_pattern_variance(stack, mask=None) -> tuple[float, float, float]:
    """Fixed-pattern variance of a frame stack (EMVA 1288 Release 4.0, spatial nonuniformity).

    Parameters
    ----------
    stack : (L, ...) array, DN
        L >= 2 frames of one illumination step (any per-frame shape).
    mask : (...) bool, optional
        Pixels to use (default: every pixel finite in all frames).

    Returns
    -------
    fpn_var : float, DN^2
        ``s2_measured - sigma2_t / L`` (may be < 0 when the fixed pattern is below the noise).
    temporal_var : float, DN^2
        ``sigma2_t``, the temporal variance of one frame averaged over the pixels.
    mean : float, DN

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> pattern = rng.normal(100.0, 2.0, 200_000)            # fixed pattern: 2 DN
    >>> stack = pattern + rng.normal(0.0, 5.0, (2, 200_000))  # temporal noise: 5 DN
    >>> fpn, tvar, mean = fixed_pattern_variance(stack)
    >>> round(float(np.sqrt(fpn)), 1), round(float(np.sqrt(tvar)), 1)
    (2.0, 5.0)
    """
    s = np.asarray(stack, np.float64)
    if s.ndim < 2 or s.shape[0] < 2:
        raise ValueError(f"stack must hold at least 2 frames of one step along axis 0, got shape "
                         f"{s.shape}; the fixed pattern cannot be told from temporal noise "
                         "with one frame")
    s = s.reshape(s.shape[0], -1)
    use = np.isfinite(s).all(axis=0)
    if mask is not None:
        use &= np.asarray(mask, bool).ravel()
    s = s[:, use]
    if s.shape[1] < 2:
        return float("nan"), float("nan"), float("nan")
    n_frames, n_px = s.shape
    mu = s.mean(axis=0)
    # frame-to-frame changes of the mean level (light flicker) are neither fixed pattern nor
    # pixel noise: each frame's spatial mean is removed before the temporal variance
    resid = s - s.mean(axis=1, keepdims=True)
    temporal = float(resid.var(axis=0, ddof=1).sum() / (n_px - 1))
    measured = float(mu.var(ddof=1))
    return measured - temporal / n_frames, temporal, float(mu.mean())


def fixed_pattern_nonuniformity(stack, band_map=None, *, dark=None, mask=None,
                                dark_stack=None) -> FixedPattern:
    """Fixed-pattern non-uniformity per band of a frame stack, in DN and percent.

    Parameters
    ----------
    stack : (L, H, W) array, DN
        L >= 2 frames of one illumination step (raw, or corrected frames).
    band_map : (H, W) int, optional
        Band index of every pixel (a mosaic's bands see different light); default one band.
    dark : (H, W) array or float, optional, DN
        Subtracted from every frame first, so the percentages are of the signal above dark (the
        EMVA 1288 PRNU). Leave out for frames that are already dark-subtracted.
    mask : (H, W) bool, optional
        Pixels to use, e.g. no DQ bit set in any frame (see :func:`uniformity_before_after`).
    dark_stack : (L_d, H, W) array, optional, DN
        Dark frames of the same exposure (L_d >= 2), instead of ``dark``: their mean is
        subtracted and their temporal variance over ``L_d`` is removed from the fixed-pattern
        variance too (EMVA 1288 Release 4.0 removes the temporal variance of both the bright
        and the dark stack), so neither the dark's temporal noise nor a modelled dark's error
        counts as pattern.

    Returns
    -------
    FixedPattern

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> gain = rng.normal(1.0, 0.01, (64, 64))                  # 1 % fixed pattern
    >>> stack = 100.0 * gain + rng.normal(0.0, 3.0, (4, 64, 64))
    >>> r = fixed_pattern_nonuniformity(stack)
    >>> round(float(r.fpn_percent[0]), 1), bool(r.eq6_percent[0] > 3)
    (1.0, True)
    """
    s = np.asarray(stack, np.float64)
    if s.ndim != 3:
        raise ValueError(f"stack must be (frames, H, W), got shape {s.shape}")
    dstack = None
    if dark_stack is not None:
        if dark is not None:
            raise ValueError("give dark or dark_stack, not both")
        dstack = np.asarray(dark_stack, np.float64)
        if dstack.ndim != 3 or dstack.shape[0] < 2 or dstack.shape[1:] != s.shape[1:]:
            raise ValueError(f"dark_stack must be (L >= 2, H, W) dark frames of the frames' "
                             f"shape {s.shape[1:]}, got shape {dstack.shape}")
        s = s - dstack.mean(axis=0)
    elif dark is not None:
        s = s - np.asarray(dark, np.float64)
    bm = np.zeros(s.shape[1:], np.int64) if band_map is None else np.asarray(band_map)
    if bm.shape != s.shape[1:]:
        raise ValueError(f"band_map has shape {bm.shape} but frames are {s.shape[1:]}")
    use = np.isfinite(s).all(axis=0)
    if mask is not None:
        use &= np.asarray(mask, bool)
    n_bands = int(bm.max()) + 1
    rows = []
    dark_tvar = np.zeros(n_bands)
    for b in range(n_bands):
        sel = use & (bm == b)
        fpn, tvar, mean = fixed_pattern_variance(s[:, sel])
        if dstack is not None:  # the dark mean's temporal variance is not pattern either
            _, dark_tvar[b], _ = fixed_pattern_variance(dstack[:, sel])
            fpn -= dark_tvar[b] / dstack.shape[0]
        eq6 = [_eq6(frame[sel]) for frame in s]
        rows.append((mean, fpn, tvar, float(np.mean(eq6)), int(sel.sum())))
    mean, fpn, tvar, eq6, npx = (np.array(c) for c in zip(*rows))
    fpn_dn = np.sqrt(np.clip(np.nan_to_num(fpn, nan=0.0), 0.0, None))
    fpn_dn = np.where(np.isfinite(fpn), fpn_dn, np.nan)
    n_fr = int(s.shape[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        pct = 100.0 * fpn_dn / mean
        n_d = 2 if dstack is None else dstack.shape[0]
        var_se = np.sqrt(2 * (np.clip(fpn, 0, None) + tvar / n_fr + dark_tvar / n_d) ** 2 / npx
                         + 2 * tvar ** 2 / (npx * n_fr ** 2 * (n_fr - 1))
                         + 2 * dark_tvar ** 2 / (npx * n_d ** 2 * (n_d - 1)))
        se_pct = 100.0 * var_se / (2 * np.maximum(fpn_dn, np.sqrt(var_se))) / mean
    return FixedPattern(mean_dn=mean, fpn_var_dn2=fpn, fpn_dn=fpn_dn, fpn_percent=pct,
                        temporal_dn=np.sqrt(tvar), eq6_percent=eq6, n_pixels=npx.astype(np.int64),
                        n_frames=n_fr, fpn_se_percent=se_pct)


def _eq6(values) -> float:
    """Eq. (6): 100 std / mean of one frame's pixels (percent)."""
    if values.size < 2:
        return float("nan")
    return float(100.0 * values.std() / values.mean())


def uniformity_before_after(frames, pipeline, *, dark=None) -> dict:
    """Fixed-pattern non-uniformity of one step's frames before and after a correction.

    Parameters
    ----------
    frames : list of :class:`hsiffc.data.frame.Frame`
        At least 2 raw frames of one illumination step (same exposure and light).
    pipeline : fitted Pipeline or stage
        Anything with ``transform(frame) -> Frame``.
    dark : (H, W) array or float, optional, DN
        Subtracted from the raw frames for "before" (so both sides are signal above dark).
        Default: the dark the pipeline removed (the corrected frame's ``dark_removed``), else
        none.

    Returns
    -------
    dict
        ``before`` and ``after`` (:class:`FixedPattern`), ``improvement_percent_points``
        (pooled before - after; positive = more uniform), ``n_pixels`` used (pixels with no DQ
        bit set in any frame, before or after, so both sides see the same pixels).
    """
    frames = list(frames)
    if len(frames) < 2:
        raise ValueError(f"give at least 2 frames of one step, got {len(frames)}")
    corrected = [pipeline.transform(f) for f in frames]
    raw = np.stack([f.data for f in frames])
    out = np.stack([c.data for c in corrected])
    if out.shape != raw.shape:
        raise ValueError(f"the pipeline changes the frame shape ({raw.shape[1:]} -> "
                         f"{out.shape[1:]}); compare before reconstruction")
    good = np.all([f.dq == 0 for f in frames] + [c.dq == 0 for c in corrected], axis=0)
    if dark is None:
        dark = corrected[0].dark_removed
    band_map = frames[0].band_map()
    before = fixed_pattern_nonuniformity(raw, band_map, dark=dark, mask=good)
    after = fixed_pattern_nonuniformity(out, band_map, mask=good)
    return {"before": before, "after": after,
            "improvement_percent_points": before.pooled_fpn_percent - after.pooled_fpn_percent,
            "n_pixels": int(good.sum())}
