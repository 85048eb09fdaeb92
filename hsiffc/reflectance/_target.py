"""How well a reflectance product measures a target of known reflectance (a white or grey panel).

The paper's eq. (6) of a *scene* says nothing about a reflectance product: a scene is not
uniform. What a field user can check is a uniform target of known reflectance recorded like a
scene (the white panel itself, or a grey card): per band, the mean reflectance against the
target's value (an exposure, gain or leakage error shows here) and the uniformity of the
reflectance over the target, with the temporal noise taken out when there are several frames
(:func:`hsiffc.flatfield.uniformity.fixed_pattern_nonuniformity`, the EMVA 1288 way), so that what is
left is the pattern the reflectance product itself carries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.mosaic import band_labels, wavelength_order
from ..flatfield.uniformity import fixed_pattern_nonuniformity

__all__ = ["TargetReport", "target_report"]


@dataclass(frozen=True)
class TargetReport:
    """Figures of a uniform target's reflectance, per band (:func:`target_report`).

    Attributes
    ----------
    expected : (bands,) float
        The target's reflectance factor.
    mean : (bands,) float
        Mean reflectance over the good values of every frame.
    bias_percent : (bands,) float
        ``100 (mean / expected - 1)``.
    fixed_pattern_percent : (bands,) float
        Non-uniformity of the reflectance with the temporal noise removed (percent of the
        mean; NaN with one frame).
    temporal_percent : (bands,) float
        One frame's temporal noise (percent of the mean; NaN with one frame).
    single_frame_percent : (bands,) float
        ``100 std / mean`` of one frame (noise included), averaged over the frames.
    n_values : (bands,) int
    n_frames : int
    """

    expected: np.ndarray
    mean: np.ndarray
    bias_percent: np.ndarray
    fixed_pattern_percent: np.ndarray
    temporal_percent: np.ndarray
    single_frame_percent: np.ndarray
    n_values: np.ndarray
    n_frames: int

    def to_dict(self) -> dict:
        """JSON-safe per-band lists (None for NaN)."""
        def lst(a):
            return [None if not np.isfinite(v) else float(f"{v:.6g}") for v in np.asarray(a,
                                                                                       float)]
        return {"expected": lst(self.expected), "mean": lst(self.mean),
                "bias_percent": lst(self.bias_percent),
                "fixed_pattern_percent": lst(self.fixed_pattern_percent),
                "temporal_percent": lst(self.temporal_percent),
                "single_frame_percent": lst(self.single_frame_percent),
                "n_values": [int(v) for v in self.n_values], "n_frames": int(self.n_frames)}

    def to_text(self, wavelengths_nm=None, labels=None) -> str:
        """A table, one row per band, by wavelength; ``labels``: each band's label by band
        index (:meth:`hsiffc.data.frame.Frame.band_labels`; default from the wavelengths)."""
        n = len(self.mean)
        labels = labels or band_labels(n, wavelengths_nm)
        width = max(len(s) for s in labels)
        lines = [f"target: {self.n_frames} frame(s); reflectance per band (mean against the "
                 "target's value; non-uniformity with the temporal noise removed)",
                 f"{'band':<{width}} {'expected':>9} {'mean':>8} {'bias %':>8} "
                 f"{'pattern %':>10} {'noise %':>8} {'1 frame %':>10}"]
        for i in wavelength_order(n, wavelengths_nm):
            lines.append(f"{labels[i]:<{width}} {self.expected[i]:>9.4f} {self.mean[i]:>8.4f} "
                         f"{self.bias_percent[i]:>+8.2f} {self.fixed_pattern_percent[i]:>10.2f} "
                         f"{self.temporal_percent[i]:>8.2f} {self.single_frame_percent[i]:>10.2f}")
        return "\n".join(lines)


def target_report(reflectance, dq, bands, n_bands: int, expected) -> TargetReport:
    """Figures of a uniform target's reflectance frames.

    Parameters
    ----------
    reflectance : (L, ...) array_like
        L >= 1 reflectance frames of the target (mosaic frames or cubes), cropped to it.
    dq : (L, ...) uint32
        Their DQ planes; a value flagged in any frame is left out.
    bands : int array, shape of one frame
        Band index of each value.
    n_bands : int
    expected : float or (n_bands,) array_like
        The target's reflectance factor.

    Returns
    -------
    TargetReport

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> frames = 0.5 * (1 + 0.01 * rng.standard_normal((1, 64))) + 0.005 * rng.standard_normal((4, 64))
    >>> r = target_report(frames, np.zeros((4, 64), np.uint32), np.zeros(64, int), 1, 0.5)
    >>> round(float(r.fixed_pattern_percent[0])), round(float(r.temporal_percent[0]))
    (1, 1)
    """
    s = np.asarray(reflectance, np.float64)
    n = s.shape[0]
    good = (np.bitwise_or.reduce(np.asarray(dq), axis=0) == 0) & np.isfinite(s).all(axis=0)
    flat = s.reshape(n, 1, -1)
    bmap = np.broadcast_to(np.asarray(bands), s.shape[1:]).reshape(1, -1)
    mask = good.reshape(1, -1)
    expected = np.broadcast_to(np.asarray(expected, np.float64), (n_bands,))
    mean = np.full(n_bands, np.nan)
    single = np.full(n_bands, np.nan)
    counts = np.zeros(n_bands, int)
    for b in range(n_bands):
        sel = mask[0] & (bmap[0] == b)
        counts[b] = int(sel.sum())
        if counts[b] >= 2:
            v = flat[:, 0, sel]
            mean[b] = v.mean()
            single[b] = float(np.mean(100 * v.std(axis=1, ddof=1) / v.mean(axis=1)))
    fpn = np.full(n_bands, np.nan)
    temporal = np.full(n_bands, np.nan)
    if n >= 2:
        fp = fixed_pattern_nonuniformity(flat, bmap, mask=mask)
        k = min(n_bands, len(fp.fpn_percent))
        fpn[:k] = fp.fpn_percent[:k]
        temporal[:k] = 100 * fp.temporal_dn[:k] / fp.mean_dn[:k]
    return TargetReport(expected.copy(), mean, 100 * (mean / expected - 1), fpn, temporal,
                        single, counts, n)
