"""Cube reconstruction stage: raw mosaic frame -> spectral cube (optionally corrected)."""

from __future__ import annotations

import numpy as np

from .. import reconstruct as rc
from ..data.dq import DQ_DTYPE
from ..data.mosaic import band_positions
from ..errors import ParameterError
from ..data.params import Param
from .base import Stage

RESOLUTIONS = ("full", "tile")
CORRECTIONS = (None, "imec", "derived")


class Reconstruct(Stage):
    """Turn a 2-D mosaic frame into a cube ``(H, W, B)`` (or ``(H', W', B)`` per tile), and
    optionally apply a spectral correction matrix to get virtual bands ``(..., V)``.

    Parameters
    ----------
    method : str
        Demosaicing method for ``resolution="full"``, one of
        :data:`hsiffc.reconstruct.DEMOSAIC_METHODS` ("nearest", "bilinear", "ppid",
        "ppid_paper", "ppid_edge", "itsd"; see :func:`hsiffc.reconstruct.demosaic`); ignored for
        ``resolution="tile"``.
    resolution : "full" or "tile"
        "full": every band at every pixel (:func:`hsiffc.reconstruct.demosaic`); "tile": one
        spectrum per complete tile (:func:`hsiffc.reconstruct.tile_cube`).
    correction : None, "imec" or "derived"
        None: the cube keeps the physical bands (band-index order = pattern-position order for
        IMEC sensors). "imec": the vendor correction matrix of ``imec_xml``. "derived": a matrix
        computed by :func:`hsiffc.spectral.spectral_correction_matrix` from the band responses
        of ``imec_xml``, for Gaussian virtual bands of FWHM ``virtual_fwhm_nm`` at the file's
        virtual wavelengths (or at the sorted band centres when the file lists none).
    imec_xml : path, optional
        IMEC sensor calibration XML; required when ``correction`` is set.
    virtual_fwhm_nm : float
        FWHM of the derived virtual bands.

    Fitted attributes (``correction`` set): ``matrix_`` (V, B) float64 ndarray and
    ``virtual_wavelengths_nm_`` (list of float); saved without pickle. With ``correction=None``
    the stage is stateless (``fit`` only marks it fitted).

    Output frame: ``meta["fwhm_nm"]`` (the mosaic's band FWHMs, or the virtual bands' width;
    None when unknown), ``meta["band_positions"]`` ((row, col) of each physical band in the
    tile; None for virtual bands), data and DQ of the cube (DQ rule in
    :mod:`hsiffc.reconstruct`; a virtual
    band ORs the DQ of every band with a non-zero coefficient), ``meta["wavelengths_nm"]``
    (band centres from the mosaic, in band order, or the virtual wavelengths; None when the
    mosaic has none), ``meta["reconstruction"]`` = {method, resolution, correction} and, for
    "tile", ``meta["tile_origin"]`` (raw row, col of the first tile). If the input has an
    ``alpha`` plane, the output alpha is a cube of the same shape as the data holding, per
    value, the max alpha of the raw pixels it was made from
    (:func:`hsiffc.reconstruct.reconstruct_alpha`; for virtual bands the max over the bands
    with non-zero coefficient), so thresholding it stays conservative. PPID's is one plane for
    every band, held as a read-only view that repeats it along the band axis.
    """

    #: the registered name, also when the class is instantiated directly (pipeline files
    #: resolve stages by this name)
    name = "reconstruct"
    gpu_as = "reconstruct"
    #: fitted state as a pipeline file stores it (:func:`hsiffc.data.products.check_product`)
    state_schema = {"fitted_": "bool", "virtual_wavelengths_nm_": "numbers",
                    "virtual_fwhm_nm_": "number|null",
                    "matrix_": ("f", ("virtual_wavelengths_nm_", "B"))}
    requires = frozenset({"mosaic"})
    produces = frozenset({"cube"})
    removes = frozenset({"mosaic"})
    param_spec = {"method": Param("choice", choices=tuple(sorted(rc.DEMOSAIC_METHODS))),
                  "resolution": Param("choice", choices=RESOLUTIONS),
                  "correction": Param("choice", choices=CORRECTIONS),
                  "imec_xml": Param("path", optional=True),
                  "virtual_fwhm_nm": Param("number", low=0, low_open=True, unit="nm")}

    def __init__(self, *, method: str = "ppid", resolution: str = "full", correction=None,
                 imec_xml=None, virtual_fwhm_nm: float = 15.0):
        self.method = method
        self.resolution = resolution
        self.correction = correction
        self.imec_xml = imec_xml
        self.virtual_fwhm_nm = virtual_fwhm_nm

    @property
    def stateless(self) -> bool:  # type: ignore[override]
        """Nothing to learn unless a correction matrix has to be loaded."""
        return self.correction is None

    # -- validation ----------------------------------------------------------------------------
    def _validate(self) -> None:
        self.validate_params()
        if self.correction is not None and self.imec_xml is None:
            raise ParameterError(f"correction={self.correction!r} needs imec_xml= (the IMEC "
                                 "sensor calibration XML giving the matrix or the band responses)")

    # -- fit / transform -----------------------------------------------------------------------
    def fit(self, frames) -> Reconstruct:
        """Prepare the spectral correction matrix (if any); returns ``self``."""
        self._validate()
        if self.correction is not None:
            from ..spectral import read_imec_xml, spectral_correction_matrix

            cal = read_imec_xml(self.imec_xml)
            if self.correction == "imec":
                matrix = np.array(cal.correction_matrix, dtype=np.float64)
                wl = [float(v) for v in cal.virtual_wavelengths_nm]
            else:
                wl = [float(v) for v in cal.virtual_wavelengths_nm]
                if not wl:
                    wl = sorted(float(c) for c in cal.bands.centres_nm)
                matrix = np.asarray(spectral_correction_matrix(
                    cal.bands, wl, float(self.virtual_fwhm_nm)), dtype=np.float64)
            if matrix.ndim != 2 or matrix.shape[0] != len(wl) or not np.all(np.isfinite(matrix)):
                raise ValueError(f"{self.imec_xml}: correction matrix of shape {matrix.shape} "
                                 f"does not match its {len(wl)} virtual wavelengths or is "
                                 "not finite")
            for f in frames or ():
                mosaic = getattr(f, "mosaic", None)
                if mosaic is not None and mosaic.n_bands != matrix.shape[1]:
                    raise ValueError(f"{self.imec_xml}: the correction matrix has "
                                     f"{matrix.shape[1]} band columns but the training frames' "
                                     f"mosaic has {mosaic.n_bands} bands")
            self.matrix_ = matrix
            self.virtual_wavelengths_nm_ = wl
            width = (cal.virtual_fwhm_nm if self.correction == "imec"
                     else float(self.virtual_fwhm_nm))
            self.virtual_fwhm_nm_ = None if width is None else float(width)
        self.fitted_ = True
        return self

    def transform(self, frame):
        """The mosaic frame ``(H, W)`` as a cube ``(H', W', bands)`` with wavelengths in ``meta``."""
        if not self.stateless:
            self.check_is_fitted()
        self._validate()
        if frame.data.ndim != 2:
            raise ValueError(f"reconstruct needs a raw 2-D mosaic frame, got data of shape "
                             f"{frame.data.shape} (already a cube?)")
        mosaic = frame.mosaic
        if mosaic is None:
            raise ValueError("reconstruct needs the frame's mosaic layout (meta['mosaic']); "
                             "this frame has none")
        alpha = None
        if self.resolution == "full":  # the cube's alpha comes from the same kernel pass
            cube, cube_dq, alpha = rc.demosaic(frame.data, mosaic, method=self.method,
                                               dq=frame.dq, alpha=frame.alpha)
        else:
            cube, cube_dq = rc.tile_cube(frame.data, mosaic, dq=frame.dq)
            if frame.alpha is not None:
                alpha = rc.reconstruct_alpha(frame.alpha, mosaic, resolution="tile")
        wavelengths = None if mosaic.wavelengths_nm is None else list(mosaic.wavelengths_nm)
        fwhm = None if mosaic.fwhm_nm is None else list(mosaic.fwhm_nm)
        positions = band_positions(mosaic)
        if self.correction is not None:
            matrix = np.asarray(self.matrix_, dtype=np.float64)
            if matrix.shape[1] != mosaic.n_bands:
                raise ValueError(f"the correction matrix has {matrix.shape[1]} band columns but "
                                 f"the frame's mosaic has {mosaic.n_bands} bands")
            cube, cube_dq = rc.apply_correction(cube, matrix, dq=cube_dq)
            if alpha is not None:
                alpha = rc.reduce_over_support(alpha, rc.correction_support(matrix), np.maximum,
                                                np.float32)
            wavelengths = [float(v) for v in self.virtual_wavelengths_nm_]
            width = getattr(self, "virtual_fwhm_nm_", None)
            fwhm = None if width is None else [float(width)] * len(wavelengths)
            positions = None
        meta = {"wavelengths_nm": wavelengths, "fwhm_nm": fwhm, "band_positions": positions,
                "reconstruction": {"method": self.method if self.resolution == "full" else None,
                                   "resolution": self.resolution,
                                   "correction": self.correction}}
        if self.resolution == "tile":
            meta["tile_origin"] = list(rc.tile_origin(frame.data.shape, mosaic))
        return frame.replace(data=cube, dq=cube_dq.astype(DQ_DTYPE, copy=False), alpha=alpha,
                             meta=meta)
