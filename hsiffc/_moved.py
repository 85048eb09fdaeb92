"""The import paths of modules that moved into the layer folders (hsiffc 0.2), kept working.

``import hsiffc.frame`` (and ``from hsiffc.model_ffc import ...``, pickles and
``unittest.mock.patch`` strings naming the old path) give the module at its new place, the
same module object, with a :class:`DeprecationWarning` naming the new path. The old paths go in
hsiffc 0.4.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: old module path -> new module path
MOVED = {
    'hsiffc.atomic': 'hsiffc.files.atomic',
    'hsiffc.folderlock': 'hsiffc.files.folderlock',
    'hsiffc.jsonsafe': 'hsiffc.files.jsonsafe',
    'hsiffc.io.limits': 'hsiffc.files.limits',
    'hsiffc.io.parsers': 'hsiffc.files.parsers',
    'hsiffc.frame': 'hsiffc.data.frame',
    'hsiffc.dq': 'hsiffc.data.dq',
    'hsiffc.mosaic': 'hsiffc.data.mosaic',
    'hsiffc.sweep': 'hsiffc.data.sweep',
    'hsiffc.params': 'hsiffc.data.params',
    'hsiffc.products': 'hsiffc.data.products',
    'hsiffc.bandstats': 'hsiffc.spectral.bandstats',
    'hsiffc.dark': 'hsiffc.data.dark',
    'hsiffc.model': 'hsiffc.leakage.model',
    'hsiffc.model_derived': 'hsiffc.leakage.model',
    'hsiffc.model_numerics': 'hsiffc.leakage.model',
    'hsiffc.validity': 'hsiffc.leakage.validity',
    'hsiffc.linearise': 'hsiffc.leakage.linearise',
    'hsiffc.ffc': 'hsiffc.flatfield.two_point',
    'hsiffc.polyffc': 'hsiffc.flatfield.polynomial',
    'hsiffc.model_ffc': 'hsiffc.flatfield.model_based',
    'hsiffc.model_flat': 'hsiffc.flatfield.model_based',
    'hsiffc.ffc_floor': 'hsiffc.flatfield.floor',
    'hsiffc.uniformity': 'hsiffc.flatfield.uniformity',
    'hsiffc.memory': 'hsiffc.batch.memory',
    # one concept, one module (hsiffc 0.2): the training of the model-based flat field with
    # the correction it feeds; the leakage model's derived quantities and helpers with it
    'hsiffc.flatfield.model_flat': 'hsiffc.flatfield.model_based',
    'hsiffc.leakage._derived': 'hsiffc.leakage.model',
    'hsiffc.leakage._numerics': 'hsiffc.leakage.model',
    # per-band statistics above the compiled kernels they run on (no data <-> kernels cycle)
    'hsiffc.data.bandstats': 'hsiffc.spectral.bandstats',
    # one module per file format (hsiffc 0.2): the parts of a format merged into it
    'hsiffc.io.corrected_format': 'hsiffc.io.corrected',
    'hsiffc.io.corrected_writer': 'hsiffc.io.corrected',
    'hsiffc.io.envi_write': 'hsiffc.io.envi',
    'hsiffc.io.emva_descriptor': 'hsiffc.io.emva',
    'hsiffc.io.sourcefacts': 'hsiffc.io.source',
    'hsiffc.io.tiffpages': 'hsiffc.io.tiff',
    'hsiffc.io.document': 'hsiffc.io.tiff',
    # diagnose's two base models in one module (hsiffc 0.2)
    'hsiffc.diagnose.linearbase': 'hsiffc.diagnose.bases',
    # simulated sweeps of users' designs, apart from design (what a sweep's design allows)
    'hsiffc.diagnose.designs': 'hsiffc.diagnose.simulated',
    # the io package's plumbing, private behind hsiffc.io (hsiffc 0.2)
    'hsiffc.io.layout': 'hsiffc.io._layout',
    'hsiffc.io.quirks': 'hsiffc.io._quirks',
    'hsiffc.io.readers': 'hsiffc.io._readers',
    'hsiffc.io.metadata': 'hsiffc.io._metadata',
    'hsiffc.io.sidecar': 'hsiffc.io._sidecar',
    'hsiffc.io.fits': 'hsiffc.io._fits',
    'hsiffc.io.images': 'hsiffc.io._images',
    # compiled CPU code in one folder (hsiffc 0.2): the calibration's per-pixel fit
    'hsiffc.calibrate.lm': 'hsiffc.kernels.lm',
    'hsiffc.calibrate.pixelfit': 'hsiffc.kernels.pixelfit',
    'hsiffc.emva1288.compiled': 'hsiffc.kernels.emva',
    'hsiffc.calibrate.pixelsamples': 'hsiffc.kernels.pixelsamples',
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves an old module path to the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} moved to {new}: import it from there (the old path goes "
                      "in hsiffc 0.4)", DeprecationWarning, stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):
        """Nothing to run: the module was imported at its new path."""


def install() -> None:
    """Put the finder first on ``sys.meta_path``, once (it answers only the old paths)."""
    if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedModules())
