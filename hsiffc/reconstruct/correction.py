"""Spectral correction matrices on cubes, and the reconstruction error metric."""

from __future__ import annotations

import numpy as np

from ..data.dq import DQ_DTYPE

__all__ = ["apply_correction", "correction_support", "reconstruction_error",
           "reduce_over_support"]


def correction_support(matrix) -> np.ndarray:
    """(V, B) bool: which bands each virtual band depends on (non-zero coefficient).

    Parameters
    ----------
    matrix : (V, B) array_like
        Spectral correction matrix (virtual bands x bands).

    Returns
    -------
    ndarray of bool, (V, B)
    """
    return np.asarray(matrix) != 0


def reduce_over_support(values, support, ufunc, dtype) -> np.ndarray:
    """(..., V): ``ufunc.reduce`` of ``values`` (..., B) over the bands each virtual band
    depends on (``support`` (V, B) bool); virtual bands with the same support share one
    reduction (the dense IMEC matrix: a single one).

    Parameters
    ----------
    values : (..., B) array_like
        Per-band values (e.g. DQ flags or alpha of a cube).
    support : (V, B) ndarray of bool
        From :func:`correction_support`.
    ufunc : numpy.ufunc
        Reduction, e.g. ``np.bitwise_or`` for DQ or ``np.maximum`` for alpha.
    dtype : numpy dtype
        Output dtype.

    Returns
    -------
    ndarray, (..., V)
        Zero for a virtual band that depends on no band.
    """
    values = np.asarray(values)
    out = np.zeros(values.shape[:-1] + (support.shape[0],), dtype)
    rows, inverse = np.unique(support, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    for k, row in enumerate(rows):
        idx = np.nonzero(row)[0]
        if idx.size:
            out[..., inverse == k] = ufunc.reduce(values[..., idx], axis=-1)[..., None]
    return out


def apply_correction(cube, matrix, *, dq=None):
    """Apply a spectral correction matrix per pixel: ``virtual = matrix @ b``.

    Parameters
    ----------
    cube : (..., B) array
        Band values along the last axis in band-index order - for IMEC sensors the pattern
        position order, which is the column order of the vendor matrix
        (:attr:`hsiffc.spectral.ImecSensorCalibration.correction_matrix`).
    matrix : (V, B) array
        Finite coefficients.
    dq : (..., B) uint32, optional
        DQ of the band values. The DQ of a virtual band is the OR of the DQ of every band with a
        non-zero coefficient in its row (with the dense IMEC matrix: the OR of all bands).

    Returns
    -------
    virtual : (..., V) float32
        The virtual-band cube.
    virtual_dq : (..., V) uint32
        Its DQ.
    """
    c = np.asarray(cube)
    m = np.asarray(matrix, dtype=np.float64)
    if m.ndim != 2:
        raise ValueError(f"matrix must be 2-D (n_virtual, n_bands), got shape {m.shape}")
    if c.ndim < 1 or c.shape[-1] != m.shape[1]:
        raise ValueError(f"the cube has {c.shape[-1] if c.ndim else 0} bands on its last axis "
                         f"but the matrix has {m.shape[1]} columns")
    if not np.all(np.isfinite(m)):
        raise ValueError("the correction matrix has NaN or inf coefficients")
    flat = c.reshape(-1, c.shape[-1]).astype(np.float32, copy=False)
    coef = np.ascontiguousarray(m.T, dtype=np.float32)
    out = np.ascontiguousarray((flat @ coef).reshape(c.shape[:-1] + (m.shape[0],)),
                               dtype=np.float32)
    out_dq = np.zeros(out.shape, DQ_DTYPE)
    if dq is not None:
        d = np.asarray(dq)
        if d.shape != c.shape:
            raise ValueError(f"dq has shape {d.shape} but the cube has {c.shape}")
        d = d.astype(DQ_DTYPE, copy=False)
        if not d.any():
            return out, out_dq
        out_dq = reduce_over_support(d, correction_support(m), np.bitwise_or, DQ_DTYPE)
    return out, out_dq


def reconstruction_error(cube, truth_cube, *, border: int = 0) -> np.ndarray:
    """Per-band RMS relative error of a reconstructed cube.

    For band b: ``sqrt(mean((cube - truth)**2)) / mean(truth)`` over the interior pixels
    (``border`` pixels dropped on every side), i.e. the RMS of ``(cube - truth) / mean(truth)``.

    Parameters
    ----------
    cube, truth_cube : (H, W, B) array_like
        Reconstructed and true cube, same shape and unit (e.g. DN).
    border : int
        Pixels dropped on every side before the statistics (>= 0, leaving an interior).

    Returns
    -------
    ndarray of float64, (B,)
        Relative error per band (dimensionless; 0.01 = 1 %).

    Raises
    ------
    ValueError
        Shapes differ or are not 3-D, the border leaves no interior, or a band's true mean is 0.

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.ones((4, 4, 2))
    >>> reconstruction_error(truth * 1.01, truth).round(6).tolist()
    [0.01, 0.01]
    """
    a = np.asarray(cube, dtype=np.float64)
    t = np.asarray(truth_cube, dtype=np.float64)
    if a.shape != t.shape or a.ndim != 3:
        raise ValueError(f"cube {a.shape} and truth {t.shape} must be (H, W, B) of one shape")
    border = int(border)
    if border < 0 or 2 * border >= min(a.shape[0], a.shape[1]):
        raise ValueError(f"border={border} leaves no interior in a {a.shape[:2]} cube")
    if border:
        a = a[border:-border, border:-border]
        t = t[border:-border, border:-border]
    mean = t.mean(axis=(0, 1))
    if np.any(mean == 0):
        raise ValueError("a band of the true cube has mean 0; the relative error is undefined")
    rms = np.sqrt(np.mean((a - t) ** 2, axis=(0, 1)))
    return rms / np.abs(mean)
