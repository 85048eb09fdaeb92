"""A simulator of a CMOS snapshot-mosaic spectral sensor whose pixels follow the leakage model.

Light (a colour-science lamp spectrum, optionally with vignetting and target reflectances) is
turned into photo-electrons per band, into a per-pixel light rate ``k`` (DN/ms) through the
band responses, the pixel's PRNU and the conversion gain, and then into a raw response by the
closed form of ``dY/dt = k - a e^{bY}`` starting from the pixel's dark level. Temporal noise
(shot noise on the collected electrons, read noise), full-well clipping, quantisation and clipping
at full scale follow. The fixed pattern (dark level with DSNU, PRNU, leakage a and b with spread,
dark current, hot and dead pixels) is drawn once from the sensor's seed and returned as ground
truth with every capture.

Defaults reproduce the paper's sensor (Liu et al.; see ``shared/reference/README.md``): 10 bit,
k about 2 DN/ms under lamp B at the Fig. 5 light level with a dynamic saturation near 800 DN and a
leakage of 2 DN/ms at 800 DN, and under the training lamp A an alpha that grows over
6.45-32.25 ms roughly as in Table I.
"""

from .params import (DEFAULT_BAND_BALANCE, PAPER_LIGHT_W_M2, Capture, SensorParams, Truth,
                     default_bands)
from .sensor import MosaicSensor

__all__ = ["SensorParams", "Truth", "Capture", "MosaicSensor", "PAPER_LIGHT_W_M2",
           "DEFAULT_BAND_BALANCE", "default_bands"]
