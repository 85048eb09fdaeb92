"""Spectral models: band responses, IMEC calibration files, illumination and photo-electron rates.

Modules
-------
bands         BandSet, synthetic Fabry-Perot bands and presets, spectral correction matrices
imec          read_imec_xml: IMEC sensor calibration XML
illumination  Illumination: blackbody, CIE illuminants, named lamps (colour-science)
radiometry    electron_rate, ColorChecker reflectances
"""

from __future__ import annotations

from .grid import DEFAULT_GRID
from .bands import (BandSet, fabry_perot_bands, gaussian_responses, imec_4x4_visible,
                    imec_5x5_nir, paper_8band, spectral_correction_matrix)
from .illumination import (PAPER_LAMPS_K, Illumination, blackbody, cie_illuminant,
                           cie_illuminant_names, lamp, lamp_names)
from .imec import (CMV2000_PIXEL_PITCH_UM, FilterArea, ImecPeak, ImecSensorCalibration,
                   read_imec_xml)
from .radiometry import COLORCHECKER_DATASET, colorchecker_reflectances, electron_rate

__all__ = [
    "DEFAULT_GRID",
    "BandSet", "fabry_perot_bands", "gaussian_responses", "paper_8band", "imec_4x4_visible",
    "imec_5x5_nir", "spectral_correction_matrix",
    "Illumination", "blackbody", "cie_illuminant", "cie_illuminant_names", "lamp", "lamp_names",
    "PAPER_LAMPS_K",
    "read_imec_xml", "ImecSensorCalibration", "ImecPeak", "FilterArea", "CMV2000_PIXEL_PITCH_UM",
    "electron_rate", "colorchecker_reflectances", "COLORCHECKER_DATASET",
]
