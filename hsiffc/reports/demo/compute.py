"""The demo's numbers: dynamic saturation of the sample sweep, and the shipped correction
pipeline run on the sample test frames (no printing, no files)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from ...leakage import model
from ...calibrate import calibrate
from ...errors import DataFormatError
from ...flatfield.two_point import uniformity_per_band
from ...data.frame import Frame
from ...data.mosaic import mosaic_band_labels, wavelength_order
from ...io import read_sweep
from ...stages import Pipeline, create
from ...flatfield.uniformity import fixed_pattern_nonuniformity

__all__ = ["SAMPLE_NAMES", "SWEEP_NAME", "THRESHOLD_PERCENT", "DemoResult", "check_samples",
           "compute_demo", "demo_pipeline", "fit_curve"]

log = logging.getLogger(__name__)

SWEEP_NAME = "sweep_2900K.tif"
TRAINING_NAME = "training_2900K.tif"
DARKS_NAME = "darks.tif"
TEST_NAME = "test_2200K.tif"
#: the files the demo reads from the sample folder
SAMPLE_NAMES = (SWEEP_NAME, TRAINING_NAME, DARKS_NAME, TEST_NAME)
THRESHOLD_PERCENT = 12.0


@dataclass
class DemoResult:
    """Everything the demo measured.

    Attributes
    ----------
    sweep : Sweep
        The 2900 K exposure sweep that was read.
    exposure_ms : (steps,) ndarray
        Exposures of the sweep's light steps (ms).
    band_mean_dn : (steps, bands) ndarray
        Mean raw response per band and light step (DN).
    alpha_percent : (steps, bands) ndarray
        Leakage percentage alpha (eq. 4) of every step and band (%).
    fits : list of dict
        Per band, the leakage model fitted to the band mean (:func:`fit_curve`).
    full_scale_dn : int
    wavelengths_nm : tuple of float
    correction : dict
        The correction pipeline on the test frames (training exposures, uniformity before and
        after, flagged fraction, cube shape), filled by :func:`compute_demo`.
    calibration, pipeline : objects
        The calibration of the sweep and the fitted Pipeline (saved by ``run_demo``).
    """

    sweep: object
    exposure_ms: np.ndarray
    band_mean_dn: np.ndarray
    alpha_percent: np.ndarray
    fits: list
    full_scale_dn: int
    wavelengths_nm: tuple
    correction: dict = field(default_factory=dict)
    calibration: object = None
    pipeline: object = None

    @property
    def band_labels(self) -> list:
        """Each band's label by band index (numbered by wavelength, with its mosaic position:
        :func:`hsiffc.data.mosaic.band_labels`)."""
        return mosaic_band_labels(self.sweep.mosaic, self.band_mean_dn.shape[1])

    @property
    def band_order(self) -> list:
        """Band indices by wavelength: the order of every table."""
        return wavelength_order(self.band_mean_dn.shape[1], self.sweep.mosaic.wavelengths_nm
                                if self.sweep.mosaic is not None else None)

    @property
    def bands_below_full_scale(self) -> list:
        """Band numbers (from 1 by wavelength) whose brightest mean stays > 5 DN below full
        scale."""
        top = self.band_mean_dn.max(axis=0)
        return [k + 1 for k, i in enumerate(self.band_order)
                if top[i] < self.full_scale_dn - 5]

    def summary(self) -> dict:
        """JSON-ready digest (``demo_summary.json``)."""
        alpha = np.where(np.isfinite(self.alpha_percent), self.alpha_percent, np.nan)
        return {"sweep": str(self.sweep.source), "full_scale_dn": self.full_scale_dn,
                "exposure_ms": self.exposure_ms.tolist(),
                "band_mean_dn": self.band_mean_dn.tolist(),
                "alpha_percent": [[None if np.isnan(v) else float(v) for v in row]
                                  for row in alpha],
                "bands": [{"band": k + 1, "label": self.band_labels[i],
                           "wavelength_nm": self.wavelengths_nm[i], **self.fits[i],
                           "plateau_dn": float(self.band_mean_dn[:, i].max())}
                          for k, i in enumerate(self.band_order)],
                "correction": self.correction}


def fit_curve(t_ms, y_dn, dark_dn) -> dict:
    """Fit the leakage model (k, a, b) to one mean response curve with a known dark level.

    Parameters
    ----------
    t_ms : (n,) array_like
        Exposure times (ms).
    y_dn : (n,) array_like
        Mean raw response at each exposure (DN).
    dark_dn : float
        Dark level (DN), held fixed.

    Returns
    -------
    dict
        ``k`` (DN/ms), ``a`` (DN/ms), ``b`` (1/DN), ``dark`` (DN), ``saturation_dn`` (the
        dynamic saturation level, DN), ``rms_dn``, and the linear fit on the samples below half
        the plateau (``k_linear`` DN/ms, ``rms_linear_dn``).

    Examples
    --------
    >>> t = np.linspace(1, 200, 25)
    >>> y = model.response(t, 5.0, 0.01, 0.012, 30.0)
    >>> f = fit_curve(t, y, 30.0)
    >>> round(f["k"], 3), round(f["saturation_dn"]) == round(float(
    ...     model.dynamic_saturation_level(5.0, 0.01, 0.012)))
    (5.0, True)
    """
    t = np.asarray(t_ms, float)
    y = np.asarray(y_dn, float)
    plateau = float(y.max())
    low = (y - dark_dn) < 0.5 * (plateau - dark_dn)
    if low.sum() < 2:
        low = np.argsort(t)[:2]
    k0 = max(float(np.polyfit(t[low], y[low] - dark_dn, 1)[0]), 1e-6)
    b0 = 4.0 / max(plateau - dark_dn, 1.0)
    loga0 = np.log(k0) - b0 * plateau

    def resid(p):
        return model.response(t, np.exp(p[0]), np.exp(p[1]), np.exp(p[2]), dark_dn) - y

    sol = least_squares(resid, [np.log(k0), loga0, np.log(b0)], method="lm", x_scale="jac")
    k, a, b = np.exp(sol.x)
    lin = np.polyfit(t[low], y[low], 1)
    return {"k": float(k), "a": float(a), "b": float(b), "dark": float(dark_dn),
            "saturation_dn": float(model.dynamic_saturation_level(k, a, b)),
            "rms_dn": float(np.sqrt(np.mean(sol.fun ** 2))),
            "k_linear": float(lin[0]),
            "rms_linear_dn": float(np.sqrt(np.mean((np.polyval(lin, t) - y) ** 2)))}


def demo_pipeline(calibration, threshold_percent: float = THRESHOLD_PERCENT) -> Pipeline:
    """The demo's two-point pipeline (the paper's): dark, alpha mask, two-point FFC trained at
    the exposure alpha selects, PPID reconstruction."""
    return Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=calibration,
                                     threshold_percent=threshold_percent)),
                     ("ffc", create("two_point_ffc", calibration=calibration,
                                    threshold_percent=threshold_percent)),
                     ("cube", create("reconstruct", method="ppid"))])


def check_samples(samples) -> Path:
    """Check that the sample folder holds the four files the demo reads (before any work and
    before the output folder is looked at).

    Parameters
    ----------
    samples : path-like
        The sample folder.

    Returns
    -------
    Path

    Raises
    ------
    DataFormatError
        A file is missing (the message names them, where to run from and how to regenerate).
    """
    samples = Path(samples)
    missing = [name for name in SAMPLE_NAMES if not (samples / name).is_file()]
    if missing:
        raise DataFormatError(
            f"sample {'file' if len(missing) == 1 else 'files'} {', '.join(missing)} not found; "
            "run from the repository root or pass the sample folder (hsiffc demo "
            "path/to/sample_cubes); regenerate them with 'python sample_cubes/make_samples.py'",
            path=samples)
    return samples


def compute_demo(samples) -> DemoResult:
    """Run the demo on the sample folder: dynamic saturation, then the correction pipeline.

    Parameters
    ----------
    samples : path-like
        Folder with ``sweep_2900K.tif``, ``training_2900K.tif``, ``darks.tif`` and
        ``test_2200K.tif`` (the repository's ``sample_cubes``).

    Returns
    -------
    DemoResult
    """
    samples = check_samples(samples)
    path = samples / SWEEP_NAME
    sweep = read_sweep(path)
    if sweep.mosaic is None:
        raise DataFormatError("the sweep has no mosaic layout in its metadata", path=path)
    log.info("fitting the leakage model to the band means of %s", path)
    means = sweep.step_means()
    light = means["kind"] == "light"
    dark = means["kind"] == "dark"
    band_map = sweep.mosaic.band_map(sweep.frame_shape)
    n_bands = sweep.mosaic.n_bands
    t = means["exposure_ms"][light]
    y = np.stack([[f[band_map == bnd].mean() for bnd in range(n_bands)]
                  for f in means["data"][light]])  # (steps, bands)
    d = np.array([np.mean([f[band_map == bnd].mean() for f in means["data"][dark]])
                  for bnd in range(n_bands)]) if dark.any() else np.zeros(n_bands)
    fits = [fit_curve(t, y[:, i], d[i]) for i in range(n_bands)]
    alpha = np.stack([model.leakage_percentage_paper(y[:, i], t, f["a"], f["b"], f["dark"])
                      for i, f in enumerate(fits)], axis=1)
    wl = sweep.mosaic.wavelengths_nm or tuple(float("nan") for _ in range(n_bands))
    result = DemoResult(sweep, t, y, alpha, fits, sweep.full_scale_dn, tuple(wl))
    _run_correction(result, samples)
    return result


def _run_correction(result: DemoResult, samples: Path) -> None:
    """Calibrate, fit the two-point pipeline on the training flats and darks, build the
    model-based pipeline ``hsiffc correct`` applies by default (from the calibration alone),
    correct the test frames, and measure uniformity before and after: eq. (6) on one frame and
    the fixed-pattern non-uniformity of each test step (EMVA 1288: temporal noise taken out)."""
    from ...batch import default_pipeline

    log.info("calibrating the sample sweep and fitting the correction pipeline")
    cal = calibrate(result.sweep)
    train = (Frame.list_from_sweep(read_sweep(samples / TRAINING_NAME))
             + Frame.list_from_sweep(read_sweep(samples / DARKS_NAME)))
    tests = Frame.list_from_sweep(read_sweep(samples / TEST_NAME))
    pipe = demo_pipeline(cal).fit(train)
    ffc = pipe.named_steps["ffc"]
    flat_field = Pipeline(pipe.steps[:3])  # before reconstruction: the mosaic, pixel by pixel
    model = default_pipeline(cal, threshold_percent=THRESHOLD_PERCENT)
    test = tests[0]
    band_map = test.band_map()
    flat_only = flat_field.transform(test)
    by_model = model.transform(test)
    # like for like: the raw frame less the dark the two-point pipeline removed (a dark
    # pedestal in eq. 6's mean would make the raw frame look more uniform than its signal),
    # and every column over the same pixels (no DQ bit in the raw frame or either correction)
    same = test.dq | flat_only.dq | by_model.dq
    before = uniformity_per_band(test.data - flat_only.dark_removed, band_map, dq=same)
    after = uniformity_per_band(flat_only.data, band_map, dq=same)
    steps = []
    for step in sorted({f.meta.get("step") for f in tests}):
        frames = [f for f in tests if f.meta.get("step") == step]
        if len(frames) >= 2:
            steps.append(_fixed_pattern_step(int(step), frames, flat_field, model))
    cube = pipe.transform(test)
    result.calibration, result.pipeline = cal, pipe
    result.correction = {
        "training_ms": list(ffc.selected_ms_), "alpha_table": ffc.alpha_table_,
        "test_exposure_ms": test.exposure_ms, "test_illumination": test.meta.get("illumination"),
        "uniformity_raw_less_dark": before.tolist(), "uniformity_corrected": after.tolist(),
        "uniformity_model_ffc": uniformity_per_band(by_model.data, band_map, dq=same).tolist(),
        "uniformity_pixels": int(np.count_nonzero(same == 0)),
        "fixed_pattern": steps,
        "flagged_fraction": float((flat_only.dq != 0).mean()),
        "cube_shape": list(cube.data.shape),
        "cube_wavelengths_nm": [float(w) for w in cube.meta.get("wavelengths_nm", ())]}


def _fixed_pattern_step(step: int, frames, two_point, model) -> dict:
    """Fixed-pattern non-uniformity of one test step: raw (less the dark the two-point
    pipeline removed), after the two-point pipeline and after model_ffc, on the same pixels
    (no DQ bit in any frame, raw or corrected by either)."""
    tp = [two_point.transform(f) for f in frames]
    mf = [model.transform(f) for f in frames]
    good = np.all([f.dq == 0 for f in frames + tp + mf], axis=0)
    band_map = frames[0].band_map()
    raw = np.stack([f.data for f in frames]).astype(np.float64)
    before = fixed_pattern_nonuniformity(raw, band_map, dark=tp[0].dark_removed, mask=good)
    after = fixed_pattern_nonuniformity(np.stack([c.data for c in tp]), band_map, mask=good)
    by_model = fixed_pattern_nonuniformity(np.stack([c.data for c in mf]), band_map, mask=good)
    return {"step": step, "exposure_ms": frames[0].exposure_ms, "n_frames": len(frames),
            "before": before.to_dict(), "after": after.to_dict(),
            "model_ffc": by_model.to_dict(),
            "improvement_percent_points": before.pooled_fpn_percent - after.pooled_fpn_percent,
            "model_improvement_percent_points": (before.pooled_fpn_percent
                                                 - by_model.pooled_fpn_percent),
            "n_pixels": int(good.sum())}
