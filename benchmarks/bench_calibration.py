"""Calibration benchmark: the vectorised joint fit on a full sensor against curve_fit per pixel.

A 2048 x 1088 sensor (a CMV2000) is calibrated from a 20-exposure sweep (2..400 ms, lamp A at a
quarter of the training irradiance, so pixels reach dynamic saturation near 900 DN; 2 light and
2 dark frames per exposure). Reported: wall time and peak memory of ``calibrate(sweep)``, one
run, with the simulation timed separately.

Baseline: the same model fitted pixel by pixel with ``scipy.optimize.curve_fit`` on the same
samples a pixel gets in ``calibrate`` (same step means and validity, dark samples as rate-0
samples, the same fixed dark current when the calibration uses one, photon-transfer weights
passed as ``sigma``, the same start values from ``initial_guess``). It is timed on a random
sample of pixels and extrapolated to the sensor; only the curve_fit calls are timed (building
samples and start values is left out, which favours the baseline). Accuracy of both is measured
against the simulator's ground truth.
"""

from __future__ import annotations

import time
import tracemalloc
import warnings
from dataclasses import replace

import numpy as np
from scipy.optimize import OptimizeWarning, curve_fit

from _util import median_time, row
from hsiffc import model
from hsiffc.calibrate import _pilot_b_grid, calibrate, fit_inputs
from hsiffc.calibrate.joint import (fit_pixels, initial_guess)
from hsiffc.calibrate.samples import collect_samples, photon_transfer
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

SHAPE = (1088, 2048)
QUICK_SHAPE = (272, 512)
EXPOSURES_MS = np.geomspace(2.0, 400.0, 20)
IRRADIANCE = "training"
IRRADIANCE_FACTOR = 0.25


# -- samples of a set of pixels, prepared exactly as calibrate_joint prepares a chunk ----------
def _pixel_samples(sweep, ptc, flat_idx):
    """Fit inputs of the pixels ``flat_idx`` (flattened indices), as in ``calibrate_joint``.

    Returns a dict with the (possibly dark-merged) fit samples ``y, t, r, valid, wgt``, the
    unmerged samples ``y_all, t_all, r_all, valid_all`` (residual RMS is taken over these, like
    the calibration's ``rms_dn``), and the fixed dark current ``dc`` (None when not used).
    """
    h, w = sweep.frame_shape
    rr, cc = np.unravel_index(np.asarray(flat_idx), (h, w))
    sub = replace(sweep, data=np.ascontiguousarray(sweep.data[:, rr, cc])[:, None, :],
                  mosaic=None, meta={})
    smp = collect_samples(sub)
    fi = fit_inputs(smp, ptc)
    out = {"y_all": fi["y_all"], "t_all": smp.exposure_ms, "r_all": smp.rate,
           "valid_all": fi["valid_all"], "dc": fi["dc"], "y": fi["y"], "t": fi["t"],
           "r": fi["r"], "valid": fi["valid"], "wgt": fi["wgt"]}
    return out


def _rms(ps, theta):
    """Unweighted RMS residual (DN) over each pixel's valid unmerged samples."""
    dc = 0.0 if ps["dc"] is None else ps["dc"][:, None]
    k = np.exp(theta[:, 0:1]) * ps["r_all"][None, :] + dc
    ym = model.response(ps["t_all"][None, :], k, np.exp(theta[:, 1:2]), np.exp(theta[:, 2:3]),
                        theta[:, 3:4])
    res = np.where(ps["valid_all"], ym - ps["y_all"], 0.0)
    return np.sqrt((res ** 2).sum(axis=1) / np.maximum(ps["valid_all"].sum(axis=1), 1))


# -- the baseline -----------------------------------------------------------------------------
def _trpredict(x, ln_k, ln_a, ln_b, d):
    """The leakage model for curve_fit: x = (t_ms, relative rate, fixed dark current)."""
    t, r, dc = x
    return model.response(t, np.exp(ln_k) * r + dc, np.exp(ln_a), np.exp(ln_b), d)


def _curve_fit_pixels(ps, theta0):
    """curve_fit on every pixel of ``ps`` in turn; returns (theta, nfev, failed, seconds)."""
    p = ps["y"].shape[0]
    theta = np.full((p, 4), np.nan)
    nfev = np.zeros(p, np.int64)
    failed = np.zeros(p, bool)
    dc = np.zeros(p) if ps["dc"] is None else ps["dc"]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizeWarning)
        for i in range(p):
            m = ps["valid"][i]
            x = np.vstack([ps["t"][m], ps["r"][m], np.full(m.sum(), dc[i])])
            try:
                popt, _, info, _, _ = curve_fit(_tr_model, x, ps["y"][i, m], p0=theta0[i],
                                                sigma=1.0 / np.sqrt(ps["wgt"][i, m]),
                                                maxfev=20000, full_output=True)
                theta[i], nfev[i] = popt, info["nfev"]
            except (RuntimeError, ValueError):
                failed[i] = True
    return theta, nfev, failed, time.perf_counter() - t0


# -- accuracy ---------------------------------------------------------------------------------
def _errors(theta, truth_k, truth_a, truth_b, truth_d):
    """Per-pixel errors: |dk/k|, |db/b|, |d ln a|, |d dark| (DN)."""
    return {"k_rel": np.abs(np.exp(theta[:, 0]) / truth_k - 1),
            "b_rel": np.abs(np.exp(theta[:, 2]) / truth_b - 1),
            "ln_a_abs": np.abs(theta[:, 1] - np.log(truth_a)),
            "dark_abs_dn": np.abs(theta[:, 3] - truth_d)}


METRICS = (("k_rel", "median |k rel. error|", ""), ("b_rel", "median |b rel. error|", ""),
           ("ln_a_abs", "median |ln a error|", ""), ("dark_abs_dn", "median |dark error|", "DN"),
           ("rms_dn", "median residual RMS", "DN"))


def main(quick: bool = False) -> dict:
    shape = QUICK_SHAPE if quick else SHAPE
    npx = shape[0] * shape[1]
    n_sample = 100 if quick else 300
    results = {"shape": list(shape), "quick": bool(quick)}
    print(f"Calibration benchmark on {shape[1]} x {shape[0]} pixels ({npx / 1e6:.2f} Mpx)"
          + (" -- QUICK MODE: reduced sensor, not the 2048 x 1088 figure" if quick else ""))
    print(f"  sweep: {EXPOSURES_MS.size} exposures {EXPOSURES_MS[0]:g}..{EXPOSURES_MS[-1]:g} ms "
          f"(geometric), lamp A at {IRRADIANCE_FACTOR} x {IRRADIANCE} irradiance, "
          "2 light + 2 dark frames per exposure")

    # -- simulate (not part of the calibration figure) ----------------------------------------
    sensor = MosaicSensor(shape, seed=0)
    t0 = time.perf_counter()
    sweep = sensor.sweep(EXPOSURES_MS, "lamp A",
                         irradiance_w_m2=PAPER_LIGHT_W_M2[IRRADIANCE] * IRRADIANCE_FACTOR,
                         n_frames=2, seed=1)
    t_sim = time.perf_counter() - t0
    truth = sweep.meta["truth"]
    results["simulate_s"] = t_sim
    results["sweep_mb"] = sweep.data.nbytes / 2 ** 20
    print(row("simulate the sweep (not in the calibration time)", t_sim, "s",
              f"{sweep.n_frames} frames, {results['sweep_mb']:.0f} MiB uint16"))

    # -- calibrate: one timed run, then one run under tracemalloc for the peak memory (tracing
    # slows numpy's allocations, so it must not be inside the timed run) --------------------
    t0 = time.perf_counter()
    cal = calibrate(sweep)
    t_cal = time.perf_counter() - t0
    tracemalloc.start()
    try:
        calibrate(sweep)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    results["calibrate_s"] = t_cal
    results["calibrate_mpx_s"] = npx / t_cal / 1e6
    results["calibrate_peak_mb"] = peak / 2 ** 20
    results["calibrate_us_per_px"] = t_cal / npx * 1e6
    print(row("calibrate(sweep), joint fit (single run)", t_cal, "s",
              f"{results['calibrate_mpx_s']:.3f} Mpx/s, "
              f"{results['calibrate_us_per_px']:.0f} us/px"))
    print(row("calibrate peak memory (tracemalloc, 2nd run, sweep excluded)",
              results["calibrate_peak_mb"],
              "MiB"))
    arr = cal.arrays
    flags = arr["flags"]
    results["flagged_fraction"] = float((flags != 0).mean())
    results["dark_current_used"] = bool(np.any(arr["dark_current_dn_per_ms"] != 0))

    # -- the same fit inputs for a random sample of pixels ------------------------------------
    ptc = photon_transfer(sweep)
    h, w = shape
    rows_per_chunk = max(1, 262144 // (w * len(sweep.steps())))  # calibrate's first chunk
    first = _pixel_samples(sweep, ptc, np.arange(min(h, rows_per_chunk) * w))
    b_grid = _pilot_b_grid(first["y"], first["t"], first["r"], first["valid"], first["wgt"],
                           first["dc"])
    del first
    rng = np.random.default_rng(2)
    idx = np.sort(rng.choice(npx, size=n_sample, replace=False))
    ps = _pixel_samples(sweep, ptc, idx)
    del sweep  # 80 frames of the full sensor: not needed any more

    def vec_fit():
        th0 = initial_guess(ps["y"], ps["t"], ps["r"], ps["valid"], ps["wgt"], ps["dc"],
                            b_grid=b_grid)
        return th0, fit_pixels(ps["y"], ps["t"], ps["r"], ps["valid"], ps["wgt"], th0,
                              dark_current=ps["dc"])

    theta0, fit = vec_fit()
    t_vec_sample = median_time(vec_fit, repeat=3 if quick else 5)
    theta_vec = np.column_stack([np.log(fit.g), np.log(fit.a), np.log(fit.b), fit.dark])
    # check: the sample's fit is the calibration's fit of the same pixels
    same = {name: np.abs(fit_val / arr[key].ravel()[idx] - 1).max() for name, fit_val, key in (
        ("k", fit.g, "responsivity"), ("a", fit.a, "a_dn_per_ms"), ("b", fit.b, "b_per_dn"))}
    results["sample_vs_calibrate_max_rel_diff"] = float(max(same.values()))

    theta_cf, nfev, failed, t_cf = _curve_fit_pixels(ps, theta0)
    per_px = t_cf / n_sample
    t_cf_sensor = per_px * npx
    results["curve_fit_sample_px"] = n_sample
    results["curve_fit_ms_per_px"] = per_px * 1e3
    results["curve_fit_sensor_s_extrapolated"] = t_cf_sensor
    results["curve_fit_median_nfev"] = float(np.median(nfev[~failed])) if (~failed).any() else 0.0
    results["curve_fit_failed"] = int(failed.sum())
    results["joint_fit_sample_ms_per_px"] = t_vec_sample / n_sample * 1e3
    results["speedup_vs_curve_fit"] = t_cf_sensor / t_cal
    results["speedup_same_sample"] = t_cf / t_vec_sample
    print(row(f"curve_fit per pixel ({n_sample} random px)", per_px * 1e3, "ms/px",
              f"median {results['curve_fit_median_nfev']:.0f} model calls/px, "
              f"{results['curve_fit_failed']} failed"))
    print(row("curve_fit extrapolated to the sensor (fits only)", t_cf_sensor, "s",
              f"{t_cf_sensor / 3600:.2f} h"))
    print(row("joint fit on the same sample (start values + fit)",
              results["joint_fit_sample_ms_per_px"], "ms/px",
              f"median of runs; {t_vec_sample * 1e3:.1f} ms for {n_sample} px"))
    print(row("ratio: curve_fit (extrapolated) / calibrate wall time",
              results["speedup_vs_curve_fit"], "x", "target >= 100x"))
    print(row("ratio on the sample itself (curve_fit / joint fit)",
              results["speedup_same_sample"], "x", "fits only, identical inputs and start values"))

    # -- accuracy against the simulator truth --------------------------------------------------
    tk = truth.k_dn_per_ms.ravel()
    ta, tb, td = (v.ravel() for v in (truth.a_dn_per_ms, truth.b_per_dn, truth.dark_dn))
    e_vec = _errors(theta_vec, tk[idx], ta[idx], tb[idx], td[idx])
    e_vec["rms_dn"] = _rms(ps, theta_vec)
    ok = ~failed
    e_cf = _errors(theta_cf[ok], tk[idx][ok], ta[idx][ok], tb[idx][ok], td[idx][ok])
    e_cf["rms_dn"] = _rms({**ps, "dc": None if ps["dc"] is None else ps["dc"][ok],
                           "y_all": ps["y_all"][ok], "valid_all": ps["valid_all"][ok]},
                          theta_cf[ok])
    all_theta = np.column_stack([np.log(arr["responsivity"].ravel()),
                                 np.log(arr["a_dn_per_ms"].ravel()),
                                 np.log(arr["b_per_dn"].ravel()), arr["dark_dn"].ravel()]
                                ).astype(np.float64)
    e_all = _errors(all_theta, tk, ta, tb, td)
    e_all["rms_dn"] = arr["rms_dn"].ravel()
    del cal, arr

    print(f"  accuracy against the simulator truth (medians; joint fit vs curve_fit on the same "
          f"{n_sample} px; {results['flagged_fraction'] * 100:.1f} % of pixels carry a DQ flag)")
    equal = True
    for key, label, unit in METRICS:
        v, c, a = (float(np.median(e[key])) for e in (e_vec, e_cf, e_all))
        results[f"joint_sample_{key}"] = v
        results[f"curve_fit_sample_{key}"] = c
        results[f"joint_all_{key}"] = a
        # equal: the joint fit's median error is no worse than curve_fit's by more than 10 %
        equal &= v <= 1.1 * c + 1e-12
        print(row(f"{label}: joint fit", v, unit, f"curve_fit {c:.4g}; joint, all px {a:.4g}"))
    # how far apart the two fits of the same pixels land
    d = np.abs(theta_vec[ok] - theta_cf[ok])
    results["joint_vs_curve_fit_median_abs_dln_k"] = float(np.median(d[:, 0]))
    results["joint_vs_curve_fit_median_abs_dln_b"] = float(np.median(d[:, 2]))
    results["joint_vs_curve_fit_median_abs_ddark_dn"] = float(np.median(d[:, 3]))
    print(row("joint fit vs curve_fit, median |d ln k|", results[
        "joint_vs_curve_fit_median_abs_dln_k"], "", f"|d ln b| {np.median(d[:, 2]):.2g}, "
              f"|d dark| {np.median(d[:, 3]):.2g} DN"))
    results["equal_accuracy"] = bool(equal)
    results["sample_vs_calibrate_check"] = results["sample_vs_calibrate_max_rel_diff"] < 1e-4
    print(f"  equal accuracy (every joint median within 10 % of curve_fit's or better): "
          f"{'yes' if equal else 'NO'}; sample fit reproduces calibrate's pixels to "
          f"{results['sample_vs_calibrate_max_rel_diff']:.1e} (float32 storage)")
    return {k: (float(v) if isinstance(v, (np.floating, np.integer)) else v)
            for k, v in results.items()}


if __name__ == "__main__":
    main()
