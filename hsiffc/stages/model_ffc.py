"""Model-based flat-field correction stage: wraps :mod:`hsiffc.flatfield.model_based`."""

from __future__ import annotations

import numpy as np

from ..calibrate.flats import combined_dark
from ..data.dq import DQ, DQ_DTYPE
from ..kernels.bits import or_into, or_into_flag_uncertain
from ..flatfield.methods import FFC_METHODS
from ..flatfield.model_based import FlatStack, log_gain_ratio, model_ffc_apply, model_flat_of
from ..data.params import Param
from .common import CALIBRATION, THRESHOLD
from .base import PreparedWithCalibration, Stage


def flat_stacks(frames, min_frames: int):
    """Light frames grouped by (exposure, illumination, step); the groups with at least
    ``min_frames`` frames are flat stacks."""
    groups: dict[tuple, list] = {}
    for f in frames:
        if f.kind == "light" and not f.is_cube:
            key = (f.exposure_ms, str(f.meta.get("illumination", "")), f.meta.get("step"))
            groups.setdefault(key, []).append(f)
    return [g for g in groups.values() if len(g) >= min_frames]


#: default limit of the predicted fixed-pattern error (percent of the corrected signal) above
#: which model FFC flags a pixel UNCERTAIN
UNCERTAIN_ABOVE_PERCENT = 5.0


class ModelFFC(Stage):
    """Flat-field correction from the calibration's per-pixel model (beyond the paper).

    Each response is inverted with the pixel's leakage model (light rate k from the dark level:
    the dark a preceding ``dark`` stage removed, else the calibration's dark at the frame's
    exposure), divided by the pixel's responsivity relative to its band's mean, and returned as
    ``k t`` in DN above dark on the band-mean scale: a uniform scene gives a uniform frame and a
    spectrum keeps its shape up to strong leakage. The responsivity map comes from the
    calibration's sweep fit and, combined by inverse variance, from every flat stack among the
    training frames (``min_flat_frames`` or more frames of one step), else from the flat stacks
    the calibration carries (``hsiffc calibrate`` folds a sweep's flat stacks into it:
    :func:`hsiffc.calibrate.flats.add_flat_stacks`); :attr:`sigma_ln_gain_` is
    each pixel's 1-sigma relative uncertainty of its factor and :attr:`uncertainty_` says per
    band how much comes from the sweep, the flats and the model's inconsistency with them.

    Flags (value kept, never deleted): SATURATED (clipped), LEAKAGE (model alpha over
    ``alpha_limit_percent``), BELOW_DARK, UNREACHABLE, NOT_CONVERGED, NO_FLAT (no usable
    responsivity: factor 1), UNCERTAIN (the correction's predicted fixed-pattern error at this
    pixel's corrected signal above ``uncertain_above_percent``).

    The predicted error is the calibration's own, carried to each output pixel: the relative
    1-sigma error of its factor (:attr:`sigma_ln_gain_`) and its dark level's error
    (the calibration's ``sigma_dark_dn``) over the corrected signal, in quadrature,
    ``sqrt(sigma_ln_gain^2 + (sigma_dark gain / signal)^2)``. Leakage's bend is left out: it
    makes the dark's share larger by ``1 / (1 - alpha)`` at most, and a pixel where that
    matters is flagged LEAKAGE (see :func:`hsiffc.flatfield.model_based.correction_uncertainty`
    for the exact propagation).

    Parameters
    ----------
    calibration : path or Calibration
    alpha_limit_percent : float
        Responses whose model alpha exceeds this are flagged LEAKAGE.
    flat_alpha_percent : float
        Model alpha at which the flat stacks' share of the factor has gone to zero (see
        :func:`hsiffc.flatfield.model_based.model_ffc_apply`).
    min_flat_frames : int
        Light frames of one step needed to count as a flat stack.
    uncertain_above_percent : float or None
        Pixels whose predicted fixed-pattern error exceeds this percentage of their corrected
        signal are flagged UNCERTAIN (None: never).
    """

    name = "model_ffc"
    gpu_as = "model_ffc"
    requires = frozenset({"mosaic", "response"})
    produces = frozenset({"dark_subtracted"})
    removes = frozenset({"raw", "response"})
    param_spec = {"calibration": CALIBRATION, "alpha_limit_percent": THRESHOLD,
                  "flat_alpha_percent": THRESHOLD,
                  "min_flat_frames": Param("integer", low=2),
                  "uncertain_above_percent": Param("number", low=0, low_open=True,
                                                   unit="percent", optional=True)}
    state_schema = FFC_METHODS["model"].state_schema

    def __init__(self, *, calibration=None, alpha_limit_percent: float = 50.0,
                 flat_alpha_percent: float = 5.0, min_flat_frames: int = 8,
                 uncertain_above_percent: float | None = UNCERTAIN_ABOVE_PERCENT):
        self.calibration = calibration
        self.uncertain_above_percent = uncertain_above_percent
        self.alpha_limit_percent = alpha_limit_percent
        self.flat_alpha_percent = flat_alpha_percent
        self.min_flat_frames = min_flat_frames

    def _cal_for(self, frame):
        cal = self.require_calibration()
        cal.check_frame(frame)
        return cal

    def fit(self, frames):
        self.validate_params()
        cal = self.require_calibration()
        frames = [f for f in frames if not f.is_cube]
        band_map = frames[0].band_map() if frames else None
        stacks = []
        for group in flat_stacks(frames, int(self.min_flat_frames)):
            cal = self._cal_for(group[0])
            usable = np.all([f.dq == 0 for f in group], axis=0)
            t = group[0].exposure_ms
            if group[0].dark_removed is not None:
                dark = group[0].dark_removed
            else:  # the dark frames of the stack's exposure, combined with the calibration's
                darks = [f.raw for f in frames if f.kind == "dark"
                         and np.isclose(f.exposure_ms, t, rtol=1e-6, atol=0.0)]
                dark = combined_dark(cal, t, darks if len(darks) >= 2 else None)
            stacks.append(FlatStack.from_arrays([f.raw for f in group], t, dark, usable=usable))
        # no flat stack among the training frames: the ones the calibration carries, if any
        # (hsiffc.calibrate.flats.add_flat_stacks), combined when it was made
        mf = model_flat_of(cal, band_map=band_map, flats=stacks, who=self.name)
        self.gain_, self.gain_sweep_ = mf.gain, mf.gain_sweep
        self.sigma_ln_gain_, self.flat_weight_, self.dq_ = mf.sigma_ln_gain, mf.flat_weight, mf.dq
        self.uncertainty_ = mf.summary
        self.fitted_ = True
        return self

    def prepare(self) -> "PreparedModelFFC":
        """The calibration prepared and :func:`~hsiffc.flatfield.model_based.log_gain_ratio`
        of the fitted factors, made now (:class:`PreparedModelFFC`)."""
        self.check_is_fitted()
        log_ratio = (None if self.gain_sweep_ is None else
                     log_gain_ratio(self.gain_, self.gain_sweep_))
        cal = self.require_calibration()
        return PreparedModelFFC(self, cal.prepare(), log_ratio, self._uncertain_terms(cal))

    def _uncertain_terms(self, cal):
        """``(c, e)`` of the UNCERTAIN test ``c > e signal^2`` (float32 planes), or None:
        ``c = (sigma_dark gain)^2``, ``e = limit^2 - sigma_ln_gain^2``."""
        if self.uncertain_above_percent is None:
            return None
        gain = np.asarray(self.gain_, np.float64)
        sigma_dark = np.asarray(cal.arrays.get("sigma_dark_dn", 0.0), np.float64)
        sigma_gain = np.nan_to_num(np.asarray(self.sigma_ln_gain_, np.float64), nan=np.inf)
        with np.errstate(invalid="ignore", over="ignore"):
            c = np.broadcast_to((sigma_dark * gain) ** 2, gain.shape).astype(np.float32)
            e = ((float(self.uncertain_above_percent) / 100.0) ** 2
                 - sigma_gain ** 2).astype(np.float32)
        return c, e

    def transform(self, frame):
        return self.prepare().transform(frame)


class PreparedModelFFC(PreparedWithCalibration):
    """A fitted :class:`ModelFFC` made ready for frames.

    Attributes
    ----------
    stage : ModelFFC
    calibration : PreparedCalibration
        Its dark line gives the dark where no dark stage removed one.
    log_ratio : (H, W) ndarray or None
        ``ln(gain_ / gain_sweep_)`` (None without a sweep factor).
    uncertain : (c, e) of float32 (H, W) planes, or None
        The UNCERTAIN test ``c > e signal^2`` (None: not flagged).
    """

    __slots__ = ("log_ratio", "uncertain")

    def __init__(self, stage, calibration, log_ratio, uncertain=None):
        super().__init__(stage, calibration)
        self.log_ratio = log_ratio
        self.uncertain = uncertain

    def transform(self, frame):
        """:meth:`ModelFFC.transform`."""
        st = self.stage
        cal = self.calibration.calibration  # as fitted (float64 a, b), not the float32 planes
        cal.check_frame(frame)
        dark = (frame.dark_removed if frame.dark_removed is not None else
                self.calibration.dark_at(frame.exposure_ms))
        out, dq, _ = model_ffc_apply(
            frame.raw, frame.exposure_ms, cal.a, cal.b, dark, st.gain_,
            gain_sweep=st.gain_sweep_, flat_alpha_percent=float(st.flat_alpha_percent),
            full_scale_dn=2 ** frame.bit_depth - 1,
            alpha_limit_percent=float(st.alpha_limit_percent), log_ratio=self.log_ratio)
        # dq is this call's own array: merged in place, in parallel (hsiffc.kernels.bits)
        if self.uncertain is None:
            or_into(dq, frame.dq, st.dq_.astype(DQ_DTYPE, copy=False))
        else:
            or_into_flag_uncertain(dq, frame.dq, st.dq_.astype(DQ_DTYPE, copy=False), out,
                                   *self.uncertain, int(DQ.UNCERTAIN))
        return frame.replace(data=out, dq=dq,
                             dark_removed=np.asarray(dark, np.float32), corrected_by=st.name,
                             meta={"ffc": "model"})
