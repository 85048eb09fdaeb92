"""Reduced-resolution cubes: one spectrum per complete mosaic tile."""

from __future__ import annotations

import numpy as np

from ..data.dq import DQ, DQ_DTYPE
from ..data.mosaic import Mosaic
from .prepare import EPS, prepare, sep_filter

__all__ = ["tile_alpha", "tile_blocks", "tile_cube", "tile_grid", "tile_origin"]


def tile_grid(shape, mosaic: Mosaic):
    """(row, col) of the first complete tile and the number of complete tiles (ny, nx).

    Parameters
    ----------
    shape : (int, int)
        (H, W) of the frame.
    mosaic : Mosaic
        Its layout (tile shape and offset).

    Returns
    -------
    y0, x0, ny, nx : int
        First complete tile's row and column, and the number of complete tiles.

    Raises
    ------
    ValueError
        The frame holds no complete tile.
    """
    H, W = int(shape[0]), int(shape[1])
    ph, pw = mosaic.tile_shape
    y0, x0 = mosaic.offset[0] % ph, mosaic.offset[1] % pw
    ny, nx = (H - y0) // ph, (W - x0) // pw
    if ny < 1 or nx < 1:
        raise ValueError(f"a frame of {H} x {W} pixels holds no complete {ph} x {pw} tile "
                         f"starting at offset {mosaic.offset}")
    return y0, x0, ny, nx


def tile_blocks(plane: np.ndarray, y0, x0, ny, nx, ph, pw) -> np.ndarray:
    """(ny, nx, ph, pw) view of the complete tiles of a plane.

    Parameters
    ----------
    plane : (H, W) ndarray
        Any per-pixel plane (raw, DQ, alpha).
    y0, x0, ny, nx : int
        From :func:`tile_grid`.
    ph, pw : int
        Tile shape.

    Returns
    -------
    ndarray, (ny, nx, ph, pw)
        A view (no copy) when ``plane`` is contiguous.
    """
    block = plane[y0:y0 + ny * ph, x0:x0 + nx * pw]
    return block.reshape(ny, ph, nx, pw).transpose(0, 2, 1, 3)


def tile_origin(shape, mosaic: Mosaic) -> tuple[int, int]:
    """(row, col) of the first complete tile: ``tile_cube`` pixel (i, j) covers raw pixels
    ``origin + (i ph .. i ph + ph - 1, j pw .. j pw + pw - 1)``.

    Parameters
    ----------
    shape : (int, int)
        (H, W) of the frame.
    mosaic : Mosaic
        Its layout.

    Returns
    -------
    (int, int)
        Row and column of the first complete tile.
    """
    y0, x0, _, _ = tile_grid(shape, mosaic)
    return y0, x0


def tile_cube(raw, mosaic: Mosaic, *, dq=None):
    """One spectrum per complete tile: the reduced-resolution cube ``(H', W', B)``.

    Tiles start at ``mosaic.offset`` (modulo the tile shape); incomplete tiles at the borders
    are dropped, so ``H' = (H - offset_row % ph) // ph`` (see :func:`tile_origin`). A band
    occurring more than once per tile takes the mean of its unflagged samples.

    Flagged samples: a tile whose band samples are all flagged takes the tent-weighted mean of
    the band in the 8 neighbouring tiles (unflagged ones; weights 1/2 side, 1/4 corner), else
    the median of the band's values in the tiles that have an unflagged sample (0 if no tile
    has one), with ``DO_NOT_USE``. DQ of a cube value = OR of the flags of the band's samples
    in its tile (plus ``DO_NOT_USE`` where the median was used).

    Parameters
    ----------
    raw : (H, W) array_like, DN
        Raw (or corrected) mosaic frame.
    mosaic : Mosaic
        Its layout.
    dq : (H, W) uint32 array, optional
        DQ flags of the raw pixels; flagged samples are not used.

    Returns
    -------
    cube : ndarray of float32, (H', W', B)
        One spectrum per complete tile, in the unit of ``raw``.
    cube_dq : ndarray of uint32, (H', W', B)

    Examples
    --------
    >>> import numpy as np
    >>> from hsiffc.data.mosaic import Mosaic
    >>> raw = np.tile(np.array([[10., 20.], [30., 40.]], np.float32), (3, 4))   # (6, 8)
    >>> cube, cube_dq = tile_cube(raw, Mosaic.square(2))
    >>> cube.shape, cube[0, 0].tolist()
    ((3, 4, 4), [10.0, 20.0, 30.0, 40.0])
    """
    p = prepare(raw, mosaic, dq)
    ph, pw = p.period
    y0, x0, ny, nx = tile_grid(p.shape, mosaic)
    tv = tile_blocks(p.raw, y0, x0, ny, nx, ph, pw)
    tg = tile_blocks(p.good, y0, x0, ny, nx, ph, pw)
    flags = np.zeros(p.shape, DQ_DTYPE) if p.dq is None else p.dq
    tq = tile_blocks(flags, y0, x0, ny, nx, ph, pw)
    B = mosaic.n_bands
    cube = np.empty((ny, nx, B), np.float32)
    cube_dq = np.zeros((ny, nx, B), DQ_DTYPE)
    k3 = np.array([0.5, 1.0, 0.5], np.float32)
    for b in range(B):
        rs, cs = np.nonzero(mosaic.pattern == b)
        v = tv[:, :, rs, cs]
        g = tg[:, :, rs, cs]
        cnt = g.sum(axis=-1).astype(np.float32)
        s = np.where(g, v, 0).sum(axis=-1, dtype=np.float32)
        have = cnt > 0
        est = np.divide(s, cnt, out=np.zeros((ny, nx), np.float32), where=have)
        bdq = np.bitwise_or.reduce(tq[:, :, rs, cs], axis=-1)
        if not have.all():
            w = have.astype(np.float32)
            num = sep_filter(est * w, k3, k3)
            den = sep_filter(w, k3, k3)
            fill = ~have & (den > EPS)
            est[fill] = num[fill] / den[fill]
            none = ~have & ~fill
            if none.any():
                est[none] = np.median(est[have]) if have.any() else 0.0
                bdq[none] |= DQ_DTYPE(DQ.DO_NOT_USE)
        cube[:, :, b] = est
        cube_dq[:, :, b] = bdq
    return cube, cube_dq


def tile_alpha(alpha, mosaic: Mosaic) -> np.ndarray:
    """(H', W', B) float32: the max alpha over each band's samples in each complete tile
    (``reconstruct_alpha(..., resolution="tile")``; ``alpha`` finite float32).

    Parameters
    ----------
    alpha : (H, W) ndarray of float32, percent
        Leakage percentage of every raw pixel (finite).
    mosaic : Mosaic
        Layout of the frame.

    Returns
    -------
    ndarray of float32, (H', W', B), percent
    """
    ph, pw = mosaic.tile_shape
    y0, x0, ny, nx = tile_grid(alpha.shape, mosaic)
    ta = tile_blocks(alpha, y0, x0, ny, nx, ph, pw)
    out = np.empty((ny, nx, mosaic.n_bands), np.float32)
    for b in range(mosaic.n_bands):
        rs, cs = np.nonzero(mosaic.pattern == b)
        out[:, :, b] = ta[:, :, rs, cs].max(axis=-1)
    return out
