"""Figures for reports: matplotlib's object API on figures the report creates.

Reports never call ``matplotlib.use`` and never touch ``pyplot``'s global state, so running a
report from a notebook leaves the user's backend and open figures alone.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..files.atomic import atomic_path

__all__ = ["new_figure", "save_figure"]


def new_figure(figsize=(6.4, 4.2), *, dpi: float = 100, nrows: int = 1, ncols: int = 1,
               **subplot_kw):
    """A new figure with an Agg canvas and its axes.

    Parameters
    ----------
    figsize : (width, height)
        Size in inches.
    dpi : float
        Dots per inch of the figure (``save_figure`` may override it when writing).
    nrows, ncols : int
        Grid of axes, as in :meth:`matplotlib.figure.Figure.subplots`.
    **subplot_kw
        Passed to :meth:`~matplotlib.figure.Figure.subplots` (``sharex``, ``gridspec_kw``...).

    Returns
    -------
    fig : matplotlib.figure.Figure
    axes : Axes or ndarray of Axes
        One Axes for a 1 x 1 grid, else an array of shape ``(nrows, ncols)`` (squeezed).

    Examples
    --------
    >>> fig, ax = new_figure((3, 2))
    >>> _ = ax.plot([0, 1], [0, 1])
    >>> fig.get_size_inches().tolist()
    [3.0, 2.0]
    """
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, **subplot_kw)
    return fig, axes


def save_figure(fig, path, *, dpi: float = 90, tight: bool = True,
                overwrite: bool | None = None) -> Path:
    """Write ``fig`` as a PNG atomically (a partly written file never appears at ``path``).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : path-like
        Output ``.png``.
    dpi : float
        Resolution of the PNG.
    tight : bool
        Crop to the drawn content (``bbox_inches="tight"``).
    overwrite : bool, optional
        Replace an existing file (None: as the write policy in force says, see
        :func:`hsiffc.files.atomic.write_policy`).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    return path
