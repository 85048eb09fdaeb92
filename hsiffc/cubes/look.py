"""One picture of a cube: :func:`quicklook` (``hsiffc quicklook CUBE -o PNG``).

Four panels: a pseudo-colour image from three wavelengths, a grid of bands, the DQ map (the
share of bands flagged at each pixel, and the most frequent flags) and the spectrum of a pixel
or region (median and 10-90 % range of its unflagged values, flagged values marked). The
figure is made with matplotlib's object API on the Agg canvas (no display, no global state).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..files.atomic import atomic_path
from ..data.dq import DQ
from ..data.mosaic import band_numbers

__all__ = ["quicklook"]

#: the most image pixels drawn along a side: the pseudo-colour and DQ panels, and each panel
#: of the band grid (a PNG of 1400 x 1000 px shows no more; a full sensor's cube is shown
#: every few pixels, its statistics still from every pixel)
DISPLAY_PX, GRID_PX = 1024, 384


def _stretch(image, good, lo=2.0, hi=98.0):
    """``image`` scaled to 0..1 between the ``lo`` and ``hi`` percentiles of its good values."""
    values = image[good] if good is not None and good.any() else image.ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        return np.zeros(image.shape, np.float32)
    a, b = np.percentile(values, [lo, hi])
    scale = b - a if b > a else 1.0
    return np.clip((image - a) / scale, 0.0, 1.0)


def _region(cube, pixel, region):
    h, w = cube.data.shape[:2]
    if region is not None:
        r0, r1, c0, c1 = (int(v) for v in region)
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
            raise ValueError(f"region {region} (row0 row1 col0 col1) is not inside the cube of "
                             f"{h} x {w} px")
        return r0, r1, c0, c1
    if pixel is None:
        pixel = (h // 2, w // 2)
    r, c = (int(v) for v in pixel)
    if not (0 <= r < h and 0 <= c < w):
        raise ValueError(f"pixel {pixel} (row col) is not inside the cube of {h} x {w} px")
    return r, r + 1, c, c + 1


def quicklook(cube, path=None, *, rgb_nm=None, bands=None, pixel=None, region=None,
              overwrite: bool | None = None, title: str | None = None, dpi: int = 100):
    """A quicklook figure of a cube, saved as PNG when ``path`` is given.

    Parameters
    ----------
    cube : Cube, Frame or path
        A :class:`~hsiffc.cubes.Cube`, a reconstructed Frame, or a cube file
        (:func:`~hsiffc.cubes.read_cube`).
    path : str or Path, optional
        PNG to write (atomically).
    rgb_nm : three floats, optional
        Wavelengths (nm) shown red, green and blue (the nearest bands); default
        :func:`~hsiffc.cubes.default_bands`.
    bands : sequence of int, optional
        Band numbers of the grid, as hsiffc numbers bands everywhere (from 1 by wavelength,
        :func:`hsiffc.data.mosaic.band_labels`); default up to 12, evenly spread.
    pixel : (row, col), optional
        Pixel whose spectrum is drawn (default: the centre).
    region : (row0, row1, col0, col1), optional
        A region instead of a pixel (rows row0..row1-1, columns col0..col1-1).
    overwrite : bool, optional
        Replace an existing PNG.
    title : str, optional
    dpi : int

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from .product import Cube
    from .readers import read_cube

    if isinstance(cube, (str, Path)):
        title = title or Path(cube).name
        cube = read_cube(cube)
    elif not isinstance(cube, Cube):
        cube = Cube.from_frame(cube)
    cube = cube.sorted()
    n = cube.n_bands
    wl = cube.wavelengths_nm
    names = cube.band_names()  # "band 3 (r0c2 614.9 nm)"
    index = {k: i for i, k in enumerate(band_numbers(n, wl))}  # band number -> cube band
    if rgb_nm is not None:
        if len(rgb_nm) != 3:
            raise ValueError(f"rgb_nm takes three wavelengths (red green blue), got {rgb_nm}")
        rgb = [cube.nearest_band(v) for v in rgb_nm]
    else:
        rgb = cube.default_bands()
    if bands is None:
        bands = np.unique(np.linspace(1, n, min(n, 12)).round().astype(int)).tolist()
    bad = [b for b in bands if int(b) not in index]
    if bad:
        raise ValueError(f"bands {bad} are not in the cube: bands are numbered 1..{n} by "
                         "wavelength (hsiffc info lists them)")
    bands = [index[int(b)] for b in bands]
    r0, r1, c0, c1 = _region(cube, pixel, region)

    fig = Figure(figsize=(14, 10), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    outer = fig.add_gridspec(2, 2)
    good = cube.dq == 0

    h, w = cube.data.shape[:2]
    extent = (-0.5, w - 0.5, h - 0.5, -0.5)  # the image's own pixel coordinates, if strided
    big = (slice(None, None, -(-max(h, w) // DISPLAY_PX)),) * 2
    small = (slice(None, None, -(-max(h, w) // GRID_PX)),) * 2

    ax = fig.add_subplot(outer[0, 0])
    image = np.stack([_stretch(cube.data[big + (b,)], good[big + (b,)]) for b in rgb], axis=-1)
    ax.imshow(image, interpolation="nearest", extent=extent)
    ax.add_patch(_box(r0, r1, c0, c1))
    ax.set_title("pseudo-colour R G B = " + ", ".join(names[b] for b in rgb))
    ax.set_axis_off()

    cols = int(np.ceil(np.sqrt(len(bands))))
    rows = int(np.ceil(len(bands) / cols))
    inner = outer[0, 1].subgridspec(rows, cols)
    for i, b in enumerate(bands):
        a = fig.add_subplot(inner[i // cols, i % cols])
        a.imshow(_stretch(cube.data[small + (b,)], good[small + (b,)]), cmap="gray",
                 interpolation="nearest", extent=extent)
        a.set_title(names[b], fontsize=8)
        a.set_axis_off()

    ax = fig.add_subplot(outer[1, 0])
    flagged = (~good).mean(axis=2)
    im = ax.imshow(flagged[big], cmap="magma", vmin=0, vmax=1, interpolation="nearest",
                   extent=extent)
    fig.colorbar(im, ax=ax, shrink=0.8, label="share of bands with a DQ bit")
    counts = [(int(np.count_nonzero(cube.dq & np.uint32(f))), f.name) for f in DQ if f]
    top = ", ".join(f"{name} {count / cube.dq.size:.2%}" for count, name in
                    sorted(counts, reverse=True)[:4] if count)
    ax.set_title("DQ: " + (top or "no flag set"), fontsize=9)
    ax.set_axis_off()

    ax = fig.add_subplot(outer[1, 1])
    x = np.asarray(wl) if wl is not None else np.arange(n)
    values = cube.data[r0:r1, c0:c1].reshape(-1, n)
    ok = good[r0:r1, c0:c1].reshape(-1, n)
    masked = np.where(ok, values, np.nan)
    with warnings.catch_warnings():  # a band without an unflagged value: NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(masked, axis=0)
        lo, hi = np.nanpercentile(masked, [10, 90], axis=0)
    ax.plot(x, med, "o-", color="C0", label="median of unflagged values")
    if values.shape[0] > 1:
        ax.fill_between(x, lo, hi, color="C0", alpha=0.25, label="10-90 %")
    flagged_bands = ~ok.any(axis=0)
    if flagged_bands.any():
        ax.plot(x[flagged_bands], np.median(values, axis=0)[flagged_bands], "x", color="C3",
                label="flagged in every value")
    where = (f"pixel (row {r0}, col {c0})" if (r1 - r0) * (c1 - c0) == 1
             else f"rows {r0}-{r1 - 1}, cols {c0}-{c1 - 1}")
    ax.set_title(f"spectrum, {where}")
    ax.set_xlabel("wavelength (nm)" if wl is not None else "band")
    ax.set_ylabel(cube.unit)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    if path is not None:
        with atomic_path(Path(path), overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png")
    return fig


def _box(r0, r1, c0, c1):
    from matplotlib.patches import Rectangle

    return Rectangle((c0 - 0.5, r0 - 0.5), max(c1 - c0, 1), max(r1 - r0, 1), fill=False,
                     edgecolor="cyan", linewidth=1.5)
