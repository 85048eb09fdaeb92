"""The simulated paper experiment, part 2: training flats, Table II through the shipped
pipeline stages, Fig. 6 spectra and the alpha-threshold trade-off.

Table II is computed by the same objects users run: for every training exposure a
``Pipeline([("dark", create("dark")), ("ffc", create("two_point_ffc", exposure_ms=...))])`` is
fitted on the training flats and darks and applied to each raw test frame, so a number of the
report certifies ``hsiffc correct`` and the Python API, not a parallel implementation.
"""

from __future__ import annotations

import warnings

import numpy as np

from ...flatfield.two_point import uniformity_per_band
from ...flatfield.uniformity import fixed_pattern_nonuniformity
from ...leakage.validity import alpha_table
from ...stages import Pipeline, create
from ...stages.refchecks import ReferenceWarning
from .config import GRID_MS, SPECTRA_MS, THRESHOLDS, select_longest, spectral_angle_deg

__all__ = ["ffc_improvement", "flatfield_pipeline", "spectra_data", "tile_spectra",
           "tradeoff", "training_stats"]


def training_stats(training, band_map, n_bands):
    """Per grid exposure and band: the flat's signal (DN above the dark, 10-frame means) and
    the single-frame SNR of the flat (mean signal / RMS temporal std over the 10 frames).

    Returns
    -------
    snr, signal_dn : (bands, len(GRID_MS)) arrays
    """
    means = training.step_means()
    snr = np.empty((n_bands, len(GRID_MS)))
    sig = np.empty((n_bands, len(GRID_MS)))
    for j, e in enumerate(GRID_MS):
        at = np.isclose(means["exposure_ms"], e)
        jl = np.flatnonzero(at & (means["kind"] == "light"))[0]
        jd = np.flatnonzero(at & (means["kind"] == "dark"))[0]
        flat, dark = means["data"][jl], means["data"][jd]
        frames = training.data[training.step == means["step"][jl]].astype(np.float64)
        var = frames.var(axis=0, ddof=1)
        for band in range(n_bands):
            m = band_map == band
            sig[band, j] = float((flat - dark)[m].mean())
            snr[band, j] = sig[band, j] / float(np.sqrt(var[m].mean()))
    return snr, sig


def flatfield_pipeline(exposure_ms: float) -> Pipeline:
    """The pipeline of Table II: master dark matched to the exposure, then two-point FFC
    (eq. 5, the paper's normalisation) trained on the flats at ``exposure_ms``.

    Stacks are averaged with the mean (the paper's 10-frame averages)."""
    return Pipeline([("dark", create("dark", average="mean")),
                     ("ffc", create("two_point_ffc", exposure_ms=float(exposure_ms),
                                    average="mean"))])


def ffc_improvement(training, tests, band_map, test_ms):
    """Improvement of eq. (6) in percentage points, ``U(raw test) - U(corrected)``, per test
    frame, band and training exposure: mean and standard error over the test frames.

    Parameters
    ----------
    training : list of Frame
        Flats (lamp A) and darks at every exposure of ``GRID_MS`` (darks at ``test_ms`` too).
    tests : list of Frame
        Raw test frames (lamp B) at ``test_ms``.
    band_map : (H, W) int array
    test_ms : float
        Exposure of the test frames (ms): its master dark is subtracted from them.

    Also the same with the raw test's non-uniformity taken after subtracting the dark at the test
    exposure, which removes the dark offset from eq. (6)'s denominator; and the fixed-pattern
    non-uniformity (EMVA 1288, :func:`hsiffc.flatfield.uniformity.fixed_pattern_nonuniformity`) of the
    test frames, raw (dark-subtracted) and corrected, which temporal noise does not blur.
    """
    darks_at_test = [f for f in training if f.kind == "dark" and np.isclose(f.exposure_ms, test_ms)]
    test_dark = np.mean([f.data for f in darks_at_test], axis=0)
    n_t, n_j = len(tests), len(GRID_MS)
    n_bands = int(np.max(band_map)) + 1
    imp = np.empty((n_t, n_bands, n_j))
    imp_ds = np.empty((n_t, n_bands, n_j))
    raw = np.stack([uniformity_per_band(t.data, band_map) for t in tests])  # (n_t, bands)
    raw_ds = np.stack([uniformity_per_band(t.data - test_dark, band_map) for t in tests])
    raw_stack = np.stack([t.data for t in tests])
    good_raw = np.all([t.dq == 0 for t in tests], axis=0)
    fpn_raw = fixed_pattern_nonuniformity(raw_stack, band_map, dark=test_dark, mask=good_raw)
    fpn = np.empty((n_bands, n_j))
    for j, e in enumerate(GRID_MS):
        train = [f for f in training if np.isclose(f.exposure_ms, e)]
        if not np.isclose(e, test_ms):
            train += darks_at_test
        with warnings.catch_warnings():  # every exposure of the grid on purpose, saturated
            warnings.simplefilter("ignore", ReferenceWarning)  # ones included: no campaign
            pipe = flatfield_pipeline(e).fit(train)
        outs = []
        for n, test in enumerate(tests):
            out = pipe.transform(test)
            outs.append(out)
            u = uniformity_per_band(out.data, band_map, dq=out.dq)
            imp[n, :, j] = raw[n] - u
            imp_ds[n, :, j] = raw_ds[n] - u
        good = good_raw & np.all([o.dq == 0 for o in outs], axis=0)
        fpn[:, j] = fixed_pattern_nonuniformity(np.stack([o.data for o in outs]), band_map,
                                                mask=good).fpn_percent
    sqn = np.sqrt(n_t)
    return {"mean": imp.mean(axis=0), "se": imp.std(axis=0, ddof=1) / sqn,
            "mean_dark_subtracted": imp_ds.mean(axis=0),
            "se_dark_subtracted": imp_ds.std(axis=0, ddof=1) / sqn,
            "raw_uniformity": raw.mean(axis=0),
            "raw_uniformity_dark_subtracted": raw_ds.mean(axis=0),
            "fpn_raw_percent": fpn_raw.fpn_percent, "fpn_percent": fpn,
            "test_dark": test_dark}


def tile_spectra(frame, band_map, n_bands):
    """(tiles, bands) spectra of a mosaic frame: each band's pixels in raster order line up
    tile by tile because every tile holds one pixel of every band."""
    cols = [np.asarray(frame)[band_map == band] for band in range(n_bands)]
    n = min(c.size for c in cols)
    return np.stack([c[:n] for c in cols], axis=1)


def spectra_data(sensor, cal, level_w_m2, threshold, seed):
    """Fig. 6: lamp B band-mean spectra at 11 exposures, their alpha and validity."""
    bm, nb = sensor.band_map, sensor.mosaic.n_bands
    sw = sensor.sweep(SPECTRA_MS, "lamp B", irradiance_w_m2=level_w_m2, n_frames=2, seed=seed)
    table = alpha_table(sw, cal)
    means = sw.step_means()
    truth = sw.meta["truth"]
    k_true = np.array([truth.k_dn_per_ms[bm == band].mean() for band in range(nb)])
    spectra, tile_angle = [], []
    tile_truth = tile_spectra(truth.k_dn_per_ms, bm, nb)
    for e in SPECTRA_MS:
        at = np.isclose(means["exposure_ms"], e)
        light = means["data"][at & (means["kind"] == "light")][0]
        dark = means["data"][at & (means["kind"] == "dark")][0]
        sig = light - dark
        spectra.append([sig[bm == band].mean() for band in range(nb)])
        # spectral correctness per tile: the first raw frame less the dark, against the tile's
        # true light-rate spectrum (noise at short exposures, leakage at long ones)
        first = sw.data[np.flatnonzero(np.isclose(sw.exposure_ms, e) & sw.is_light)[0]]
        tiles = tile_spectra(first.astype(np.float64) - dark, bm, nb)
        tile_angle.append(float(np.mean(spectral_angle_deg(tiles, tile_truth))))
    spectra = np.asarray(spectra)
    norm = spectra / spectra.max(axis=1, keepdims=True)
    alpha = table.alpha  # (bands, 11)
    valid = np.all(alpha < threshold, axis=0)
    best = int(np.flatnonzero(valid)[-1]) if valid.any() else 0
    pair = spectral_angle_deg(norm[:, None, :], norm[None, :, :])
    iu = np.triu_indices(len(SPECTRA_MS), 1)
    vv = valid[iu[0]] & valid[iu[1]]
    iv = valid[iu[0]] != valid[iu[1]]
    ii = ~valid[iu[0]] & ~valid[iu[1]]
    pvals = pair[iu]
    return {"exposure_ms": np.asarray(SPECTRA_MS), "spectra_dn": spectra, "normalised": norm,
            "alpha_percent": alpha, "valid": valid, "best_index": best,
            "best_ms": float(SPECTRA_MS[best]),
            "first_invalid_ms": (float(np.asarray(SPECTRA_MS)[~valid].min())
                                 if (~valid).any() else None),
            "truth_spectrum": k_true, "truth_normalised": k_true / k_true.max(),
            "angle_to_best_deg": spectral_angle_deg(norm, norm[best]),
            "angle_to_truth_deg": spectral_angle_deg(norm, k_true),
            "tile_angle_to_truth_deg": np.asarray(tile_angle),
            "pair_angle_deg": pair,
            "mean_angle_valid_pairs_deg": float(pvals[vv].mean()) if vv.any() else None,
            "mean_angle_invalid_valid_pairs_deg": float(pvals[iv].mean()) if iv.any() else None,
            "mean_angle_invalid_pairs_deg": float(pvals[ii].mean()) if ii.any() else None,
            "wavelengths_nm": list(sensor.mosaic.wavelengths_nm or []),
            "level_w_m2": level_w_m2}


def tradeoff(alpha_grid, snr_grid, imp_grid, spec, weights):
    """Criteria against the alpha threshold and the threshold the user's weights choose."""
    nb = alpha_grid.shape[0]
    grid = np.asarray(GRID_MS)
    sp_ms = spec["exposure_ms"]
    sp_alpha_max = spec["alpha_percent"].max(axis=0)
    rows = []
    for thr in THRESHOLDS:
        sel, fallback = [], False
        for band in range(nb):
            j = select_longest(alpha_grid[band], grid, thr)
            if j is None:
                j, fallback = 0, True
            sel.append(j)
        sel = np.asarray(sel)
        js = select_longest(sp_alpha_max, sp_ms, thr)
        if js is None:
            js, fallback = 0, True
        snr = snr_grid[np.arange(nb), sel]
        rows.append({"threshold_percent": thr,
                     "selected_ms": grid[sel],
                     "snr_db": float(np.mean(20 * np.log10(snr))),
                     "ru_pp": float(np.mean(imp_grid[np.arange(nb), sel])),
                     "spectral_ms": float(sp_ms[js]),
                     "sc_tile_deg": float(spec["tile_angle_to_truth_deg"][js]),
                     "sc_band_mean_deg": float(spec["angle_to_truth_deg"][js]),
                     "fallback": fallback})

    def norm(v, higher_better=True):
        v = np.asarray(v, np.float64)
        span = v.max() - v.min()
        s = (v - v.min()) / span if span > 0 else np.ones_like(v)
        return s if higher_better else 1.0 - s

    s_snr = norm([r["snr_db"] for r in rows])
    s_ru = norm([r["ru_pp"] for r in rows])
    s_sc = norm([r["sc_tile_deg"] for r in rows], higher_better=False)

    def choose(w):
        total = (w["snr"] * s_snr + w["sc"] * s_sc + w["ru"] * s_ru) / sum(w.values())
        # the first maximum: of equally good thresholds, the lowest (the least leakage)
        j = int(np.flatnonzero(total >= total.max() - 1e-12)[0])
        return j, total

    j, total = choose(weights)
    for i, r in enumerate(rows):
        r.update(score_snr=float(s_snr[i]), score_sc=float(s_sc[i]), score_ru=float(s_ru[i]),
                 score_total=float(total[i]))
    presets = {}
    for name, w in (("equal", {"snr": 1, "sc": 1, "ru": 1}),
                    ("snr only", {"snr": 1, "sc": 0, "ru": 0}),
                    ("sc only", {"snr": 0, "sc": 1, "ru": 0}),
                    ("ru only", {"snr": 0, "sc": 0, "ru": 1}),
                    ("snr=2,sc=1,ru=1", {"snr": 2, "sc": 1, "ru": 1}),
                    ("snr=1,sc=2,ru=1", {"snr": 1, "sc": 2, "ru": 1})):
        jp, _ = choose(w)
        presets[name] = {"weights": w, "threshold_percent": THRESHOLDS[jp],
                         "selected_ms": rows[jp]["selected_ms"],
                         "spectral_ms": rows[jp]["spectral_ms"]}
    return {"rows": rows, "weights": weights, "chosen_index": j,
            "chosen_threshold_percent": THRESHOLDS[j], "chosen": rows[j], "presets": presets}


