"""Flat-field corrections as array functions, and the figures that judge them.

- :mod:`.two_point` - the classic two-point (dark + flat) correction;
- :mod:`.polynomial` - per-pixel polynomial correction over several flats;
- :mod:`.model_based` - the leakage-model-based correction, its uncertainty and its training
  (responsivity per pixel);
- :mod:`.floor` - the fixed-pattern floor a calibration sweep sets;
- :mod:`.uniformity` - fixed-pattern non-uniformity figures;
- :mod:`.methods` - the family's registry :data:`FFC_METHODS`: every method behind one
  signature, :func:`correct_flat`, returning one type, :class:`Corrected`.

The stages in :mod:`hsiffc.stages` wrap these functions.
"""

from .methods import FFC_METHODS, FROM_CALIBRATION, Corrected, FFCMethod, correct_flat

__all__ = ["FFC_METHODS", "FROM_CALIBRATION", "Corrected", "FFCMethod", "correct_flat"]
