"""Hot and dead pixel detection and repair from same-band neighbours (an hsiffc plugin stage).

On a snapshot mosaic the eight nearest pixels of a pixel see other bands, so a general-purpose
filter such as a 3x3 median replaces a defect with a mixture of bands. This stage only uses
pixels of the same band: those a whole number of mosaic tiles away.
"""

from __future__ import annotations

import warnings

import numpy as np

from hsiffc.data.dq import DQ, DQ_DTYPE
from hsiffc.data.params import Param
from hsiffc.stages import Stage

__all__ = ["HotPixelRepair", "same_band_offsets", "same_band_median"]
__version__ = "0.1.0"

#: Quantisation noise of an integer ADC (DN): the robust sigma is never taken below it, so a
#: perfectly uniform dark does not make every pixel 1 DN above its neighbours "hot".
SIGMA_FLOOR_DN = float(1.0 / np.sqrt(12.0))


def same_band_offsets(tile_shape, radius: int = 1) -> list[tuple[int, int]]:
    """Offsets (dy, dx) to the same-band neighbours within ``radius`` tiles.

    Examples
    --------
    >>> same_band_offsets((2, 4))
    [(-2, -4), (-2, 0), (-2, 4), (0, -4), (0, 4), (2, -4), (2, 0), (2, 4)]
    """
    ph, pw, r = int(tile_shape[0]), int(tile_shape[1]), int(radius)
    return [(i * ph, j * pw) for i in range(-r, r + 1) for j in range(-r, r + 1)
            if (i, j) != (0, 0)]


def same_band_median(values, offsets, rows=None, cols=None, exclude=None) -> np.ndarray:
    """Median of the neighbours at ``offsets`` of the pixels (rows, cols) (default: all pixels).

    Neighbours off the sensor or where ``exclude`` is True are left out; the result is NaN
    where no neighbour remains. Returns a float32 array shaped like ``rows`` (or like
    ``values`` when every pixel is asked for).
    """
    values = np.asarray(values, dtype=np.float32)
    h, w = values.shape
    full = rows is None
    if full:
        rows, cols = np.indices((h, w)).reshape(2, -1)
    stack = np.full((len(offsets), rows.size), np.nan, dtype=np.float32)
    for k, (dy, dx) in enumerate(offsets):
        r, c = rows + dy, cols + dx
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        if exclude is not None:
            inside[inside] &= ~exclude[r[inside], c[inside]]
        stack[k, inside] = values[r[inside], c[inside]]
    with warnings.catch_warnings():  # "All-NaN slice": those pixels have no neighbour left
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(stack, axis=0)
    return med.reshape(h, w) if full else med


def _by_exposure(frames, kind: str) -> dict[float, list]:
    groups: dict[float, list] = {}
    for f in frames:
        if f.kind == kind:
            groups.setdefault(round(f.exposure_ms, 6), []).append(f)
    return groups


def _median_frame(frames) -> np.ndarray:
    return np.median(np.stack([f.data for f in frames]), axis=0).astype(np.float32)


class HotPixelRepair(Stage):
    """Detect hot and dead pixels in training frames and repair them from same-band neighbours.

    Place it first in a pipeline, on raw frames: a pipeline then also repairs the training
    darks and flats that later stages learn from, so the dark stage sees a repaired pixel's
    dark consistently.

    Parameters
    ----------
    hot_sigma : float
        A pixel is hot when its master dark (median of the training darks of the longest dark
        exposure) exceeds the median of its same-band neighbours by more than ``hot_sigma``
        robust sigmas (1.4826 x MAD of that residual over the sensor).
    dead_fraction : float
        A pixel is dead when its dark-subtracted flat response (training light frames of an
        exposure that has darks, else minus the master dark) is below ``dead_fraction`` of its
        same-band neighbourhood median. A pixel found hot is not also tested for dead.
    radius : int
        Neighbourhood size in mosaic tiles: the same-band pixels at (i*ph, j*pw) for
        -radius <= i, j <= radius, (ph, pw) the tile shape (1 x 1 without a mosaic).

    Attributes
    ----------
    hot_, dead_ : ndarray of uint8, (H, W)
        Defect maps (1 = flagged).
    n_hot_, n_dead_ : int
    sigma_dn_ : float or None
        Robust sigma of the dark residual (None without dark frames).
    dark_exposure_ms_, flat_exposure_ms_ : float or None
        Exposures the detection used.

    Examples
    --------
    >>> from hsiffc.stages import create
    >>> create("hot_pixel_repair", hot_sigma=8.0)
    HotPixelRepair(hot_sigma=8.0, dead_fraction=0.5, radius=1)
    """

    name = "hot_pixel_repair"
    #: it needs raw mosaic frames (the darks it learns from keep their dark level)
    requires = frozenset({"mosaic", "raw"})
    param_spec = {"hot_sigma": Param("number", low=0, low_open=True),
                  "dead_fraction": Param("number", low=0, high=1, low_open=True,
                                         high_open=True),
                  "radius": Param("integer", low=1)}

    def __init__(self, *, hot_sigma: float = 6.0, dead_fraction: float = 0.5, radius: int = 1):
        self.hot_sigma = hot_sigma
        self.dead_fraction = dead_fraction
        self.radius = radius

    def fit(self, frames) -> "HotPixelRepair":
        """Find hot pixels in the training darks and dead pixels in the training flats."""
        self.validate_params()
        frames = [f for f in frames if not f.is_cube]
        if not frames:
            raise ValueError("hot_pixel_repair needs raw training frames: darks (for hot "
                             "pixels) and/or flats (for dead pixels)")
        if any(f.dark_removed is not None for f in frames):
            raise ValueError("training frames are already dark-subtracted; place "
                             "hot_pixel_repair before the dark stage (it needs raw darks)")
        shape, mosaic = frames[0].data.shape, frames[0].mosaic
        if any(f.data.shape != shape for f in frames):
            raise ValueError("training frames differ in shape; give frames of one sensor region")
        tile = mosaic.tile_shape if mosaic is not None else (1, 1)
        offsets = same_band_offsets(tile, self.radius)
        darks, lights = _by_exposure(frames, "dark"), _by_exposure(frames, "light")
        hot, dead, master = np.zeros(shape, bool), np.zeros(shape, bool), None
        self.sigma_dn_ = self.dark_exposure_ms_ = self.flat_exposure_ms_ = None
        if darks:
            t_dark = max(darks)
            master = _median_frame(darks[t_dark])
            resid = master - same_band_median(master, offsets)
            finite = np.isfinite(resid)
            r = resid[finite]
            sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))) if r.size else 0.0,
                        SIGMA_FLOOR_DN)
            hot = finite & (resid > float(self.hot_sigma) * sigma)
            self.sigma_dn_, self.dark_exposure_ms_ = sigma, float(t_dark)
        if lights:
            matched = [t for t in lights if t in darks]
            t_flat = max(matched) if matched else max(lights)
            flat = _median_frame(lights[t_flat])
            if matched:
                flat = flat - _median_frame(darks[t_flat])
            elif master is not None:
                flat = flat - master
            ref = same_band_median(flat, offsets)
            with np.errstate(invalid="ignore"):
                dead = (ref > 0) & (flat < float(self.dead_fraction) * ref) & ~hot
            self.flat_exposure_ms_ = float(t_flat)
        self.hot_ = hot.astype(np.uint8)
        self.dead_ = dead.astype(np.uint8)
        self.n_hot_, self.n_dead_ = int(hot.sum()), int(dead.sum())
        self.tile_shape_ = [int(tile[0]), int(tile[1])]
        self.fitted_ = True
        return self

    def transform(self, frame):
        """A new frame with hot/dead pixels replaced by the median of their unflagged same-band
        neighbours and DQ.HOT / DQ.DEAD set (a defect with no usable neighbour keeps its value
        and also gets DO_NOT_USE)."""
        self.check_is_fitted()
        hot, dead = np.asarray(self.hot_, bool), np.asarray(self.dead_, bool)
        if frame.is_cube:
            raise ValueError("hot_pixel_repair works on raw mosaic frames, not cubes; place it "
                             "before reconstruction")
        if frame.data.shape != hot.shape:
            raise ValueError(f"frame has shape {frame.data.shape} but the defect maps were "
                             f"learnt on {hot.shape}; use frames of the same sensor region")
        tile = frame.mosaic.tile_shape if frame.mosaic is not None else (1, 1)
        if list(tile) != list(self.tile_shape_):
            raise ValueError(f"frame mosaic tile {tuple(tile)} differs from the training "
                             f"tile {tuple(self.tile_shape_)}")
        bad = hot | dead
        unusable = bad | ((frame.dq & DQ_DTYPE(DQ.DO_NOT_USE)) != 0)
        rows, cols = np.nonzero(bad)
        data, dq, kept = frame.data.copy(), frame.dq.copy(), 0
        if rows.size:
            med = same_band_median(frame.data, same_band_offsets(tile, self.radius), rows, cols,
                                   exclude=unusable)
            ok = np.isfinite(med)
            data[rows[ok], cols[ok]] = med[ok]
            dq[rows[~ok], cols[~ok]] |= DQ_DTYPE(DQ.DO_NOT_USE)
            kept = int((~ok).sum())
        dq[hot] |= DQ_DTYPE(DQ.HOT)
        dq[dead] |= DQ_DTYPE(DQ.DEAD)
        info = {"hot": int(hot.sum()), "dead": int(dead.sum()), "unrepaired": kept}
        return frame.replace(data=data, dq=dq, meta={"hot_pixel_repair": info})
