"""The EMVA 1288 reference implementation (``emva1288`` from PyPI) run as its documentation
shows, for the benchmark to time as a whole process: ``python3 emva_reference_run.py DESC``.

Descriptor -> ``ParseEmvaDescriptorFile`` -> ``LoadImageData`` -> ``Data1288`` ->
``Results1288``, every figure of its results dictionary computed (histograms included), K and
PRNU1288 printed. The reference (1.0.2) predates numpy 2 and calls ``np.asfarray``, which
numpy 2 removed: this script gives it back (``np.asarray`` with a float dtype) before importing
it; nothing else is changed.
"""

from __future__ import annotations

import logging
import sys

import numpy as np

if not hasattr(np, "asfarray"):
    np.asfarray = lambda a, dtype=np.float64: np.asarray(a, dtype=dtype)

from emva1288.process import Data1288, LoadImageData, ParseEmvaDescriptorFile, Results1288  # noqa: E402,E501
from emva1288.process.routines import obj_to_dict  # noqa: E402


def main(descriptor: str) -> None:
    parser = ParseEmvaDescriptorFile(descriptor, loglevel=logging.ERROR)
    data = Data1288(LoadImageData(parser.images, loglevel=logging.ERROR).data,
                    loglevel=logging.ERROR)
    res = Results1288(data.data, loglevel=logging.ERROR)
    obj_to_dict(res)  # every figure of its report
    print(f"K {res.K:.10g} DN/e-, PRNU1288 {res.PRNU1288:.10g} %")


if __name__ == "__main__":
    main(sys.argv[1])
