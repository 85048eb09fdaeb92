"""Per-frame statistics a batch records: eq. (6) non-uniformity per band before and after.

Like for like, as the demo's fixed-pattern table: "before" is the input less the dark the
pipeline removed (a dark pedestal would inflate eq. 6's mean and make the input look more
uniform than its signal is), "after" the corrected data, both over the same pixels (no DQ bit
in the input nor in the output). On large frames the statistic is taken on whole tile rows,
evenly spaced, totalling about ``STATS_PIXELS`` pixels, so it costs little next to the
correction itself.
"""

from __future__ import annotations

import numpy as np

from ..data.mosaic import mosaic_band_labels, wavelength_order
from ..flatfield.two_point import uniformity_per_band

__all__ = ["STATS_PIXELS", "FrameStats", "band_uniformity", "cube_uniformity", "mean_bands",
           "stats_rows"]

STATS_PIXELS = 1 << 16


def stats_rows(shape, mosaic) -> np.ndarray:
    """Rows (whole tile rows, evenly spaced) on which uniformity is estimated."""
    h, w = shape
    th = mosaic.tile_shape[0] if mosaic is not None else 1
    blocks = h // th
    if blocks == 0 or h * w <= STATS_PIXELS:
        return np.arange(h)
    step = max(1, blocks // max(1, STATS_PIXELS // (w * th)))
    return (np.arange(0, blocks, step)[:, None] * th + np.arange(th)[None, :]).ravel()


def band_uniformity(values, band, dq) -> list:
    """Eq. (6) per band over the pixels without DQ bits (:func:`hsiffc.flatfield.two_point.uniformity_per_band`),
    rounded to 4 significant digits; None where a band has no value."""
    u = uniformity_per_band(values, band, dq=dq)
    return [float(f"{x:.4g}") if np.isfinite(x) else None for x in u]


def cube_uniformity(cube, dq) -> list:
    """Eq. (6) per band of a cube (H, W, B) on evenly spaced rows (about :data:`STATS_PIXELS`
    values per band), over the values without DQ bits."""
    h, w, n = cube.shape
    rows = stats_rows((h, w), None)
    values = cube[rows].reshape(-1, n)
    band = np.broadcast_to(np.arange(n), values.shape)
    return band_uniformity(values, np.ascontiguousarray(band), dq[rows].reshape(-1, n))


def mean_bands(rows) -> list:
    """Per band mean over frames (None entries are bands without a value)."""
    v = np.array([[np.nan if x is None else x for x in r] for r in rows], float)
    ok = np.isfinite(v)
    mean = np.where(ok, v, 0.0).sum(0) / np.maximum(ok.sum(0), 1)
    return [float(m) if c else None for m, c in zip(mean, ok.any(0))]


class FrameStats:
    """Statistics of one file's frames, collected frame by frame (a few numbers per frame).

    Parameters
    ----------
    shape : (int, int)
        Frame shape (H, W).
    mosaic : Mosaic or None
        Band layout; without one the whole frame is one band.
    """

    def __init__(self, shape, mosaic):
        self.rows = stats_rows(shape, mosaic)
        full = mosaic.band_map(shape) if mosaic is not None else np.zeros(shape, np.int64)
        self.band = full[self.rows]
        if mosaic is not None:  # whole tile rows: the map of a frame that high, which band
            rows_map = mosaic.band_map((len(self.rows), shape[1]))  # statistics sum by phase
            if np.array_equal(rows_map, self.band):
                self.band = rows_map
        self.n_bands = int(self.band.max()) + 1
        # how users see the bands: numbered by wavelength, with the mosaic position
        self.labels = mosaic_band_labels(mosaic, self.n_bands)
        self.order = wavelength_order(self.n_bands, None if mosaic is None
                                      else mosaic.wavelengths_nm)
        self.all_rows = len(self.rows) == shape[0]
        self.nonfinite, self.flagged, self.before, self.after = [], [], [], []
        self.nonfinite_out: list = []

    def add(self, frame, result, nonfinite: int, nonfinite_out: int = 0) -> None:
        """Record input ``frame`` and its corrected ``result`` (Frames) with its counts of
        NaN/inf pixels in the input and in the corrected data. Eq. (6) before: the input less
        ``result.dark_removed``; after: ``result.data``; both over the pixels without a DQ bit
        in either."""
        r = self.rows
        self.nonfinite.append(int(nonfinite))
        self.nonfinite_out.append(int(nonfinite_out))
        self.flagged.append(round(np.count_nonzero(result.dq) / result.dq.size, 6))
        # eq. (6) of a scene is no figure of a reflectance product (a scene is not uniform):
        # 'hsiffc reflectance check' measures one on a uniform target
        if frame.kind != "light" or result.meta.get("units") == "reflectance factor":
            self.before.append(None)
            self.after.append(None)
            return
        if result.is_cube:  # before: the mosaic frame's own flags; after: the cube's bands
            before = frame.data[r]
            if result.dark_removed is not None:
                before = before - result.dark_removed[r]
            self.before.append(band_uniformity(before, self.band, frame.dq[r]))
            self.after.append(cube_uniformity(result.data, result.dq))
            return
        dq = frame.dq[r] | result.dq[r]  # the same pixels before and after
        before = frame.data[r]
        if result.dark_removed is not None:
            before = before - result.dark_removed[r]
        self.before.append(band_uniformity(before, self.band, dq))
        self.after.append(band_uniformity(result.data[r], self.band, dq))

    def to_dict(self) -> dict:
        """The per-frame lists, as the provenance records them."""
        return {"nonfinite_pixels": self.nonfinite, "nonfinite_output_pixels": self.nonfinite_out,
                "flagged_fraction": self.flagged,
                "uniformity_before": self.before, "uniformity_after": self.after,
                "uniformity_rows": "all" if self.all_rows else len(self.rows)}

    def file_result(self) -> dict:
        """``light_frames`` and the per band means over the light frames (None when none),
        by band index; ``band_labels`` and ``band_order`` (band indices by wavelength) say how
        tables name and list them."""
        light = [b for b in self.before if b is not None]
        if not light:
            return {}
        return {"light_frames": len(light), "uniformity_before": mean_bands(light),
                "uniformity_after": mean_bands([a for a in self.after if a is not None]),
                "band_labels": self.labels, "band_order": self.order}
