"""Statistics of a mosaic frame per band: one function, :func:`band_reduce`, for every caller.

Every band of a snapshot mosaic sees its own light, so flat-field normalisation, alpha tables
and uniformity figures are taken per band. An empty band (no usable pixel) gives NaN, meaning
"no statistic": each caller turns it into its own neutral value (a flat-field factor of 1 with
the NO_FLAT flag; ``inf``, "no alpha", in alpha tables), so NaN never reaches an output.
"""

from __future__ import annotations

import numpy as np

from ..kernels.bands import band_sums
from ..data.mosaic import row_period
from ..data.params import validate_method

STATISTICS = ("mean", "median", "p95")


def band_layout(values, band_map, mask=None, mask_name: str = "good", *,
                what: str = "the image"):
    """Check a frame's band map (and a per-pixel mask) against its values; the band
    statistics' common start.

    Parameters
    ----------
    values : (H, W) ndarray
    band_map : (H, W) int array or None (the whole frame is band 0)
    mask : (H, W) array, optional
        A per-pixel plane that must have the values' shape (``good``, ``dq``).
    mask_name : str
        Its name in the error message.
    what : str
        The values' name in the error messages.

    Returns
    -------
    band_map : ndarray
    period : int
        :func:`hsiffc.data.mosaic.row_period` of the map (0 if unknown).
    n_bands : int
        ``band_map.max() + 1``.

    Raises
    ------
    ValueError
        A shape differs, the frame is empty or a band index is negative.
    """
    v = np.asarray(values)
    bm = np.zeros(v.shape, np.intp) if band_map is None else np.asarray(band_map)
    if bm.shape != v.shape:
        raise ValueError(f"band_map has shape {bm.shape} but {what} has {v.shape}; give the "
                         "band map of the same frame")
    if mask is not None and np.shape(mask) != v.shape:
        raise ValueError(f"{mask_name} has shape {np.shape(mask)} but {what} has {v.shape}; "
                         f"give the {mask_name} plane of the same frame")
    if v.size == 0:
        raise ValueError(f"{what} is empty (shape {v.shape}); band statistics need at least "
                         "one pixel")
    period = row_period(band_map) if v.ndim == 2 else 0  # a mosaic's map: first rows say all
    rows = bm[:period] if period else bm
    if not np.issubdtype(rows.dtype, np.integer):
        raise ValueError(f"band_map must hold integer band indices, not {rows.dtype}")
    if rows.min() < 0:
        raise ValueError(f"band_map has a negative band index ({rows.min()}); bands are "
                         "numbered from 0")
    return bm, period, int(rows.max()) + 1


def band_mean(sums, counts) -> np.ndarray:
    """The mean per band from its sum and count (:func:`hsiffc.kernels.bands.band_sums`):
    NaN where the count is 0."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def band_reduce(values, band_map=None, good=None, *, statistic: str = "mean",
                n_bands: int | None = None) -> np.ndarray:
    """One statistic of ``values`` per band, over the good, finite pixels.

    Parameters
    ----------
    values : (H, W) array_like
        Per-pixel values (any unit; the result has the same unit).
    band_map : (H, W) int array, optional
        Band index per pixel (None: the whole frame is band 0).
    good : (H, W) bool array, optional
        Pixels to use (None: all). Non-finite values are never used.
    statistic : "mean", "median" or "p95"
    n_bands : int, optional
        Length of the result (default ``band_map.max() + 1``).

    Returns
    -------
    (n_bands,) float64
        The statistic per band; NaN for a band without a usable pixel. Index with
        ``result[band_map]`` to broadcast it back per pixel.

    Examples
    --------
    >>> band_reduce(np.array([[1., 3.], [5., np.nan]]), np.array([[0, 0], [1, 1]])).tolist()
    [2.0, 5.0]
    >>> band_reduce(np.ones((2, 2)), np.zeros((2, 2), int), np.zeros((2, 2), bool)).tolist()
    [nan]
    """
    validate_method(statistic, STATISTICS, "band statistic")
    v = np.asarray(values)
    bm, period, n = band_layout(v, band_map, good, "good", what="values")
    if n_bands is not None:
        n = int(n_bands)
    if statistic == "mean":  # one compiled pass (hsiffc.kernels.bands)
        as2d = (lambda a: np.reshape(a, (1, -1) if v.ndim < 2 else (-1, v.shape[-1])))
        sums, counts = band_sums(as2d(v), as2d(bm), None if good is None else as2d(good), n,
                                 period)
        return band_mean(sums, counts)
    v = np.asarray(v, np.float64)
    use = np.isfinite(v)
    if good is not None:
        use &= np.asarray(good, bool)
    out = np.full(n, np.nan)
    q = 50.0 if statistic == "median" else 95.0
    for band in range(n):
        sel = v[use & (bm == band)]
        if sel.size:
            out[band] = np.percentile(sel, q)
    return out
