"""Calibration benchmark: the numba per-pixel fit on a full sensor against curve_fit per pixel.

A 2048 x 1088 sensor (a CMV2000) is calibrated from a 20-exposure sweep (2..400 ms, lamp A at a
quarter of the training irradiance, so pixels reach dynamic saturation near 900 DN; 2 light and
2 dark frames per exposure). Reported: wall time of ``calibrate(sweep)`` (one run after a
warm-up on a small sweep, so the figure excludes numba's one-time compilation, which is cached
on disk and stated separately), the peak resident memory it adds, and where the time goes.

Baseline: the same model fitted pixel by pixel with ``scipy.optimize.curve_fit`` on exactly the
samples and weights each pixel's fit sees in ``calibrate`` (light step means, the merged dark
sample, the same fixed dark current; weights passed as ``sigma``; the same start values). It is
timed on a random sample of pixels and extrapolated per pixel to the sensor; only the curve_fit
calls are timed (building samples and start values is left out, which favours the baseline), as
the CPU time of the thread that runs them (waiting for the core is not counted); the wall time
is printed too. On this shared machine the baseline is not steady: with the same 26 model calls
per pixel, its wall time read 2.2 to 15 ms per pixel in different page runs and its thread time
2.5 to 8.3, so the ratio swings with it (about 900 to 5900 x so far, above the target in every
run); the cause was not found (the same code in a quiet process reads 2.5).
Accuracy of both is measured against the simulator's ground truth (medians).
"""

from __future__ import annotations

import resource
import time
import warnings
from dataclasses import replace

import numpy as np
from scipy.optimize import OptimizeWarning, curve_fit

from benchutil import figure, row
from hsiffc.leakage import model
from hsiffc.calibrate import calibrate, collect_samples, photon_transfer
from hsiffc.calibrate.joint import prepared_samples, run_kernel
from hsiffc.calibrate.sensor import kernel_samples
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor

SHAPE = (1088, 2048)
QUICK_SHAPE = (272, 512)
EXPOSURES_MS = np.geomspace(2.0, 400.0, 20)
IRRADIANCE = "training"
IRRADIANCE_FACTOR = 0.25


def _sweep(shape, seed=0):
    sensor = MosaicSensor(shape, seed=seed)
    return sensor.sweep(EXPOSURES_MS, "lamp A",
                        irradiance_w_m2=PAPER_LIGHT_W_M2[IRRADIANCE] * IRRADIANCE_FACTOR,
                        n_frames=2, seed=seed + 1)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# -- the samples of a set of pixels, prepared exactly as calibrate prepares them -------------
def _pixel_inputs(sweep, ptc, flat_idx, cal):
    """Each pixel's fit samples as the kernel sees them (light means, weights, the merged dark
    sample, the dark current) and its start values, for the pixels ``flat_idx``."""
    h, w = sweep.frame_shape
    rr, cc = np.unravel_index(np.asarray(flat_idx), (h, w))
    sub = replace(sweep, data=np.ascontiguousarray(sweep.data[:, rr, cc])[:, None, :],
                  mosaic=None, meta={})
    ks = kernel_samples(collect_samples(sub), ptc)
    dm = cal.fitted_on["dark_model"]
    dc = "estimate" if dm["dark_current"] else None
    ps = prepared_samples(ks["y"], ks["valid"], ks["t"], ks["r"], ks["light"], ks["dark"],
                          n_frames=ks["n_frames"], noise=ks["noise"], dark_current=dc)
    starts = dm["start_b_per_dn_and_margin"]
    kw = {"b_start": starts[0], "margins": (starts[1],)} if starts else {}
    start = run_kernel(**ks, dark_current=dc, max_iter=0, **kw).theta
    return ks, ps, start, dm.get("model", "in_well"), dc, kw


def _curve_fit_pixels(ks, ps, theta0):
    """curve_fit on every pixel in turn; returns (theta, nfev, failed, thread CPU seconds,
    wall seconds)."""
    p = ps["y"].shape[0]
    theta = np.full((p, 4), np.nan)
    nfev = np.zeros(p, np.int64)
    failed = np.zeros(p, bool)
    light = ks["light"]

    def f(x, ln_g, ln_a, ln_b, d):
        t, r, dc = x
        return model.response(t, np.exp(ln_g) * r + dc, np.exp(ln_a), np.exp(ln_b), d)

    t0 = time.perf_counter()
    c0 = time.thread_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizeWarning)
        for i in range(p):
            m = light & (ps["w"][i] > 0)
            t = np.append(ks["t"][m], ps["dark_t_ms"][i])
            r = np.append(ks["r"][m], 0.0)
            y = np.append(ps["y"][i, m], ps["dark_dn"][i])
            w = np.append(ps["w"][i, m], ps["dark_weight"][i])
            x = np.vstack([t, r, np.full(t.size, ps["dark_current"][i])])
            try:
                popt, _, info, _, _ = curve_fit(f, x, y, p0=theta0[i], sigma=1 / np.sqrt(w),
                                                maxfev=20000, full_output=True)
                theta[i], nfev[i] = popt, info["nfev"]
            except (RuntimeError, ValueError):
                failed[i] = True
    return theta, nfev, failed, time.thread_time() - c0, time.perf_counter() - t0


def _errors(theta, truth, idx):
    """Per-pixel errors against the truth: |dk/k|, |db/b|, |d ln a|, |d dark| (DN)."""
    tk, ta, tb, td = (np.ravel(v)[idx] for v in (truth.k_dn_per_ms, truth.a_dn_per_ms,
                                                 truth.b_per_dn, truth.dark_dn))
    return {"k_rel": np.abs(np.exp(theta[:, 0]) / tk - 1),
            "b_rel": np.abs(np.exp(theta[:, 2]) / tb - 1),
            "ln_a_abs": np.abs(theta[:, 1] - np.log(ta)),
            "dark_abs_dn": np.abs(theta[:, 3] - td)}


def _rms(ks, ps, theta):
    """Unweighted RMS residual (DN) over each pixel's light samples and merged dark."""
    dc = ps["dark_current"][:, None]
    t = np.column_stack([np.broadcast_to(ks["t"], ps["y"].shape), ps["dark_t_ms"]])
    r = np.column_stack([np.broadcast_to(ks["r"], ps["y"].shape), np.zeros(len(ps["y"]))])
    y = np.column_stack([ps["y"], ps["dark_dn"]])
    use = np.column_stack([(ps["w"] > 0) & ks["light"][None, :], ps["dark_weight"] > 0])
    with np.errstate(over="ignore", invalid="ignore"):
        m = model.response(t, np.exp(theta[:, 0:1]) * r + dc, np.exp(theta[:, 1:2]),
                           np.exp(theta[:, 2:3]), theta[:, 3:4])
    res = np.where(use, m - y, 0.0)
    return np.sqrt((res ** 2).sum(axis=1) / np.maximum(use.sum(axis=1), 1))


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
    # -- warm-up: first call in this process (numba loads its compiled kernels from the disk
    # cache, or compiles them once if the cache is cold) -----------------------------------
    t0 = time.perf_counter()
    calibrate(_sweep((16, 16), seed=5))
    results["first_call_small_s"] = time.perf_counter() - t0
    print(row("first call on a 16 x 16 sweep (kernel load/compile)",
              results["first_call_small_s"], "s", "cached on disk after the first compile"))

    t0 = time.perf_counter()
    sweep = _sweep(shape)
    results["simulate_s"] = time.perf_counter() - t0
    results["sweep_mb"] = sweep.data.nbytes / 2 ** 20
    print(row("simulate the sweep (not in the calibration time)", results["simulate_s"], "s",
              f"{sweep.n_frames} frames, {results['sweep_mb']:.0f} MiB uint16"))

    rss0 = _peak_rss_mb()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    cal = calibrate(sweep)
    t_cal = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    results["calibrate_s"] = t_cal
    results["calibrate_cpu_s"] = cpu
    results["calibrate_mpx_s"] = npx / t_cal / 1e6
    results["calibrate_peak_rss_added_mb"] = max(_peak_rss_mb() - rss0, 0.0)
    print(row("calibrate(sweep), wall time (single run)", t_cal, "s",
              f"{results['calibrate_mpx_s']:.3f} Mpx/s; CPU {cpu:.1f} s (2 cores: "
              f"{cpu / t_cal:.2f} busy)"))
    print(row("calibrate: peak resident memory added", results["calibrate_peak_rss_added_mb"],
              "MiB", "process peak RSS after - before"))
    arr = cal.arrays
    status = cal.fitted_on["fit_status"]
    results["fit_status"] = status
    results["flagged_fraction"] = float((arr["flags"] != 0).mean())
    print(f"  fit status: {status}; dark model: {cal.fitted_on['dark_model']['model']}")

    # -- baseline on a random sample of pixels, same samples, weights and start values -------
    ptc = photon_transfer(sweep)
    rng = np.random.default_rng(2)
    idx = np.sort(rng.choice(npx, size=n_sample, replace=False))
    ks, ps, theta0, dmodel, dc, kw = _pixel_inputs(sweep, ptc, idx, cal)
    truth = sweep.meta["truth"]
    del sweep
    theta_cf, nfev, failed, t_cf, t_cf_wall = _curve_fit_pixels(ks, ps, theta0)
    fit = run_kernel(**ks, dark_current=dc, dark_model=dmodel, **kw)
    theta_k = fit.theta
    per_px = t_cf / n_sample
    results["curve_fit_sample_px"] = n_sample
    results["curve_fit_ms_per_px"] = per_px * 1e3
    results["curve_fit_wall_ms_per_px"] = t_cf_wall / n_sample * 1e3
    results["curve_fit_sensor_s_extrapolated"] = per_px * npx
    results["curve_fit_median_nfev"] = float(np.median(nfev[~failed])) if (~failed).any() else 0
    results["curve_fit_failed"] = int(failed.sum())
    results["speedup_vs_curve_fit"] = per_px * npx / t_cal
    same = np.abs(fit.g / arr["responsivity"].ravel()[idx] - 1).max()
    results["sample_vs_calibrate_max_rel_diff_k"] = float(same)
    print(row(f"curve_fit per pixel ({n_sample} random px)", per_px * 1e3, "ms/px",
              f"CPU time of its thread (wall {results['curve_fit_wall_ms_per_px']:.3g} ms/px); "
              f"median {results['curve_fit_median_nfev']:.0f} model calls/px, "
              f"{results['curve_fit_failed']} failed"))
    print(row("curve_fit extrapolated to the sensor (fits only)", per_px * npx, "s",
              f"{per_px * npx / 3600:.2f} h"))
    print(row("ratio: curve_fit (extrapolated) / calibrate wall time",
              results["speedup_vs_curve_fit"], "x", "target >= 500x"))

    # -- accuracy against the simulator truth ----------------------------------------------
    ok = ~failed
    e_k = _errors(theta_k, truth, idx)
    e_k["rms_dn"] = _rms(ks, ps, theta_k)
    e_cf = _errors(theta_cf[ok], truth, idx[ok])
    e_cf["rms_dn"] = _rms(ks, {k: v[ok] for k, v in ps.items()}, theta_cf[ok])
    all_theta = np.column_stack([np.log(arr["responsivity"].ravel()),
                                 np.log(arr["a_dn_per_ms"].ravel()),
                                 np.log(arr["b_per_dn"].ravel()), arr["dark_dn"].ravel()]
                                ).astype(np.float64)
    e_all = _errors(all_theta, truth, slice(None))
    print(f"  accuracy against the simulator truth (medians; kernel vs curve_fit on the same "
          f"{n_sample} px; {results['flagged_fraction'] * 100:.2f} % of pixels carry a DQ flag)")
    equal = True
    for key, label, unit in METRICS:
        v, c = float(np.median(e_k[key])), float(np.median(e_cf[key]))
        a = float(np.median(e_all[key])) if key in e_all else float(np.median(arr["rms_dn"]))
        results[f"kernel_sample_{key}"] = v
        results[f"curve_fit_sample_{key}"] = c
        results[f"calibrate_all_{key}"] = a
        equal &= v <= 1.1 * c + 1e-12  # equal: no worse than curve_fit by more than 10 %
        print(row(f"{label}: kernel", v, unit, f"curve_fit {c:.4g}; calibrate, all px {a:.4g}"))
    d = np.abs(theta_k[ok] - theta_cf[ok])
    results["kernel_vs_curve_fit_median_abs_dln_k"] = float(np.median(d[:, 0]))
    results["kernel_vs_curve_fit_median_abs_dln_b"] = float(np.median(d[:, 2]))
    print(row("kernel vs curve_fit, median |d ln k|", results[
        "kernel_vs_curve_fit_median_abs_dln_k"], "", f"|d ln b| {np.median(d[:, 2]):.2g}, "
              f"|d dark| {np.median(d[:, 3]):.2g} DN"))
    results["equal_accuracy"] = bool(equal)
    results["figures"] = [
        figure(f"calibrate a {shape[1]} x {shape[0]} sensor ({EXPOSURES_MS.size} exposures)",
               t_cal, "s", baseline=per_px * npx,
               baseline_name=f"scipy curve_fit per pixel, extrapolated from {n_sample} px",
               ratio=results["speedup_vs_curve_fit"],
               target="<= 10 s and >= 500 x faster than curve_fit, equal accuracy",
               met=bool(t_cal <= 10.0 and results["speedup_vs_curve_fit"] >= 500 and equal),
               note="ratio = curve_fit CPU time (its thread) / calibrate wall time; equal "
                    f"accuracy: {'yes' if equal else 'NO'}")]
    print(f"  equal accuracy (every kernel median within 10 % of curve_fit's or better): "
          f"{'yes' if equal else 'NO'}; the sample fit reproduces calibrate's k to "
          f"{same:.1e} (float32 storage)")
    return {k: (float(v) if isinstance(v, (np.floating, np.integer)) else v)
            for k, v in results.items()}


if __name__ == "__main__":
    main()
