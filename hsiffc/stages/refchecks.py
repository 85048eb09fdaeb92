"""Checks of the dark and flat references a pipeline is fitted on, with numbers, as the
reflectance stage checks its white reference (:mod:`hsiffc.reflectance`): a flat too dark for
its noise, a dark above the flat ("were the dark and flat swapped?"), one frame where its
noise cannot be measured, a saturated flat, a dark as bright as a flat.

Each condition is one warning (an :class:`~hsiffc.errors.HsiffcWarning` with its figures),
given at fit; the fit goes on.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..data.dq import DQ
from ..errors import HsiffcWarning, band_figures

__all__ = ["DarkAboveFlatWarning", "DarkTooBrightWarning", "FlatSaturatedWarning",
           "FlatTooDarkWarning", "ReferenceWarning", "SingleReferenceFrameWarning",
           "check_darks", "check_flats"]

#: the flat's median level above dark, as a fraction of the range above dark, under which it
#: is too dark (the reflectance stage's default ``min_reference_level``)
MIN_LEVEL_FRACTION = 0.10
#: percentage of a band's pixels at full scale above which a flat is saturated
MAX_SATURATED_PERCENT = 1.0
#: a dark whose median is above this fraction of the full scale is no dark
MAX_DARK_FRACTION = 0.5


class ReferenceWarning(HsiffcWarning):
    """Base class of the dark and flat reference checks' warnings."""


class FlatTooDarkWarning(ReferenceWarning):
    """The flat's level above dark is low: its noise is printed into every corrected frame."""


class DarkAboveFlatWarning(ReferenceWarning):
    """The dark is above the flat in some band: the two were probably swapped."""


class SingleReferenceFrameWarning(ReferenceWarning):
    """One reference frame: its noise cannot be measured, and is a fixed pattern."""


class FlatSaturatedWarning(ReferenceWarning):
    """Part of the flat is at full scale: those pixels' gains are wrong."""


class DarkTooBrightWarning(ReferenceWarning):
    """The dark frames are as bright as a flat: a light frame given as a dark?"""


def _warn(category, text, figures, stacklevel):
    warnings.warn(category(text, figures=figures), stacklevel=stacklevel + 1)


def check_flats(stage: str, stack, signal, *, stacklevel: int = 3) -> None:
    """The checks of one flat exposure's frames ``stack`` (dark-subtracted Frames) whose
    average above dark is ``signal`` (H, W)."""
    from ..spectral.bandstats import band_reduce  # compiled: imported when a flat is checked

    f0 = stack[0]
    band_map = f0.band_map()
    n_bands = int(band_map.max()) + 1
    t, n = float(f0.exposure_ms), len(stack)
    full = 2.0 ** int(f0.bit_depth) - 1
    level = band_reduce(np.asarray(signal, np.float64), band_map, statistic="median",
                        n_bands=n_bands)
    rng = band_reduce(full - np.asarray(f0.dark_removed, np.float64), band_map,
                      statistic="median", n_bands=n_bands)
    frac = level / np.maximum(rng, 1e-9)
    labels = f0.band_labels()  # numbered by wavelength, with the mosaic position

    def bands(idx, values, fmt):
        return band_figures(idx, values, fmt, labels=labels)

    swapped = [i for i in range(n_bands) if level[i] <= 0]
    if swapped:
        _warn(DarkAboveFlatWarning,
              f"{stage}: the dark is above the flat ({t:g} ms) in {len(swapped)} of {n_bands} "
              f"bands: {bands(swapped, level, '.1f')} DN flat less dark: were the dark and "
              "flat swapped? (--dark takes the dark frames, --flat the flat ones; or check "
              "the kind in their metadata); those bands cannot be flat-fielded",
              {"exposure_ms": t, "bands": [labels[i] for i in swapped],
               "level_dn": [float(level[i]) for i in swapped]}, stacklevel)
    dim = [i for i in range(n_bands) if 0 < frac[i] < MIN_LEVEL_FRACTION]
    if dim:
        dim = sorted(dim, key=lambda i: frac[i])
        _warn(FlatTooDarkWarning,
              f"{stage}: flat ({t:g} ms) too dark in {len(dim)} of {n_bands} bands: "
              f"{bands(dim, level, '.1f')} DN above dark "
              f"({', '.join(f'{100 * frac[i]:.1f} %' for i in dim[:6])} of the range; asked "
              f"for >= {100 * MIN_LEVEL_FRACTION:g} %): its noise is printed into every "
              "corrected frame; lengthen the flat's exposure or light it better",
              {"exposure_ms": t, "bands": [labels[i] for i in dim],
               "level_dn": [float(level[i]) for i in dim],
               "level_fraction": [float(frac[i]) for i in dim]}, stacklevel)
    sat = np.mean([band_reduce(((f.dq & DQ.SATURATED) != 0).astype(np.float64), band_map,
                               n_bands=n_bands) for f in stack], axis=0) * 100
    hit = [i for i in range(n_bands) if sat[i] > MAX_SATURATED_PERCENT]
    if hit:
        _warn(FlatSaturatedWarning,
              f"{stage}: flat ({t:g} ms) saturated: {bands(hit, sat, '.2g')} % of the "
              f"pixels at full scale (allowed {MAX_SATURATED_PERCENT:g} %); their gains are wrong and "
              "flagged: shorten the flat's exposure or dim the light",
              {"exposure_ms": t, "bands": [labels[i] for i in hit],
               "saturated_percent": [float(sat[i]) for i in hit]}, stacklevel)
    if n < 2:
        _warn(SingleReferenceFrameWarning,
              f"{stage}: one flat frame ({t:g} ms): its noise cannot be measured and is "
              "printed into every corrected frame as a fixed pattern; record 10 or more "
              "frames of the flat", {"exposure_ms": t, "n_frames": n}, stacklevel)


def check_darks(stage: str, groups, masters, *, stacklevel: int = 3) -> None:
    """The checks of the dark frames ``groups`` (``{exposure: [Frame]}``) and their masters
    (one (H, W) per exposure, in the same order)."""
    for (t, stack), master in zip(groups.items(), masters):
        f0 = stack[0]
        full = 2.0 ** int(f0.bit_depth) - 1
        med = float(np.median(master))
        if med > MAX_DARK_FRACTION * full:
            _warn(DarkTooBrightWarning,
                  f"{stage}: the dark frames at {t:g} ms have a median of {med:.0f} DN "
                  f"({100 * med / full:.0f} % of the range): a light frame given as a dark? "
                  "(--dark takes frames with the lens capped; or check the kind in their "
                  "metadata)", {"exposure_ms": float(t), "median_dn": med}, stacklevel)
        if len(stack) < 2:
            _warn(SingleReferenceFrameWarning,
                  f"{stage}: one dark frame at {t:g} ms: its noise cannot be measured and is "
                  "subtracted from every frame as a fixed pattern; record 10 or more dark "
                  "frames", {"exposure_ms": float(t), "n_frames": len(stack)}, stacklevel)
