"""Joint calibration of a whole sensor: design checks, sensor-wide choices, the per-pixel fit.

``calibrate_joint`` refuses sweeps that cannot calibrate anything (with a one-line reason),
makes the sensor-wide choices on a pilot sample of pixels (is there a dark current; does it
fill the well or add after it; where does the fit start b), then fits every pixel with the
numba kernel of :mod:`hsiffc.kernels.pixelfit`, chunk by chunk, and reports per pixel which model
was used and why.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..leakage import model
from ..data.dq import DQ
from ..errors import DataFormatError, ParameterError
from ..data.sweep import Sweep
from ..kernels import pixelfit
from . import choice
from .joint import B_GRID, run_kernel
from .product import Calibration
from .samples import (PhotonTransfer, Samples, collect_samples, dark_lines,
                      exposure_offset, kernel_samples, linear_fit, photon_transfer)

log = logging.getLogger(__name__)

N_PILOT = 4096
MIN_LIGHT_DOSES = 3
DO_NOT_USE_STATUS = (pixelfit.TOO_FEW,) + pixelfit.NO_FIT


def check_design(sweep: Sweep, light_rate=None) -> None:
    """Refuse sweeps that cannot calibrate the model, with a one-line reason and fix.

    Parameters
    ----------
    sweep : Sweep
        The sweep to calibrate.
    light_rate : array_like, optional
        One relative light rate per step, if given to the calibration.

    Raises
    ------
    DataFormatError
        No light frames; non-finite raw values; fewer than three distinct light doses
        (positive exposure x light rate) among the light steps (a light step at zero exposure
        carries no dose: with a known light rate it is a sample of the dark level, with an
        unknown one, as in EMVA 1288 data, it is left out and counted).
    """
    src = sweep.source or None
    if not sweep.is_light.any():
        raise DataFormatError("the sweep has no light frames to calibrate from; record light "
                              "frames at several exposures (or light levels)", path=src)
    if sweep.data.dtype.kind == "f":
        bad = ~np.isfinite(sweep.data)
        n_bad = int(bad.sum())
        if n_bad:
            f, rr, cc = (int(v[0]) for v in np.nonzero(bad))
            raise DataFormatError(
                f"the sweep has {n_bad} non-finite raw values ({100 * n_bad / bad.size:.3g} %; "
                f"first in frame {f} at row {rr}, column {cc}); raw frames must be finite DN: "
                "re-export the frames from the camera or replace the bad values before "
                "calibrating", path=src)
    doses = _light_doses(sweep, light_rate)
    if len(doses) < MIN_LIGHT_DOSES:
        raise DataFormatError(
            f"the sweep has {len(doses)} distinct light dose(s) (exposure x light rate) among "
            f"its light steps; calibrating the response needs at least {MIN_LIGHT_DOSES}: "
            "record light frames at more exposures or light levels", path=src)


def _light_doses(sweep: Sweep, light_rate=None) -> np.ndarray:
    """Distinct relative light doses (rate x exposure) of the usable light steps."""
    from .samples import relative_light_rate

    steps = sweep.steps()
    first = np.array([np.flatnonzero(sweep.step == s)[0] for s in steps])
    info = {"kind": sweep.kind[first], "photons": sweep.photons[first],
            "exposure_ms": sweep.exposure_ms[first], "illumination": sweep.illumination[first]}
    rate, _ = relative_light_rate(info, light_rate=light_rate)
    ok = (info["kind"] == "light") & np.isfinite(rate) & (rate > 0) & (info["exposure_ms"] > 0)
    dose = rate[ok] * info["exposure_ms"][ok]
    return np.unique(np.round(dose / dose.max(), 9)) if dose.size else dose


def _dark_slopes(ks) -> np.ndarray:
    """Per-pixel least-squares slope (DN/ms) of the valid dark samples against exposure, not
    clipped at 0 (the pilot's test of whether the sensor has a dark current at all)."""
    slope = dark_lines(ks)[2]
    return slope[np.isfinite(slope)]


def _pilot(sweep: Sweep, ptc, full_well_dn, light_rate, dark_current, dark_model, seed=0,
           fix_dark=False, offset="auto", n_pilot=N_PILOT):
    """Sensor-wide choices on a random sample of pixels: dark current used or not, dark model,
    start value of b, exposure offset. Returns (use_dc, dark_model, b0, t0, report dict)."""
    h, w = sweep.frame_shape
    n = h * w
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(n, size=min(n, n_pilot), replace=False))
    rr, cc = np.unravel_index(idx, (h, w))
    sub = replace(sweep, data=np.ascontiguousarray(sweep.data[:, rr, cc])[:, None, :],
                  mosaic=None, meta={k: sweep.meta[k] for k in ("frames_averaged",)
                                     if k in sweep.meta})
    smp = collect_samples(sub, full_well_dn=full_well_dn, light_rate=light_rate)
    ks = kernel_samples(smp, ptc)
    dark_exposures = np.unique(smp.exposure_ms[(smp.kind == "dark") & smp.usable_step])
    report = {"n_pilot_pixels": int(idx.size), "n_dark_exposures": int(dark_exposures.size)}
    if offset == "auto":
        report["exposure_offset"] = exposure_offset(ks)
        t0 = report["exposure_offset"]["exposure_offset_ms"]
    else:
        t0 = float(offset or 0.0)
        report["exposure_offset"] = {"exposure_offset_ms": t0, "used": bool(t0),
                                     "reason": "given"}
    ks = kernel_samples(smp, ptc, exposure_offset_ms=t0)
    use_dc = False
    if dark_current is True or (dark_current == "auto" and dark_exposures.size >= 2):
        dc = _dark_slopes(ks)
        med = float(np.median(dc))
        se = 1.4826 * float(np.median(np.abs(dc - med))) / np.sqrt(dc.size)
        use_dc = dark_current is True or med > 3 * se
        report["median_dark_current_dn_per_ms"] = med
    models = [dark_model] if (dark_model != "auto" or not use_dc) else ["in_well", "additive"]
    if not use_dc and dark_model == "auto":
        models = ["in_well"]
    fits = {}
    for m in models:
        fits[m] = run_kernel(**ks, dark_current="estimate" if use_dc else None, dark_model=m,
                             b_start=B_GRID, fix_dark=fix_dark)
    chi2 = {m: float(np.nansum(f.chi2)) for m, f in fits.items()}
    chosen = min(chi2, key=chi2.get)
    if len(chi2) > 1:
        report["pilot_chi2_by_dark_model"] = chi2
    fit = fits[chosen]
    good = (fit.status == pixelfit.LEAKAGE) & fit.leak_constrained
    starts = None
    if good.sum() >= 10:
        # where each pixel's saturation level lies above its highest valid sample, in 1/b
        use = ks["valid"] & ks["light"][:, None]
        ymax = np.where(use, ks["y"], -np.inf).max(axis=0)
        rref = np.where(use, ks["r"][:, None], 0.0).max(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            sat = (np.log(fit.g * rref) - np.log(fit.a)) / fit.b
        margin = np.median((fit.b * (sat - ymax))[good])
        starts = (float(np.median(fit.b[good])), float(margin))
    report["start_b_per_dn_and_margin"] = starts
    return use_dc, chosen, starts, t0, report


def calibrate_joint(sweep: Sweep, *, full_well_dn: float | None = None, light_rate=None,
                    dark_current: bool | str = "auto", dark_model: str = "auto",
                    dark_from: str = "frames", exposure_offset_ms="auto", flats=None,
                    choose: bool = True, rows_per_chunk: int | None = None,
                    progress=None, ptc: PhotonTransfer | None = None,
                    pilot_pixels: int = N_PILOT) -> Calibration:
    """Joint per-pixel fit of responsivity, a, b and the dark model from one sweep, with each
    band's model chosen by held-out prediction.

    Every per-pixel parameter is earned from the data that determine it best: the dark level
    of each pixel from its dark frames (``dark_from="frames"``: the fit holds it there; the
    light response does not set it), a light response that does not start at the dark level
    as one exposure offset for the sensor (:func:`~hsiffc.calibrate.samples.exposure_offset`),
    leakage a and b only where the sweep determines them, and per band the simplest model
    that predicts held-out light steps as well as the richer ones
    (:mod:`hsiffc.calibrate.choice`; ``fitted_on["model_choice"]`` records what was kept and
    every candidate's held-out error).

    Parameters
    ----------
    sweep : Sweep
        Light and (ideally) dark steps. The light rate of a step is photons / exposure when
        photon counts are present (EMVA 1288), else 1 for every light step (single
        illumination), or ``light_rate`` (one value per step).
    full_well_dn : float, optional
        Samples at or above this level (DN) are left out as full-well saturated.
    dark_current : "auto", True or False
        Estimate a per-pixel dark current (DN/ms) from dark steps at two or more exposures
        ("auto": when they exist and the sensor as a whole shows one above the noise).
    dark_model : "auto", "in_well" or "additive"
        Whether the dark current fills the well with the signal (and leaks with it) or adds to
        the response after it; "auto" picks the one that fits a pilot sample of pixels better.
    dark_from : "frames" or "fit"
        The dark level from the dark frames (default, where the sweep has them), or a free
        parameter of each pixel's fit (the intercept of its light response; before 0.9).
    exposure_offset_ms : "auto" or float, ms
        Light collected for ``t + t0``: "auto" measures ``t0`` on the sweep (0 where it is not
        significant), a number sets it.
    flats : Sweep, optional
        Flat stacks and the dark frames of their exposure: the stack two-point becomes a
        candidate of the model choice (fold them into the calibration afterwards with
        :func:`hsiffc.calibrate.flats.add_flat_stacks`).
    choose : bool
        Choose the model by held-out prediction, and use a pixel's leakage only where its
        samples earn it (default); False keeps the leakage model wherever its fit converged
        (with ``dark_from="fit"`` and ``exposure_offset_ms=0``: the leakage model's own account
        of a sweep, as the EMVA 1288 leakage analysis and the paper's reproduction use it).
    rows_per_chunk : int, optional
        Rows fitted at once (memory is bounded by rows x width x steps).
    progress : callable, optional
        Called with (rows_done, rows_total) after each chunk.
    ptc : PhotonTransfer, optional
        The photon transfer of the sweep's raw frames, when its frames are step means
        (``meta["frames_averaged"]``: how many raw frames each stands for) that cannot give
        it (:func:`~hsiffc.calibrate.samples.photon_transfer_from_pairs`).
    pilot_pixels : int
        Pixels drawn at random (seed 0) for the sensor-wide choices made before the per-pixel
        fit (dark current, dark model, the start values of b and of the saturation margin).

    Returns
    -------
    Calibration
        With per-pixel ``fit_status`` (see :data:`hsiffc.kernels.pixelfit.STATUS_REASONS`),
        ``model_kept`` (code of :data:`hsiffc.calibrate.choice.CANDIDATES`) and, in
        ``fitted_on``, the counts per reason, the dark model, the exposure offset and the
        model choice.

    Raises
    ------
    DataFormatError
        The sweep cannot calibrate the model (see :func:`check_design`), or no pixel has
        enough valid samples.
    """
    check_design(sweep, light_rate)
    if dark_from not in ("frames", "fit"):
        raise ParameterError(f"dark_from must be 'frames' or 'fit', got {dark_from!r}")
    h, w = sweep.frame_shape
    ptc = ptc or photon_transfer(sweep)
    fix = dark_from == "frames" and bool(sweep.is_dark.any())
    use_dc, dmodel, starts, t0, pilot = _pilot(sweep, ptc, full_well_dn, light_rate,
                                               dark_current, dark_model, fix_dark=fix,
                                               offset=exposure_offset_ms, n_pilot=pilot_pixels)
    settings = choice.FitSettings(ptc, full_well_dn, use_dc, dmodel, starts, t0, fix)
    chosen = (choice.choose_models(sweep, settings, flats=flats, light_rate=light_rate)
              if choose else None)
    band_map = (sweep.mosaic.band_map(sweep.frame_shape) if sweep.mosaic is not None
                else np.zeros(sweep.frame_shape, np.int64))
    codes = choice.kept_codes(chosen, band_map)
    n_steps = len(sweep.steps())
    rows_per_chunk = rows_per_chunk or max(1, (1 << 21) // (w * n_steps))
    out = {name: np.zeros((h, w), np.float32) for name in (
        "responsivity", "a_dn_per_ms", "b_per_dn", "dark_dn", "dark_current_dn_per_ms",
        "sigma_ln_g", "sigma_ln_a", "sigma_ln_b", "sigma_dark_dn", "rms_dn", "chi2_red",
        "saturation_ref_dn")}
    counts = {name: np.zeros((h, w), np.int32) for name in ("n_valid", "n_clipped", "n_full_well")}
    status = np.zeros((h, w), np.uint8)
    linear = np.zeros((h, w), bool)
    info = None
    for r0 in range(0, h, rows_per_chunk):
        rows = slice(r0, min(h, r0 + rows_per_chunk))
        smp = collect_samples(sweep, full_well_dn=full_well_dn, light_rate=light_rate, rows=rows,
                              dtype=np.float64)  # the kernel's precision: no conversion pass
        info = info or smp
        fit, ks = settings.fit(smp)
        kept = choice.candidate_parameters(fit, ks, settings, codes[rows].ravel(), earn=choose)
        shape = (rows.stop - rows.start, w)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            sat = np.where(kept["a"] > 0, model.dynamic_saturation_level(
                np.maximum(fit.g * fit.r_ref, 1e-300), np.maximum(kept["a"], 1e-300), fit.b),
                np.inf)
        lin = kept["linear"]
        for name, v in (("responsivity", kept["responsivity"]), ("a_dn_per_ms", kept["a"]),
                        ("b_per_dn", fit.b), ("dark_dn", kept["dark"]),
                        ("dark_current_dn_per_ms", fit.dark_current),
                        ("sigma_ln_g", kept["sigma_ln_g"]),
                        ("sigma_ln_a", fit.sigma[:, 1]),
                        ("sigma_ln_b", fit.sigma[:, 2]),
                        ("sigma_dark_dn", fit.sigma[:, 3]),  # held: the dark frames' error
                        ("rms_dn", fit.rms_dn), ("chi2_red", fit.chi2_red),
                        ("saturation_ref_dn", sat)):
            out[name][rows] = v.reshape(shape)
        linear[rows] = lin.reshape(shape)
        usable = smp.usable_step
        counts["n_valid"][rows] = fit.n_valid.reshape(shape)
        counts["n_clipped"][rows] = smp.clipped[usable].sum(axis=0, dtype=np.int32).reshape(shape)
        if full_well_dn is not None:  # else no sample is at full well
            counts["n_full_well"][rows] = (smp.full_well & ~smp.clipped)[usable].sum(
                axis=0, dtype=np.int32).reshape(shape)
        status[rows] = fit.status.reshape(shape)
        if progress:
            progress(rows.stop, h)
    flags = choice.calibration_flags(status, out["sigma_ln_b"],
                                     codes == choice.CODES["pixel_leakage"])
    _refuse_if_nothing_fitted(sweep, status, counts)
    _fill_unusable(out, status)
    light_ok = info.usable_step & (info.kind == "light")
    arrays = {**out, **counts, "flags": flags, "fit_status": status,
              "model_kept": np.where(linear & (codes == choice.CODES["pixel_leakage"]),
                                     choice.CODES["linear"], codes).astype(np.uint8)}
    if info.rate_unit.startswith("1 ="):
        arrays["k_ref_dn_per_ms"] = out["responsivity"]
    fitted = _fitted_on(sweep, info, ptc, full_well_dn)
    fitted["fit_status"] = {pixelfit.STATUS_REASONS[c]: int((status == c).sum())
                            for c in sorted(pixelfit.STATUS_REASONS) if (status == c).any()}
    fitted["dark_model"] = {
        "dark_current": bool(use_dc), "model": dmodel if use_dc else "constant dark level",
        "description": ("dark level + dark current x exposure, the dark current "
                        + ("filling the well with the signal (it leaks with it)"
                           if dmodel == "in_well" else "added to the response after leakage")
                        if use_dc else "a constant dark level per pixel"),
        "dark_from": "dark frames" if fix else "each pixel's fit",
        **pilot}
    fitted["exposure_offset_ms"] = float(t0)
    fitted["model_choice"] = chosen or {"bands": None, "reason": (
        "not asked" if not choose else "too few light steps or no dark frames to compare "
        "models on held-out steps: the leakage model where the sweep determines it")}
    log.info("calibrated %d x %d px: %s", w, h, fitted["fit_status"])
    return Calibration(arrays=arrays, domain=_domain(sweep, info, info.rate[light_ok]),
                       method="joint", fitted_on=fitted)


def _refuse_if_nothing_fitted(sweep, status, counts) -> None:
    if not np.isin(status, DO_NOT_USE_STATUS).all():
        return
    n_px = status.size
    reasons = {pixelfit.STATUS_REASONS[c]: int((status == c).sum()) for c in DO_NOT_USE_STATUS
               if (status == c).any()}
    main = max(reasons, key=reasons.get)
    raise DataFormatError(
        f"no pixel of the sweep can be calibrated: {main} in {reasons[main]} of {n_px} pixels "
        f"({int(counts['n_clipped'].sum())} samples clipped at full scale, "
        f"{int(counts['n_full_well'].sum())} at full well); record the sweep with shorter "
        "exposures or less light so that the response stays below full scale",
        path=sweep.source or None)


def _fill_unusable(out, status) -> None:
    """Pixels without a fit (flagged DO_NOT_USE) get the sensor's median parameters: finite
    values; their uncertainties are infinite."""
    bad = np.isin(status, pixelfit.NO_FIT)
    if not bad.any():
        return
    for name in ("responsivity", "a_dn_per_ms", "b_per_dn", "dark_dn", "dark_current_dn_per_ms",
                 "saturation_ref_dn", "rms_dn", "chi2_red"):
        v = out[name]
        good = ~bad & np.isfinite(v)
        v[bad] = np.median(v[good]) if good.any() else 0.0
    for name in ("sigma_ln_g", "sigma_ln_a", "sigma_ln_b", "sigma_dark_dn"):
        out[name][bad] = np.inf


def _domain(sweep: Sweep, info: Samples, rates) -> dict:
    usable = info.usable_step
    return {"exposure_ms": [float(info.exposure_ms[usable].min()),
                            float(info.exposure_ms[usable].max())],
            "light_rate": [float(np.min(rates)), float(np.max(rates))] if len(rates) else [0, 0],
            "light_rate_unit": info.rate_unit, "bit_depth": sweep.bit_depth,
            "full_scale_dn": sweep.full_scale_dn, "frame_shape": list(sweep.frame_shape),
            "mosaic": sweep.mosaic.to_dict() if sweep.mosaic else None}


def _fitted_on(sweep: Sweep, info: Samples, ptc, full_well_dn) -> dict:
    return {"source": sweep.source or "in-memory sweep", "n_frames": sweep.n_frames,
            "n_steps": len(info.step), "n_unusable_steps": int((~info.usable_step).sum()),
            "illuminations": sorted(set(info.illumination[info.kind == "light"].tolist())),
            "photon_transfer": None if ptc is None else {
                "gain_dn_per_e": ptc.gain_dn_per_e, "read_var_dn2": ptc.read_var_dn2},
            "full_well_dn": full_well_dn}
