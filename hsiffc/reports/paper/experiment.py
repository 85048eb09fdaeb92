"""The paper's section V on the simulated 8-band sensor: every number of the report, no files."""

from __future__ import annotations

import time

import numpy as np

from ...calibrate import calibrate
from ...data.frame import Frame
from ...simulate import PAPER_LIGHT_W_M2, MosaicSensor
from ...leakage.validity import AlphaTable, alpha_table
from .config import (CANDIDATES_MS, FIG4_LEVELS, GRID_MS, N_TEST_FRAMES, N_TRAIN_FRAMES,
                     SPECTRA_PEAK_K, TEST_MS, THRESHOLD_PERCENT, index_of, parse_weights)
from .flatfield import ffc_improvement, spectra_data, tradeoff, training_stats
from .responses import calibration_sweep, fig2_data, fig4_data, fig5_data, pick_pixel

__all__ = ["simulate_paper_experiment"]


def simulate_paper_experiment(*, seed=0, shape=(128, 128), threshold=THRESHOLD_PERCENT,
                              weights=None, n_test_frames=N_TEST_FRAMES) -> dict:
    """Run the paper's section V on the simulated sensor; every number, no files.

    Parameters
    ----------
    seed : int
        Seeds the sensor's fixed pattern and every capture.
    shape : (H, W)
        Sensor size in pixels, a multiple of the 2 x 4 mosaic tile.
    threshold : float
        alpha threshold (percent) of Tables I and II and Fig. 6.
    weights : dict or str, optional
        Trade-off weights (:func:`~hsiffc.reports.paper.config.parse_weights`).
    n_test_frames : int
        Independent raw test frames of Table II.

    Returns
    -------
    dict
        ``fig2``, ``fig4``, ``fig5``, ``table1`` (an AlphaTable), ``table2``, ``grid``,
        ``fig6``, ``tradeoff``, ``timing`` and the settings.
    """
    shape = (int(shape[0]), int(shape[1]))
    if shape[0] % 2 or shape[1] % 4 or min(shape) < 8:
        raise ValueError(f"shape must be a multiple of the 2 x 4 mosaic tile and >= 8, got {shape}")
    weights = parse_weights(weights)
    timing = {}
    t0 = time.perf_counter()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1288]))
    sensor = MosaicSensor(shape, seed=int(seed))
    bm, nb = sensor.band_map, sensor.mosaic.n_bands
    light = dict(PAPER_LIGHT_W_M2)

    cal_sweep = calibration_sweep(sensor, light["training"], rng)
    cal = calibrate(cal_sweep, method="paper")
    timing["calibration_s"] = time.perf_counter() - t0
    pix = pick_pixel(cal, bm, band=0)
    fig4 = fig4_data(cal_sweep, cal, pix)
    del cal_sweep

    t1 = time.perf_counter()
    fig5 = fig5_data(sensor, cal, pix, light["fig5"], int(rng.integers(2 ** 62)))
    fig2 = fig2_data(fig5)
    timing["fig5_fig2_s"] = time.perf_counter() - t1

    t1 = time.perf_counter()
    training = sensor.sweep(GRID_MS, "lamp A", irradiance_w_m2=light["training"],
                            n_frames=N_TRAIN_FRAMES, seed=int(rng.integers(2 ** 62)))
    grid_table = alpha_table(training, cal)
    cols = [index_of(grid_table.exposures_ms, e) for e in CANDIDATES_MS]
    table1 = AlphaTable(np.asarray(CANDIDATES_MS), grid_table.alpha[:, cols],
                        grid_table.wavelengths_nm, grid_table.statistic,
                        grid_table.method).select(threshold)
    snr_grid, sig_grid = training_stats(training, bm, nb)
    training = Frame.list_from_sweep(training)
    raw_tests = sensor.capture(TEST_MS, "lamp B", irradiance_w_m2=light["test"],
                               n_frames=n_test_frames, seed=int(rng.integers(2 ** 62))).frames
    tests = [Frame.from_raw(f, exposure_ms=TEST_MS, bit_depth=sensor.params.bit_depth,
                            mosaic=sensor.mosaic, illumination="lamp B") for f in raw_tests]
    ffc = ffc_improvement(training, tests, bm, TEST_MS)
    del training
    imp_grid, se_grid = ffc["mean"], ffc["se"]
    test_stack = raw_tests.astype(np.float64)
    test_mean = np.array([test_stack[:, bm == band].mean() for band in range(nb)])
    test_signal = np.array([(test_stack.mean(axis=0) - ffc["test_dark"])[bm == band].mean()
                            for band in range(nb)])
    timing["tables_s"] = time.perf_counter() - t1

    imp, se = imp_grid[:, cols], se_grid[:, cols]
    best = imp.argmax(axis=1)
    sel_idx = np.array([np.nan if np.isnan(s) else index_of(CANDIDATES_MS, s)
                        for s in table1.selected_ms])
    table2 = {"exposures_ms": np.asarray(CANDIDATES_MS), "improvement_pp": imp, "se_pp": se,
              "best_ms": np.asarray(CANDIDATES_MS)[best], "selected_ms": table1.selected_ms,
              "improvement_dark_subtracted_pp": ffc["mean_dark_subtracted"][:, cols],
              "se_dark_subtracted_pp": ffc["se_dark_subtracted"][:, cols],
              "raw_uniformity_percent": ffc["raw_uniformity"],
              "raw_uniformity_dark_subtracted_percent": ffc["raw_uniformity_dark_subtracted"],
              "test_mean_dn": test_mean, "test_signal_dn": test_signal,
              "fpn_raw_percent": ffc["fpn_raw_percent"],
              "fpn_percent": ffc["fpn_percent"][:, cols],
              "n_test_frames": int(n_test_frames)}
    within = []
    for band in range(nb):
        if np.isnan(sel_idx[band]):
            within.append(False)
            continue
        j = int(sel_idx[band])
        d_se = np.hypot(se[band, j], se[band, best[band]])
        within.append(bool(imp[band, j] >= imp[band, best[band]] - 2 * d_se))
    table2["selected_within_2se_of_best"] = np.asarray(within)

    t1 = time.perf_counter()
    spec_level = light["test"] * SPECTRA_PEAK_K / 25.0
    spec = spectra_data(sensor, cal, spec_level, threshold, int(rng.integers(2 ** 62)))
    timing["spectra_s"] = time.perf_counter() - t1
    trade = tradeoff(grid_table.alpha, snr_grid, imp_grid, spec, weights)
    timing["simulated_total_s"] = time.perf_counter() - t0
    return {"seed": int(seed), "shape": list(shape), "threshold_percent": float(threshold),
            "light_w_m2": {**light, "spectra": spec_level},
            "calibration": {"method": "paper", "n_illuminations": len(FIG4_LEVELS),
                            "fraction_flag_free": float(np.mean(np.asarray(cal["flags"]) == 0))},
            "fig4": fig4, "fig5": fig5, "fig2": fig2,
            "table1": table1, "grid": {"exposures_ms": np.asarray(GRID_MS),
                                       "alpha_percent": grid_table.alpha, "snr": snr_grid,
                                       "signal_dn": sig_grid, "improvement_pp": imp_grid,
                                       "se_pp": se_grid},
            "table2": table2, "fig6": spec, "tradeoff": trade, "timing": timing,
            "wavelengths_nm": list(sensor.mosaic.wavelengths_nm or [])}


