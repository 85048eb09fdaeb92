"""The paper's section V as a report: Tables I and II, Figures 2, 4, 5 and 6, the alpha-threshold
trade-off of its future work, and the same flat-field questions on the real EMVA 1288 sweep.

:func:`run_paper_report` runs everything on the simulated 8-band sensor of
:mod:`hsiffc.simulate` and writes ``report.md`` (tables with the paper's values beside ours),
PNG figures and one CSV per table or figure into a folder. Every file is written atomically.

The experiment, as in the paper (Liu et al., section V):

* lamp A (2900 K blackbody, colour-science) for training, lamp B (2200 K) for testing, uniform
  light (an integrating sphere: no vignetting), every training image the mean of 10 frames;
* calibration by the paper's procedure (section III.C): exposure sweeps into dynamic
  saturation under 16 levels of lamp A, k from the linear part, a and b from the 16 (saturated
  level, k) pairs of every pixel (Fig. 4);
* Fig. 5 / Fig. 2: one pixel of band 1 under lamp B at the light of Fig. 5 (k about 2 DN/ms),
  10 frames per exposure up to 1000 ms, against the leakage model (eq. 3) and the linear model
  (eq. 1), with k estimated from the linear part of that pixel's own data;
* Table I: alpha (eq. 4, k ~ signal / exposure, median over a band's pixels) of the 10-frame
  training images at 6.45-32.25 ms, the longest under 12 % selected;
* Table II: improvement of eq. (6) by two-point FFC (eq. 5) trained at each candidate, on raw
  test frames at 16.125 ms under lamp B (several independent frames: mean and standard error);
* Fig. 6: lamp B spectra (band means of the dark-subtracted frame, no flat-field) at the 11
  exposures 3.225-35.475 ms, normalised by their maximum; a spectrum is invalid when any band's
  alpha exceeds the threshold;
* the trade-off: for every threshold 1-100 %, SNR of the selected training flats, uniformity
  improvement (Table II metric) and spectral correctness, normalised to [0, 1] and combined with
  user weights.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from .._json import json_safe
from .. import __version__, model
from ..atomic import atomic_path, atomic_write_text

__all__ = ["CANDIDATES_MS", "PAPER_VALUES", "TEST_MS", "THRESHOLD_PERCENT", "emva_ffc_levels",
           "find_emva_dir", "parse_weights", "run_paper_report", "simulate_paper_experiment",
           "spectral_angle_deg"]

log = logging.getLogger(__name__)

STEP_MS = 3.225  # the paper's exposures are multiples of 3.225 ms
CANDIDATES_MS = (6.45, 12.9, 19.35, 25.8, 32.25)  # Table I / II
GRID_MS = tuple(round(STEP_MS * n, 4) for n in range(1, 13))  # training grid 3.225-38.7 ms
SPECTRA_MS = tuple(round(STEP_MS * n, 4) for n in range(1, 12))  # Fig. 6: 11 exposures
TEST_MS = 16.125
THRESHOLD_PERCENT = 12.0
N_TRAIN_FRAMES = 10
N_TEST_FRAMES = 8
FIG4_LEVELS = tuple(np.geomspace(0.03, 0.8, 16))  # lamp A, relative to the training light
FIG5_EXPOSURES_MS = tuple(float(t) for t in np.arange(20.0, 1000.1, 20.0))
FIG2_LAST_MS = 700.0
SPECTRA_PEAK_K = 30.0  # Fig. 6 light: brightest band at the training light rate of band 1
THRESHOLDS = tuple(float(t) for t in range(1, 101))
WEIGHT_KEYS = ("snr", "sc", "ru")
EMVA_N_CANDIDATES = 11
EMVA_MIN_SIGNAL_DN = 10.0
EMVA_MAX_CLIPPED = 0.01

#: Numbers the paper gives (percent for alpha and Table II; DN, DN/ms, ms elsewhere).
PAPER_VALUES = {
    "table1_alpha_percent": {1: [0.04, 0.11, 0.47, 5.15, 37.15],
                             2: [0.01, 0.13, 10.40, 12.92, 66.97],
                             3: [0.01, 0.09, 1.39, 17.93, 76.44]},
    "table2_improvement_pp": {1: [0.03, 0.14, 0.16, 0.17, -0.20],
                              2: [0.03, 0.15, 0.18, 0.13, -0.90],
                              3: [0.04, 0.11, 0.16, 0.03, -1.16]},
    "fig2": {"pentagram_alpha_percent": 0.12, "circle_alpha_percent": 74.63,
             "triangle_alpha_percent": 173.5, "triangle_ms": 700.0, "saturated_near_ms": 600.0},
    "fig5": {"k_dn_per_ms": 2.0, "saturation_dn": 800.0, "leak_rate_at_800_dn_per_ms": 2.0,
             "leakage_visible_after_ms": 430.0},
    "fig4_n_illuminations": 16,
    "fig6": {"n_exposures": 11, "deformed_above_ms": 29.0},
}


# -- small helpers ---------------------------------------------------------------------------

def parse_weights(weights=None) -> dict:
    """User weights of the trade-off criteria as a dict ``{"snr", "sc", "ru"}``.

    Accepts None (all 1), a dict, or text like ``"snr=1,sc=2,ru=0"``. Criteria not named get
    weight 1. Weights must be finite and >= 0, and not all 0.
    """
    out = {k: 1.0 for k in WEIGHT_KEYS}
    if weights is None:
        return out
    if isinstance(weights, str):
        items = {}
        for part in (p.strip() for p in weights.split(",")):
            if not part:
                continue
            if "=" not in part:
                raise ValueError(f"weights must look like 'snr=1,sc=1,ru=1'; got {part!r}")
            key, val = (s.strip() for s in part.split("=", 1))
            try:
                items[key.lower()] = float(val)
            except ValueError:
                raise ValueError(f"weight {key!r} must be a number, got {val!r}") from None
        weights = items
    for key, val in dict(weights).items():
        if key not in WEIGHT_KEYS:
            raise ValueError(f"unknown weight {key!r}; use {', '.join(WEIGHT_KEYS)} (SNR, "
                             "spectral correctness, response uniformity)")
        val = float(val)
        if not np.isfinite(val) or val < 0:
            raise ValueError(f"weight {key}={val} must be finite and >= 0")
        out[key] = val
    if sum(out.values()) <= 0:
        raise ValueError("at least one weight must be > 0")
    return out


def find_emva_dir(start=None) -> Path | None:
    """The real EMVA 1288 sweep folder (``shared/data/emva1288-cmos8-roi``), or None.

    Looked for under ``$HSIFFC_SHARED_DATA``, beside the repository (``../shared/data``) and
    relative to the working directory (``../shared/data``, ``shared/data``).
    """
    name = "emva1288-cmos8-roi"
    roots = []
    if os.environ.get("HSIFFC_SHARED_DATA"):
        roots.append(Path(os.environ["HSIFFC_SHARED_DATA"]))
    repo = Path(__file__).resolve().parents[2]
    cwd = Path(start) if start is not None else Path.cwd()
    roots += [repo.parent / "shared" / "data", cwd.parent / "shared" / "data",
              cwd / "shared" / "data"]
    for root in roots:
        cand = root / name
        if (cand / "EMVA1288_Data.txt").exists():
            return cand
    return None


def spectral_angle_deg(x, y) -> np.ndarray:
    """Angle (degrees) between spectra along the last axis (0 = same shape, any scale)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    num = (x * y).sum(axis=-1)
    den = np.sqrt((x * x).sum(axis=-1) * (y * y).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.clip(num / den, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def _idx(values, target) -> int:
    values = np.asarray(values, np.float64)
    j = int(np.argmin(np.abs(values - target)))
    if not np.isclose(values[j], target, rtol=0, atol=1e-6):
        raise ValueError(f"{target} not among {values.tolist()}")
    return j


def _select_longest(alpha_row, exposures, threshold):
    """Index of the longest exposure with alpha under the threshold (None if none)."""
    ok = np.flatnonzero(np.asarray(alpha_row) < threshold)
    if not ok.size:
        return None
    return int(ok[np.argmax(np.asarray(exposures)[ok])])


def _fmt(v, nd=2, signed=False) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "n/a"
    return f"{v:+.{nd}f}" if signed else f"{v:.{nd}f}"


def _csv_text(header, rows) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([_csv_cell(v) for v in r])
    return buf.getvalue()


def _csv_cell(v):
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    if isinstance(v, np.integer):
        return int(v)
    return v


def _savefig(fig, path, dpi=90):
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)


# -- the simulated experiment ----------------------------------------------------------------

def _calibration_sweep(sensor, train_w_m2, rng):
    """Exposure sweeps into dynamic saturation under 16 levels of lamp A (Fig. 4's data).

    Exposures per level: 8 from 1 ms up to the time the nominal sensor (band-1 k = 30 DN/ms at
    the training light, saturation 800 DN at 2 DN/ms, b 0.0125/DN) needs to reach its dynamic
    saturation level linearly, and 4 at 1.6-3.4 times that, deep in the plateau.
    """
    from ..sweep import Sweep

    p = sensor.params
    parts = []
    for i, level in enumerate(FIG4_LEVELS):
        k = 30.0 * level
        y_sat = p.leak_ref_dn + np.log(k / p.leak_rate_dn_per_ms) / p.leak_b_per_dn
        t_lin = (y_sat - p.dark_level_dn) / k
        ts = np.concatenate([np.geomspace(1.0, t_lin, 8), t_lin * np.array([1.6, 2.2, 2.8, 3.4])])
        parts.append(sensor.sweep(np.round(ts, 3), "lamp A", irradiance_w_m2=train_w_m2 * level,
                                  n_frames=2, darks=(i == 0), seed=int(rng.integers(2 ** 62)),
                                  label=f"lamp A x{level:.4f}"))
    cat = {f: np.concatenate([getattr(q, f) for q in parts])
           for f in ("data", "exposure_ms", "kind", "illumination")}
    return Sweep(cat["data"], cat["exposure_ms"], cat["kind"], p.bit_depth,
                 illumination=cat["illumination"], mosaic=sensor.mosaic, source="simulated",
                 meta={"truth": parts[0].meta["truth"]})


def _pick_pixel(cal, band_map, band=0):
    """A typical, fully constrained pixel of ``band``: the one closest to the band's median
    ln a and b (in robust-sigma units) among those with every saturation pair usable."""
    ln_a = np.log(np.asarray(cal.a, np.float64))
    b = np.asarray(cal.b, np.float64)
    mask = (band_map == band) & (np.asarray(cal["flags"]) == 0)
    if "n_saturation_pairs" in cal.arrays:
        npairs = np.asarray(cal["n_saturation_pairs"])
        mask &= npairs == npairs[mask].max()
    dist = np.zeros(b.shape)
    for v in (ln_a, b):
        med = np.median(v[mask])
        mad = 1.4826 * np.median(np.abs(v[mask] - med)) or 1.0
        dist += ((v - med) / mad) ** 2
    dist[~mask] = np.inf
    r, c = np.unravel_index(int(np.argmin(dist)), b.shape)
    return int(r), int(c)


def _fig4_data(cal_sweep, cal, pix):
    """(saturated level, k) pairs of one pixel for the 16 illuminations, and the fit."""
    means = cal_sweep.step_means()
    light = means["kind"] == "light"
    labels = list(dict.fromkeys(means["illumination"][light].tolist()))
    r, c = pix
    rows = []
    for i, lab in enumerate(labels):
        sel = light & (means["illumination"] == lab)
        order = np.argsort(means["exposure_ms"][sel])
        y = means["data"][sel][order][:, r, c]
        rows.append({"illumination": lab, "relative_light": FIG4_LEVELS[i],
                     "k_dn_per_ms": float(cal[f"k_illum{i}_dn_per_ms"][r, c]),
                     "saturated_dn": float(y[-2:].mean()),
                     "plateau_step_dn": float(y[-1] - y[-2])})
    truth = cal_sweep.meta["truth"]
    ln_a_err = np.log(np.asarray(cal.a, np.float64) / truth.a_dn_per_ms)
    a, b = float(cal.a[r, c]), float(cal.b[r, c])
    a_t, b_t = float(truth.a_dn_per_ms[r, c]), float(truth.b_per_dn[r, c])
    return {"pixel": [r, c], "pairs": rows, "a_dn_per_ms": a, "b_per_dn": b,
            "a_true_dn_per_ms": a_t, "b_true_per_dn": b_t,
            "leak_at_800_dn_per_ms": a * np.exp(800 * b),
            "leak_at_800_true_dn_per_ms": a_t * np.exp(800 * b_t),
            "sensor_median_abs_rel_error_b": float(np.median(np.abs(cal.b / truth.b_per_dn - 1))),
            "sensor_median_abs_error_ln_a": float(np.median(np.abs(ln_a_err))),
            "n_illuminations": len(rows)}


def _fig5_data(sensor, cal, pix, fig5_w_m2, seed):
    """One pixel under lamp B at the light of Fig. 5: measured (10-frame mean) against the
    leakage model and the linear model, k from the pixel's own linear part."""
    r, c = pix
    ts = np.asarray(FIG5_EXPOSURES_MS)
    sw = sensor.sweep(ts, "lamp B", irradiance_w_m2=fig5_w_m2, n_frames=N_TRAIN_FRAMES,
                      darks=False, seed=seed)
    y = sw.data[:, r, c].astype(np.float64).reshape(ts.size, N_TRAIN_FRAMES)
    mean, se = y.mean(axis=1), y.std(axis=1, ddof=1) / np.sqrt(N_TRAIN_FRAMES)
    a, b, dark = (float(np.asarray(v, np.float64)[r, c]) for v in (cal.a, cal.b, cal.dark))
    # the paper's rule for k: avoid saturated data. Samples with alpha (eq. 4, k ~ signal/t)
    # under 5 % are the linear part; k is the slope through the dark level
    alpha_sig = model.leakage_percentage_paper(mean, ts, a, b, dark)
    use = alpha_sig < 5.0
    k = float(np.sum(ts[use] * (mean[use] - dark)) / np.sum(ts[use] ** 2))
    t_fine = np.linspace(0.0, ts.max(), 501)
    leak = model.response(t_fine, k, a, b, dark)
    lin = model.linear_response(t_fine, k, dark)
    leak_s = model.response(ts, k, a, b, dark)
    lin_s = model.linear_response(ts, k, dark)
    dev = lin_s - mean
    over = dev > 3 * se
    visible = next((float(ts[i]) for i in range(ts.size) if over[i:].all()), None)
    rel = dev / np.maximum(mean - dark, 1e-9)
    visible5 = next((float(ts[i]) for i in range(ts.size) if (rel[i:] > 0.05).all()), None)
    y_sat = float(model.dynamic_saturation_level(k, a, b))
    frac = (leak - dark) / (y_sat - dark)
    t99 = float(t_fine[np.argmax(frac >= 0.99)]) if (frac >= 0.99).any() else None
    early = ts <= PAPER_VALUES["fig5"]["leakage_visible_after_ms"]
    truth = sw.meta["truth"]
    return {
        "pixel": [r, c], "exposure_ms": ts, "measured_dn": mean, "measured_se_dn": se,
        "frames": y, "leakage_model_dn": leak_s, "linear_model_dn": lin_s,
        "t_fine_ms": t_fine, "leakage_fine_dn": leak, "linear_fine_dn": lin,
        "k_dn_per_ms": k, "k_true_dn_per_ms": float(truth.k_total_dn_per_ms[r, c]),
        "band1_median_k_true": float(np.median(truth.k_dn_per_ms[sensor.band_map == 0])),
        "n_linear_samples": int(use.sum()), "a_dn_per_ms": a, "b_per_dn": b, "dark_dn": dark,
        "dynamic_saturation_dn": y_sat,
        "measured_plateau_dn": float(mean[-5:].mean()),
        "leak_at_800_dn_per_ms": a * np.exp(800 * b),
        "leakage_visible_after_ms": visible,
        "linear_5pct_high_after_ms": visible5,
        "t_99pct_saturation_ms": t99,
        "rms_leakage_dn": float(np.sqrt(np.mean((leak_s - mean) ** 2))),
        "rms_linear_dn": float(np.sqrt(np.mean((lin_s - mean) ** 2))),
        "rms_leakage_early_dn": float(np.sqrt(np.mean((leak_s - mean)[early] ** 2))),
        "rms_linear_early_dn": float(np.sqrt(np.mean((lin_s - mean)[early] ** 2))),
        "rms_leakage_late_dn": float(np.sqrt(np.mean((leak_s - mean)[~early] ** 2))),
        "rms_linear_late_dn": float(np.sqrt(np.mean((lin_s - mean)[~early] ** 2))),
        "alpha_paper_raw_percent": model.leakage_percentage_paper(mean, ts, a, b, 0.0),
        "alpha_signal_percent": alpha_sig,
    }


def _fig2_data(f5):
    """Fig. 2: the Fig. 5 pixel up to 700 ms with points tagged by alpha (the paper's k ~ Y/t)."""
    ts = f5["exposure_ms"]
    keep = ts <= FIG2_LAST_MS + 1e-9
    alpha = f5["alpha_paper_raw_percent"][keep]
    alpha_sig = f5["alpha_signal_percent"][keep]
    la = np.log(np.where(np.isfinite(alpha) & (alpha > 0), alpha, np.nan))
    pv = PAPER_VALUES["fig2"]
    j_tri = int(np.flatnonzero(keep)[-1])
    j_pent = int(np.nanargmin(np.abs(la - np.log(pv["pentagram_alpha_percent"]))))
    before = np.where(np.arange(la.size) < j_tri, la, np.nan)
    j_circ = int(np.nanargmin(np.abs(before - np.log(pv["circle_alpha_percent"]))))
    tags = {}
    for name, j in (("pentagram", j_pent), ("circle", j_circ), ("triangle", j_tri)):
        y = float(f5["measured_dn"][j])
        tags[name] = {"exposure_ms": float(ts[j]), "response_dn": y,
                      "alpha_percent": float(alpha[j]), "alpha_signal_percent": float(alpha_sig[j]),
                      "apparent_k_dn_per_ms": (y - f5["dark_dn"]) / float(ts[j]),
                      "paper_alpha_percent": pv[f"{name}_alpha_percent"]}
    return {"exposure_ms": ts[keep], "measured_dn": f5["measured_dn"][keep],
            "alpha_percent": alpha, "alpha_signal_percent": alpha_sig, "tags": tags,
            "dark_dn": f5["dark_dn"], "t_99pct_saturation_ms": f5["t_99pct_saturation_ms"]}


def _training_stats(training, band_map, n_bands):
    """Per grid exposure: 10-frame flat and dark means, and per band the single-frame SNR of
    the flat (mean signal / RMS temporal std over the 10 frames)."""
    means = training.step_means()
    flats, darks = [], []
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
        flats.append(flat)
        darks.append(dark)
    return np.stack(flats), np.stack(darks), snr, sig


def _ffc_improvement(flats, darks, tests, band_map, test_dark):
    """Improvement of eq. (6) in percentage points, ``U(raw test) - U(corrected)``, per test
    frame, band and training exposure: mean and standard error over the test frames.

    Also the same with the raw test's non-uniformity taken after subtracting ``test_dark`` (the
    dark at the test exposure), which removes the dark offset from eq. (6)'s denominator.
    """
    from ..ffc import two_point_correct, uniformity_per_band

    n_t, n_j = tests.shape[0], flats.shape[0]
    n_bands = int(np.max(band_map)) + 1
    imp = np.empty((n_t, n_bands, n_j))
    imp_ds = np.empty((n_t, n_bands, n_j))
    raw = np.stack([uniformity_per_band(t, band_map) for t in tests])  # (n_t, bands)
    raw_ds = np.stack([uniformity_per_band(t - test_dark, band_map) for t in tests])
    for j in range(n_j):
        for n in range(n_t):
            corr, dq = two_point_correct(tests[n], darks[j], flats[j], band_map=band_map)
            u = uniformity_per_band(corr, band_map, dq=dq)
            imp[n, :, j] = raw[n] - u
            imp_ds[n, :, j] = raw_ds[n] - u
    sqn = np.sqrt(n_t)
    return {"mean": imp.mean(axis=0), "se": imp.std(axis=0, ddof=1) / sqn,
            "mean_dark_subtracted": imp_ds.mean(axis=0),
            "se_dark_subtracted": imp_ds.std(axis=0, ddof=1) / sqn,
            "raw_uniformity": raw.mean(axis=0),
            "raw_uniformity_dark_subtracted": raw_ds.mean(axis=0)}


def _tile_spectra(frame, band_map, n_bands):
    """(tiles, bands) spectra of a mosaic frame: each band's pixels in raster order line up
    tile by tile because every tile holds one pixel of every band."""
    cols = [np.asarray(frame)[band_map == band] for band in range(n_bands)]
    n = min(c.size for c in cols)
    return np.stack([c[:n] for c in cols], axis=1)


def _spectra_data(sensor, cal, level_w_m2, threshold, seed):
    """Fig. 6: lamp B band-mean spectra at 11 exposures, their alpha and validity."""
    from ..validity import alpha_table

    bm, nb = sensor.band_map, sensor.mosaic.n_bands
    sw = sensor.sweep(SPECTRA_MS, "lamp B", irradiance_w_m2=level_w_m2, n_frames=2, seed=seed)
    table = alpha_table(sw, cal)
    means = sw.step_means()
    truth = sw.meta["truth"]
    k_true = np.array([truth.k_dn_per_ms[bm == band].mean() for band in range(nb)])
    spectra, tile_angle = [], []
    tile_truth = _tile_spectra(truth.k_dn_per_ms, bm, nb)
    for e in SPECTRA_MS:
        at = np.isclose(means["exposure_ms"], e)
        light = means["data"][at & (means["kind"] == "light")][0]
        dark = means["data"][at & (means["kind"] == "dark")][0]
        sig = light - dark
        spectra.append([sig[bm == band].mean() for band in range(nb)])
        # spectral correctness per tile: the first raw frame less the dark, against the tile's
        # true light-rate spectrum (noise at short exposures, leakage at long ones)
        first = sw.data[np.flatnonzero(np.isclose(sw.exposure_ms, e) & sw.is_light)[0]]
        tiles = _tile_spectra(first.astype(np.float64) - dark, bm, nb)
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


def _tradeoff(alpha_grid, snr_grid, imp_grid, spec, weights):
    """Criteria against the alpha threshold and the threshold the user's weights choose."""
    nb = alpha_grid.shape[0]
    grid = np.asarray(GRID_MS)
    sp_ms = spec["exposure_ms"]
    sp_alpha_max = spec["alpha_percent"].max(axis=0)
    rows = []
    for thr in THRESHOLDS:
        sel, fallback = [], False
        for band in range(nb):
            j = _select_longest(alpha_grid[band], grid, thr)
            if j is None:
                j, fallback = 0, True
            sel.append(j)
        sel = np.asarray(sel)
        js = _select_longest(sp_alpha_max, sp_ms, thr)
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


def simulate_paper_experiment(*, seed=0, shape=(128, 128), threshold=THRESHOLD_PERCENT,
                              weights=None, n_test_frames=N_TEST_FRAMES) -> dict:
    """Run the paper's section V on the simulated sensor; returns every number (no files)."""
    from ..calibrate import calibrate
    from ..simulate import PAPER_LIGHT_W_M2, MosaicSensor
    from ..validity import AlphaTable, alpha_table

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

    cal_sweep = _calibration_sweep(sensor, light["training"], rng)
    cal = calibrate(cal_sweep, method="paper")
    timing["calibration_s"] = time.perf_counter() - t0
    pix = _pick_pixel(cal, bm, band=0)
    fig4 = _fig4_data(cal_sweep, cal, pix)
    del cal_sweep

    t1 = time.perf_counter()
    fig5 = _fig5_data(sensor, cal, pix, light["fig5"], int(rng.integers(2 ** 62)))
    fig2 = _fig2_data(fig5)
    timing["fig5_fig2_s"] = time.perf_counter() - t1

    t1 = time.perf_counter()
    training = sensor.sweep(GRID_MS, "lamp A", irradiance_w_m2=light["training"],
                            n_frames=N_TRAIN_FRAMES, seed=int(rng.integers(2 ** 62)))
    grid_table = alpha_table(training, cal)
    cols = [_idx(grid_table.exposures_ms, e) for e in CANDIDATES_MS]
    table1 = AlphaTable(np.asarray(CANDIDATES_MS), grid_table.alpha[:, cols],
                        grid_table.wavelengths_nm, grid_table.statistic,
                        grid_table.method).select(threshold)
    flats, darks, snr_grid, sig_grid = _training_stats(training, bm, nb)
    del training
    tests = sensor.capture(TEST_MS, "lamp B", irradiance_w_m2=light["test"],
                           n_frames=n_test_frames,
                           seed=int(rng.integers(2 ** 62))).frames.astype(np.float64)
    test_dark = darks[_idx(GRID_MS, TEST_MS)]
    ffc = _ffc_improvement(flats, darks, tests, bm, test_dark)
    imp_grid, se_grid = ffc["mean"], ffc["se"]
    test_mean = np.array([tests[:, bm == band].mean() for band in range(nb)])
    test_signal = np.array([(tests.mean(axis=0) - test_dark)[bm == band].mean()
                            for band in range(nb)])
    timing["tables_s"] = time.perf_counter() - t1

    imp, se = imp_grid[:, cols], se_grid[:, cols]
    best = imp.argmax(axis=1)
    sel_idx = np.array([np.nan if np.isnan(s) else _idx(CANDIDATES_MS, s)
                        for s in table1.selected_ms])
    table2 = {"exposures_ms": np.asarray(CANDIDATES_MS), "improvement_pp": imp, "se_pp": se,
              "best_ms": np.asarray(CANDIDATES_MS)[best], "selected_ms": table1.selected_ms,
              "improvement_dark_subtracted_pp": ffc["mean_dark_subtracted"][:, cols],
              "se_dark_subtracted_pp": ffc["se_dark_subtracted"][:, cols],
              "raw_uniformity_percent": ffc["raw_uniformity"],
              "raw_uniformity_dark_subtracted_percent": ffc["raw_uniformity_dark_subtracted"],
              "test_mean_dn": test_mean, "test_signal_dn": test_signal,
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
    spec = _spectra_data(sensor, cal, spec_level, threshold, int(rng.integers(2 ** 62)))
    timing["spectra_s"] = time.perf_counter() - t1
    trade = _tradeoff(grid_table.alpha, snr_grid, imp_grid, spec, weights)
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


# -- the real EMVA 1288 sweep ----------------------------------------------------------------

def emva_ffc_levels(emva_dir, *, threshold=THRESHOLD_PERCENT,
                    n_candidates=EMVA_N_CANDIDATES) -> dict:
    """Two-point FFC on the real EMVA 1288 sweep trained at candidate flat levels.

    Candidates: ``n_candidates`` light steps spread evenly over the sweep's usable light steps;
    flat = the step's 2-frame mean, dark = the 2-frame mean of the dark step at the same
    exposure. Each is tested at every other light step with at least ``EMVA_MIN_SIGNAL_DN`` of
    signal and at most ``EMVA_MAX_CLIPPED`` of its pixels clipped (eq. 6 on the corrected 2-frame
    test mean, clipped test pixels left out). alpha of each flat comes from a joint calibration
    of the sweep; alpha picks the brightest candidate whose median alpha stays under the
    threshold.
    """
    from ..calibrate import calibrate
    from ..ffc import two_point_correct, uniformity
    from ..io import read_emva1288
    from ..validity import alpha_map
    from .emva_leakage import sweep_steps_only

    t0 = time.perf_counter()
    sweep = sweep_steps_only(read_emva1288(emva_dir))
    t_read = time.perf_counter() - t0
    fs = sweep.full_scale_dn
    means = sweep.step_means()
    kinds, expo = means["kind"], means["exposure_ms"]
    light = np.flatnonzero((kinds == "light") & (expo > 0))
    dark_idx = np.flatnonzero(kinds == "dark")

    def dark_for(i):
        same = dark_idx[np.isclose(expo[dark_idx], expo[i], rtol=1e-9, atol=0)]
        if same.size:
            return int(same[0])
        return int(dark_idx[np.argmin(np.abs(expo[dark_idx] - expo[i]))])

    darks = {int(i): dark_for(i) for i in light}
    clipped = {int(i): (sweep.data[sweep.step == means["step"][i]] >= fs).any(axis=0)
               for i in light}
    signal = np.array([means["data"][i].mean() - means["data"][darks[int(i)]].mean()
                       for i in light])
    clip_frac = np.array([clipped[int(i)].mean() for i in light])
    tests = [int(i) for i, s, cf in zip(light, signal, clip_frac)
             if s >= EMVA_MIN_SIGNAL_DN and cf <= EMVA_MAX_CLIPPED]
    pos = np.unique(np.round(np.linspace(0.08 * (light.size - 1), light.size - 1,
                                         n_candidates)).astype(int))
    cands = [int(light[p]) for p in pos]

    t1 = time.perf_counter()
    cal = calibrate(sweep, method="joint")
    t_cal = time.perf_counter() - t1

    t1 = time.perf_counter()
    test_sig, raw_u, noise_u = [], [], []
    for j in tests:
        ok = ~clipped[j]
        sig = means["data"][j] - means["data"][darks[j]]
        test_sig.append(float(sig[ok].mean()))
        raw_u.append(uniformity(sig, ok))
        fr = sweep.data[sweep.step == means["step"][j]].astype(np.float64)
        # temporal noise floor of a 2-frame mean: std((f1 - f2) / 2) relative to the signal
        noise_u.append(float(100 * np.std((fr[0] - fr[1])[ok] / 2) / sig[ok].mean()))
    u = np.full((len(cands), len(tests)), np.nan)
    rows = []
    for ci, c in enumerate(cands):
        flat, dark = means["data"][c], means["data"][darks[c]]
        for ti, j in enumerate(tests):
            corr, dq = two_point_correct(means["data"][j], dark, flat)
            u[ci, ti] = uniformity(corr, ~clipped[j] & (dq == 0))
        others = np.array([j != c for j in tests])
        a = alpha_map(flat, float(expo[c]), cal)
        fin = a[np.isfinite(a)]
        rows.append({"step": int(means["step"][c]), "exposure_ms": float(expo[c]),
                     "photons": float(means["photons"][c]),
                     "signal_dn": float(flat.mean() - dark.mean()),
                     "clipped_fraction": float(clipped[c].mean()),
                     "alpha_median_percent": float(np.median(fin)) if fin.size else np.inf,
                     "alpha_p95_percent": float(np.percentile(fin, 95)) if fin.size else np.inf,
                     "alpha_invalid_fraction": float(np.mean(~(a < threshold))),
                     "mean_nonuniformity_percent": float(np.mean(u[ci, others])),
                     "median_nonuniformity_percent": float(np.median(u[ci, others]))})
    t_ffc = time.perf_counter() - t1
    mean_u = np.array([r["mean_nonuniformity_percent"] for r in rows])
    best = int(np.argmin(mean_u))
    med_alpha = np.array([r["alpha_median_percent"] for r in rows])
    p95_alpha = np.array([r["alpha_p95_percent"] for r in rows])
    sig_c = np.array([r["signal_dn"] for r in rows])
    sel = _select_longest(med_alpha, sig_c, threshold)
    sel95 = _select_longest(p95_alpha, sig_c, threshold)
    return {"source": str(emva_dir), "frame_shape": list(sweep.frame_shape),
            "bit_depth": sweep.bit_depth, "n_light_steps": int(light.size),
            "threshold_percent": float(threshold), "candidates": rows,
            "test_steps": [int(means["step"][j]) for j in tests],
            "test_signal_dn": np.asarray(test_sig), "raw_nonuniformity_percent": np.asarray(raw_u),
            "noise_floor_percent": np.asarray(noise_u), "nonuniformity_percent": u,
            "best_index": best, "selected_index": sel, "selected_index_p95": sel95,
            "best_step": rows[best]["step"],
            "selected_step": None if sel is None else rows[sel]["step"],
            "selected_step_p95": None if sel95 is None else rows[sel95]["step"],
            "raw_mean_nonuniformity_percent": float(np.mean(raw_u)),
            "calibration_flag_free": float(np.mean(np.asarray(cal["flags"]) == 0)),
            "timing": {"read_s": t_read, "calibration_s": t_cal, "ffc_s": t_ffc}}


# -- figures -----------------------------------------------------------------------------------

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _plot_fig4(f4, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    y = np.array([p["saturated_dn"] for p in f4["pairs"]])
    k = np.array([p["k_dn_per_ms"] for p in f4["pairs"]])
    ax.plot(y, k, "o", color="k", ms=5, mfc="none", label="measured (saturated level, k)")
    yy = np.linspace(y.min() - 30, y.max() + 30, 200)
    ax.plot(yy, f4["a_dn_per_ms"] * np.exp(f4["b_per_dn"] * yy), "-", color="tab:red",
            label=f"fit k = a e^(bY): a = {f4['a_dn_per_ms']:.3g} DN/ms, "
                  f"b = {f4['b_per_dn']:.4f}/DN")
    ax.plot(yy, f4["a_true_dn_per_ms"] * np.exp(f4["b_true_per_dn"] * yy), ":", color="0.4",
            label="simulator truth")
    ax.axvline(800, color="0.7", lw=0.8)
    ax.axhline(2, color="0.7", lw=0.8)
    ax.set_xlabel("saturated level Y (DN)")
    ax.set_ylabel("light rate k = leakage at saturation (DN/ms)")
    ax.set_title(f"Fig. 4: saturated level vs light rate, pixel {tuple(f4['pixel'])} (band 1), "
                 f"{len(y)} illuminations of lamp A", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _savefig(fig, path)


def _plot_fig5(f5, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.errorbar(f5["exposure_ms"], f5["measured_dn"], yerr=f5["measured_se_dn"], fmt="o", ms=3,
                color="k", mfc="none", lw=0.8, label="'measured' (simulated, 10-frame mean)")
    ax.plot(f5["t_fine_ms"], f5["leakage_fine_dn"], "-", color="tab:blue",
            label=f"leakage model, eq. (3): RMS {f5['rms_leakage_dn']:.1f} DN")
    ax.plot(f5["t_fine_ms"], f5["linear_fine_dn"], "--", color="tab:orange",
            label=f"linear model, eq. (1): RMS {f5['rms_linear_dn']:.1f} DN")
    if f5["leakage_visible_after_ms"] is not None:
        ax.axvline(f5["leakage_visible_after_ms"], color="0.5", lw=0.8, ls=":")
        ax.text(f5["leakage_visible_after_ms"] + 8, 80,
                f"leakage visible\nafter {f5['leakage_visible_after_ms']:.0f} ms", fontsize=8)
    ax.axhline(f5["dynamic_saturation_dn"], color="tab:blue", lw=0.7, ls=":")
    ax.set_ylim(0, 1060)
    ax.set_xlabel("exposure time (ms)")
    ax.set_ylabel("response (DN)")
    ax.set_title(f"Fig. 5: lamp B, pixel {tuple(f5['pixel'])} (band 1): k = "
                 f"{f5['k_dn_per_ms']:.2f} DN/ms, saturation {f5['dynamic_saturation_dn']:.0f} DN",
                 fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    _savefig(fig, path)


def _plot_fig2(f2, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.plot(f2["exposure_ms"], f2["measured_dn"], "-", color="0.6", lw=1, label="response")
    marks = {"pentagram": ("*", 14, "tab:green"), "circle": ("o", 9, "tab:orange"),
             "triangle": ("^", 10, "tab:red")}
    for name, tag in f2["tags"].items():
        m, ms, col = marks[name]
        t, y = tag["exposure_ms"], tag["response_dn"]
        ax.plot([0, t], [f2["dark_dn"], y], "--", color=col, lw=0.8)
        ax.plot(t, y, m, ms=ms, color=col,
                label=f"{name} {t:.0f} ms: alpha {tag['alpha_percent']:.2f} % "
                      f"(paper {tag['paper_alpha_percent']:g} %), "
                      f"k {tag['apparent_k_dn_per_ms']:.2f}")
    ax.axhline(1023, color="0.3", ls=":", lw=0.8)
    ax.text(10, 1000, "full scale 1023 DN (the fixed saturation rule)", fontsize=7)
    ax.set_ylim(0, 1060)
    ax.set_xlabel("exposure time (ms)")
    ax.set_ylabel("response (DN)")
    ax.set_title("Fig. 2: responses tagged by alpha (eq. 4, k ~ Y/t); dashed: apparent k from "
                 "the dark offset", fontsize=9)
    ax.legend(fontsize=7.5, loc="lower right")
    ax.grid(alpha=0.3)
    _savefig(fig, path)


def _plot_fig6(sp, path):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    wl = sp["wavelengths_nm"] or list(range(1, sp["normalised"].shape[1] + 1))
    cmap = plt.get_cmap("viridis")
    n = len(sp["exposure_ms"])
    for i, e in enumerate(sp["exposure_ms"]):
        ok = bool(sp["valid"][i])
        ax.plot(wl, sp["normalised"][i], "-" if ok else ":", lw=1.4 if ok else 1.6,
                color=cmap(i / max(n - 1, 1)),
                label=f"{e:.3f} ms{'' if ok else ' (invalid)'}")
    ax.plot(wl, sp["truth_normalised"], "k--", lw=0.8, label="true spectrum")
    ax.set_xlabel("band centre (nm)")
    ax.set_ylabel("band mean / max")
    ax.set_title(f"Fig. 6: lamp B at 11 exposures; dotted: alpha over threshold in some band\n"
                 f"mean spectral angle: valid pairs "
                 f"{_fmt(sp['mean_angle_valid_pairs_deg'], 2)} deg, "
                 f"invalid-valid pairs {_fmt(sp['mean_angle_invalid_valid_pairs_deg'], 2)} deg",
                 fontsize=9)
    ax.legend(fontsize=6.5, ncol=2, loc="upper left")
    ax.grid(alpha=0.3)
    _savefig(fig, path)


def _plot_tradeoff(tr, path):
    plt = _plt()
    rows = tr["rows"]
    thr = np.array([r["threshold_percent"] for r in rows])
    fig, axes = plt.subplots(2, 2, figsize=(9.0, 6.0), sharex=True)
    chosen = tr["chosen_threshold_percent"]
    for ax, key, col, lab in ((axes[0, 0], "snr_db", "tab:green",
                               "SNR of the training flats (dB, single frame)"),
                              (axes[0, 1], "ru_pp", "tab:blue",
                               "RU: uniformity improvement (pp)"),
                              (axes[1, 0], "sc_tile_deg", "tab:purple",
                               "SC: spectral angle per tile (deg, lower = better)")):
        ax.plot(thr, [r[key] for r in rows], "-", color=col)
        ax.set_title(lab, fontsize=9)
        ax.axvline(chosen, color="k", ls="--", lw=0.8)
        ax.axvline(THRESHOLD_PERCENT, color="0.6", ls=":", lw=0.8)
        ax.grid(alpha=0.3)
    ax = axes[1, 1]
    for key, col, lab in (("score_snr", "tab:green", "SNR"), ("score_sc", "tab:purple", "SC"),
                          ("score_ru", "tab:blue", "RU")):
        ax.plot(thr, [r[key] for r in rows], "-", color=col, lw=1, label=lab)
    w = tr["weights"]
    ax.plot(thr, [r["score_total"] for r in rows], "k-", lw=2,
            label=f"weighted: snr={w['snr']:g}, sc={w['sc']:g}, ru={w['ru']:g}")
    ax.axvline(chosen, color="k", ls="--", lw=0.8)
    ax.axvline(THRESHOLD_PERCENT, color="0.6", ls=":", lw=0.8)
    ax.text(chosen * 1.06, 0.03, f"chosen {chosen:g} %", fontsize=8)
    ax.set_title("normalised scores (1 = best); dotted: the paper's 12 %", fontsize=9)
    ax.legend(fontsize=7.5, loc="lower left")
    ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xscale("log")
        ax.set_xlabel("alpha threshold (%)")
    fig.suptitle("Trade-off against the alpha threshold (simulated sensor)", fontsize=10)
    fig.tight_layout()
    _savefig(fig, path)


def _plot_emva(em, path):
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.2), gridspec_kw={"width_ratios": [1.5, 1]})
    ax = axes[0]
    x = em["test_signal_dn"]
    ax.plot(x, em["raw_nonuniformity_percent"], "-", color="0.5", lw=1.2,
            label="no FFC (dark subtracted)")
    ax.plot(x, em["noise_floor_percent"], ":", color="k", lw=1,
            label="temporal noise of the 2-frame test mean")
    rows = em["candidates"]
    show = {0, em["best_index"], len(rows) - 1, len(rows) // 2}
    if em["selected_index"] is not None:
        show.add(em["selected_index"])
    cmap = plt.get_cmap("plasma")
    for ci in sorted(show):
        r = rows[ci]
        tags = []
        if ci == em["best_index"]:
            tags.append("best")
        if ci == em["selected_index"]:
            tags.append("alpha-selected")
        lab = (f"flat at {r['signal_dn']:.0f} DN (alpha {r['alpha_median_percent']:.2g} %)"
               + (f" [{', '.join(tags)}]" if tags else ""))
        yv = np.where(np.asarray(em["test_steps"]) == r["step"], np.nan,
                      em["nonuniformity_percent"][ci])
        ax.plot(x, yv, "-", lw=1.4,
                color=cmap(ci / max(len(rows) - 1, 1) * 0.9), label=lab)
        ax.axvline(r["signal_dn"], color=cmap(ci / max(len(rows) - 1, 1) * 0.9), lw=0.5, ls="--")
    from matplotlib.ticker import FormatStrFormatter, NullFormatter
    ax.set_yscale("log")
    ax.set_ylim(0.4, 8)
    ax.set_yticks([0.5, 1, 2, 4, 8])
    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("test level: mean signal above dark (DN)")
    ax.set_ylabel("residual non-uniformity, eq. (6) (%)")
    ax.set_title("Real EMVA 1288 sweep: two-point FFC trained at one level, tested at the others",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.3, which="both")
    ax = axes[1]
    sig = [r["signal_dn"] for r in rows]
    ax.plot(sig, [r["mean_nonuniformity_percent"] for r in rows], "o-", color="tab:blue",
            label="mean over test levels")
    ax.plot(sig[em["best_index"]], rows[em["best_index"]]["mean_nonuniformity_percent"], "s",
            ms=11, mfc="none", color="tab:green", label="best")
    if em["selected_index"] is not None:
        ax.plot(sig[em["selected_index"]],
                rows[em["selected_index"]]["mean_nonuniformity_percent"], "*", ms=12,
                color="tab:red", label=f"alpha < {em['threshold_percent']:g} % (median)")
    ax.axhline(em["raw_mean_nonuniformity_percent"], color="0.5", lw=0.8, label="no FFC")
    ax.set_xlabel("flat level: mean signal above dark (DN)")
    ax.set_ylabel("mean residual non-uniformity (%)")
    ax3 = ax.twinx()
    ax3.semilogy(sig, [max(r["alpha_median_percent"], 1e-4) for r in rows], "--", color="tab:red",
                 lw=0.8)
    ax3.axhline(em["threshold_percent"], color="tab:red", lw=0.5, ls=":")
    ax3.set_ylabel("median alpha of the flat (%)", color="tab:red")
    ax.legend(fontsize=7, loc="upper center")
    ax.grid(alpha=0.3)
    ax.set_title("Which flat level?", fontsize=9)
    fig.tight_layout()
    _savefig(fig, path)


# -- CSV files ---------------------------------------------------------------------------------

def _csvs(sim, em) -> dict:
    out = {}
    t1 = sim["table1"]
    t2 = sim["table2"]
    p1, p2 = PAPER_VALUES["table1_alpha_percent"], PAPER_VALUES["table2_improvement_pp"]
    rows = []
    for band in range(t1.alpha.shape[0]):
        for j, e in enumerate(t1.exposures_ms):
            paper = p1.get(band + 1, [None] * 5)[j]
            rows.append([band + 1, sim["wavelengths_nm"][band], e, t1.alpha[band, j],
                         "" if paper is None else paper, t1.selected_ms[band] == e])
    out["table1_alpha.csv"] = _csv_text(
        ["band", "wavelength_nm", "exposure_ms", "alpha_percent", "paper_alpha_percent",
         "selected"], rows)
    rows = []
    for band in range(t2["improvement_pp"].shape[0]):
        for j, e in enumerate(t2["exposures_ms"]):
            paper = p2.get(band + 1, [None] * 5)[j]
            rows.append([band + 1, e, t2["improvement_pp"][band, j], t2["se_pp"][band, j],
                         "" if paper is None else paper, t2["selected_ms"][band] == e,
                         t2["best_ms"][band] == e, t2["improvement_dark_subtracted_pp"][band, j],
                         t2["se_dark_subtracted_pp"][band, j], t2["raw_uniformity_percent"][band],
                         t2["raw_uniformity_dark_subtracted_percent"][band],
                         t2["test_mean_dn"][band]])
    out["table2_uniformity.csv"] = _csv_text(
        ["band", "training_exposure_ms", "improvement_pp", "standard_error_pp",
         "paper_improvement_pp", "selected_by_alpha", "best",
         "improvement_vs_dark_subtracted_test_pp", "standard_error_dark_subtracted_pp",
         "test_uniformity_raw_percent", "test_uniformity_dark_subtracted_percent",
         "test_mean_raw_dn"], rows)
    g = sim["grid"]
    rows = [[band + 1, e, g["alpha_percent"][band, j], g["signal_dn"][band, j], g["snr"][band, j],
             g["improvement_pp"][band, j], g["se_pp"][band, j]]
            for band in range(g["alpha_percent"].shape[0]) for j, e in enumerate(g["exposures_ms"])]
    out["training_grid.csv"] = _csv_text(
        ["band", "exposure_ms", "alpha_percent", "flat_signal_dn", "flat_snr_single_frame",
         "improvement_pp", "standard_error_pp"], rows)
    f4 = sim["fig4"]
    rows = [[p["illumination"], p["relative_light"], p["saturated_dn"], p["k_dn_per_ms"],
             f4["a_dn_per_ms"] * np.exp(f4["b_per_dn"] * p["saturated_dn"])] for p in f4["pairs"]]
    out["fig4_saturation_vs_rate.csv"] = _csv_text(
        ["illumination", "relative_light", "saturated_dn", "k_dn_per_ms", "fit_k_dn_per_ms"], rows)
    f5 = sim["fig5"]
    rows = [[t, m, s, lk, ln, ar, asg] for t, m, s, lk, ln, ar, asg in zip(
        f5["exposure_ms"], f5["measured_dn"], f5["measured_se_dn"], f5["leakage_model_dn"],
        f5["linear_model_dn"], f5["alpha_paper_raw_percent"], f5["alpha_signal_percent"])]
    out["fig5_response_lamp_b.csv"] = _csv_text(
        ["exposure_ms", "measured_dn", "measured_se_dn", "leakage_model_dn", "linear_model_dn",
         "alpha_paper_percent", "alpha_dark_subtracted_percent"], rows)
    f2 = sim["fig2"]
    tag_at = {v["exposure_ms"]: k for k, v in f2["tags"].items()}
    rows = [[t, y, a, asg, tag_at.get(float(t), "")] for t, y, a, asg in zip(
        f2["exposure_ms"], f2["measured_dn"], f2["alpha_percent"], f2["alpha_signal_percent"])]
    out["fig2_alpha_tags.csv"] = _csv_text(
        ["exposure_ms", "response_dn", "alpha_paper_percent", "alpha_dark_subtracted_percent",
         "tag"], rows)
    sp = sim["fig6"]
    nb = sp["normalised"].shape[1]
    rows = []
    for i, e in enumerate(sp["exposure_ms"]):
        rows.append([e, bool(sp["valid"][i]), sp["alpha_percent"][:, i].max(),
                     sp["angle_to_best_deg"][i], sp["angle_to_truth_deg"][i],
                     sp["tile_angle_to_truth_deg"][i], *sp["normalised"][i], *sp["spectra_dn"][i]])
    rows.append(["truth", "", "", "", 0.0, "", *sp["truth_normalised"], *sp["truth_spectrum"]])
    out["fig6_spectra.csv"] = _csv_text(
        ["exposure_ms", "valid", "max_band_alpha_percent", "angle_to_best_deg",
         "angle_to_truth_deg", "mean_tile_angle_to_truth_deg"]
        + [f"band{b + 1}_normalised" for b in range(nb)]
        + [f"band{b + 1}_signal_dn" for b in range(nb)], rows)
    tr = sim["tradeoff"]
    rows = [[r["threshold_percent"], r["snr_db"], r["ru_pp"], r["sc_tile_deg"],
             r["sc_band_mean_deg"], r["spectral_ms"], r["score_snr"], r["score_sc"], r["score_ru"],
             r["score_total"], r["fallback"], *r["selected_ms"]] for r in tr["rows"]]
    out["tradeoff.csv"] = _csv_text(
        ["threshold_percent", "snr_db", "ru_improvement_pp", "sc_tile_angle_deg",
         "sc_band_mean_angle_deg", "spectral_exposure_ms", "score_snr", "score_sc", "score_ru",
         "score_weighted", "fallback_to_shortest"]
        + [f"band{b + 1}_training_ms" for b in range(len(tr["rows"][0]["selected_ms"]))], rows)
    if em is not None:
        rows = [[r["step"], r["exposure_ms"], r["photons"], r["signal_dn"], r["clipped_fraction"],
                 r["alpha_median_percent"], r["alpha_p95_percent"], r["alpha_invalid_fraction"],
                 r["mean_nonuniformity_percent"], r["median_nonuniformity_percent"],
                 i == em["best_index"], i == em["selected_index"]]
                for i, r in enumerate(em["candidates"])]
        out["emva_ffc_levels.csv"] = _csv_text(
            ["flat_step", "exposure_ms", "photons", "flat_signal_dn", "clipped_fraction",
             "alpha_median_percent", "alpha_p95_percent", "fraction_alpha_over_threshold",
             "mean_nonuniformity_percent", "median_nonuniformity_percent", "best",
             "selected_by_alpha"], rows)
        rows = []
        for ti, step in enumerate(em["test_steps"]):
            rows.append([step, em["test_signal_dn"][ti], em["raw_nonuniformity_percent"][ti],
                         em["noise_floor_percent"][ti],
                         *em["nonuniformity_percent"][:, ti]])
        out["emva_ffc_matrix.csv"] = _csv_text(
            ["test_step", "test_signal_dn", "no_ffc_percent", "noise_floor_percent"]
            + [f"flat_step{r['step']}_percent" for r in em["candidates"]], rows)
    return out


# -- Markdown ----------------------------------------------------------------------------------

def _markdown(sim, em, emva_note, timing) -> str:
    t1, t2, f2, f4, f5, sp, tr = (sim[k] for k in ("table1", "table2", "fig2", "fig4", "fig5",
                                                   "fig6", "tradeoff"))
    p1, p2 = PAPER_VALUES["table1_alpha_percent"], PAPER_VALUES["table2_improvement_pp"]
    thr = sim["threshold_percent"]
    L = [f"# The paper's section V, reproduced (hsiffc {__version__})", "",
         f"Simulated 8-band sensor {sim['shape'][0]} x {sim['shape'][1]} px (seed {sim['seed']}); "
         f"threshold {thr:g} %. Values in parentheses are the paper's. Total run time "
         f"{timing['total_s']:.1f} s.", "",
         "## Fig. 4: calibration of a and b", "",
         f"{f4['n_illuminations']} illuminations of lamp A (paper: 16); pixel {tuple(f4['pixel'])} "
         f"of band 1: a = {f4['a_dn_per_ms']:.3g} DN/ms (true {f4['a_true_dn_per_ms']:.3g}), "
         f"b = {f4['b_per_dn']:.5f} /DN (true {f4['b_true_per_dn']:.5f}); leakage at 800 DN "
         f"{f4['leak_at_800_dn_per_ms']:.2f} DN/ms (paper: about 2). Over the sensor the median "
         f"error is {100 * f4['sensor_median_abs_rel_error_b']:.1f} % in b and "
         f"{f4['sensor_median_abs_error_ln_a']:.2f} in ln a.", "",
         "![Fig. 4](fig4_saturation_vs_rate.png)", "",
         "## Fig. 5: simulated response with and without leakage, lamp B", "",
         "| quantity | ours | paper |", "|---|---|---|",
         f"| k (DN/ms) | {f5['k_dn_per_ms']:.2f} | about 2 |",
         f"| dynamic saturation (DN) | {f5['dynamic_saturation_dn']:.0f} (measured plateau "
         f"{f5['measured_plateau_dn']:.0f}) | about 800 |",
         f"| leakage at 800 DN (DN/ms) | {f5['leak_at_800_dn_per_ms']:.2f} | about 2 |",
         f"| leakage visible after (ms): linear model above the data by > 3 standard errors "
         f"| {_fmt(f5['leakage_visible_after_ms'], 0)} | about 430 |",
         f"| ... by > 5 % of the signal | {_fmt(f5['linear_5pct_high_after_ms'], 0)} | |",
         f"| RMS error, leakage model (DN) | {f5['rms_leakage_dn']:.1f} "
         f"(<= 430 ms: {f5['rms_leakage_early_dn']:.1f}, "
         f"later: {f5['rms_leakage_late_dn']:.1f}) | - |",
         f"| RMS error, linear model (DN) | {f5['rms_linear_dn']:.1f} "
         f"(<= 430 ms: {f5['rms_linear_early_dn']:.1f}, "
         f"later: {f5['rms_linear_late_dn']:.1f}) | - |",
         "", "![Fig. 5](fig5_response_lamp_b.png)", "",
         "## Fig. 2: points tagged by alpha", "",
         "| tag | exposure (ms) | response (DN) | alpha, k ~ Y/t (%) | alpha, k ~ (Y - dark)/t (%) "
         "| paper alpha (%) |", "|---|---|---|---|---|---|"]
    for name, tag in f2["tags"].items():
        L.append(f"| {name} | {tag['exposure_ms']:.0f} | {tag['response_dn']:.0f} | "
                 f"{tag['alpha_percent']:.2f} | {tag['alpha_signal_percent']:.2f} | "
                 f"{tag['paper_alpha_percent']:g} |")
    L += ["", f"The model reaches 99 % of its dynamic saturation signal at "
              f"{_fmt(f2['t_99pct_saturation_ms'], 0)} ms (paper: saturated near 600 ms).", "",
          "![Fig. 2](fig2_alpha_tags.png)", "",
          f"## Table I: alpha (%) of the training images, [selected] at {thr:g} %", "",
          "| band | " + " | ".join(f"{e:g} ms" for e in t1.exposures_ms) + " |",
          "|---" * (len(t1.exposures_ms) + 1) + "|"]
    for band in range(t1.alpha.shape[0]):
        cells = []
        for j, e in enumerate(t1.exposures_ms):
            txt = f"{t1.alpha[band, j]:.2f}"
            if t1.selected_ms[band] == e:
                txt = f"**[{txt}]**"
            if band + 1 in p1:
                txt += f" ({p1[band + 1][j]:.2f})"
            cells.append(txt)
        L.append(f"| {band + 1} | " + " | ".join(cells) + " |")
    L += ["", "## Table II: uniformity improvement (percentage points) by two-point FFC", "",
          f"Test: {t2['n_test_frames']} raw frames at {TEST_MS} ms under lamp B; mean over the "
          "frames (standard error in the CSV); **bold**: best column; [brackets]: selected by "
          "alpha.", "",
          "| band | " + " | ".join(f"{e:g} ms" for e in t2["exposures_ms"])
          + " | best within 2 SE |",
          "|---" * (len(t2["exposures_ms"]) + 2) + "|"]
    for band in range(t2["improvement_pp"].shape[0]):
        cells = []
        for j, e in enumerate(t2["exposures_ms"]):
            txt = f"{t2['improvement_pp'][band, j]:+.3f}"
            if t2["best_ms"][band] == e:
                txt = f"**{txt}**"
            if t2["selected_ms"][band] == e:
                txt = f"[{txt}]"
            if band + 1 in p2:
                txt += f" ({p2[band + 1][j]:+.2f})"
            cells.append(txt)
        ok = "yes" if t2["selected_within_2se_of_best"][band] else "no"
        L.append(f"| {band + 1} | " + " | ".join(cells) + f" | {ok} |")
    sel_best = int(np.sum(t2["selected_ms"] == t2["best_ms"]))
    worse = int(np.sum(t2["improvement_pp"][:, -1] < np.array(
        [t2["improvement_pp"][b, list(t2["exposures_ms"]).index(s)] if np.isfinite(s) else np.nan
         for b, s in enumerate(t2["selected_ms"])])))
    L += ["", "The same improvement when the raw test image's non-uniformity is taken after "
              "subtracting the dark (eq. 6 then has no dark offset in its denominator; the "
              "corrected image has none either):", "",
          "| band | test level (DN above dark) | "
          + " | ".join(f"{e:g} ms" for e in t2["exposures_ms"]) + " |",
          "|---" * (len(t2["exposures_ms"]) + 2) + "|"]
    for band in range(t2["improvement_pp"].shape[0]):
        L.append(f"| {band + 1} | {t2['test_signal_dn'][band]:.0f} | "
                 + " | ".join(f"{v:+.3f}" for v in t2["improvement_dark_subtracted_pp"][band])
                 + " |")
    L += ["", f"alpha selects the best column in {sel_best} of {len(t2['best_ms'])} bands and a "
              f"column within two standard errors of it in "
              f"{int(np.sum(t2['selected_within_2se_of_best']))}; the longest exposure is worse "
              f"than the selected one in {worse} bands.", "",
          "## Fig. 6: spectra of lamp B at 11 exposures", "",
          f"Band means of the dark-subtracted frames (no flat-field), normalised by their maximum. "
          f"A spectrum is invalid when any band's median alpha exceeds {thr:g} %. Light: lamp B "
          f"with the brightest band at {SPECTRA_PEAK_K:g} DN/ms.", "",
          "| exposure (ms) | valid | max band alpha (%) | angle to best valid (deg) "
          "| angle to truth (deg) | per-tile angle to truth (deg) |", "|---|---|---|---|---|---|"]
    for i, e in enumerate(sp["exposure_ms"]):
        L.append(f"| {e:.3f} | {'yes' if sp['valid'][i] else 'no'} | "
                 f"{sp['alpha_percent'][:, i].max():.2f} | {sp['angle_to_best_deg'][i]:.3f} | "
                 f"{sp['angle_to_truth_deg'][i]:.3f} | {sp['tile_angle_to_truth_deg'][i]:.2f} |")
    L += ["", f"Mean spectral angle between valid spectra: "
              f"{_fmt(sp['mean_angle_valid_pairs_deg'], 3)} deg; between an invalid and a valid "
              f"one: {_fmt(sp['mean_angle_invalid_valid_pairs_deg'], 3)} deg; first invalid "
              f"exposure {_fmt(sp['first_invalid_ms'], 3)} ms (paper: deformed above 29 ms).", "",
          "![Fig. 6](fig6_spectra.png)", "",
          "## Trade-off: SNR, spectral correctness and response uniformity against the threshold",
          "",
          "For every threshold 1-100 %: per band the longest training exposure (3.225-38.7 ms, "
          "lamp A) under it; SNR = mean over bands of the single-frame SNR of that flat (dB); "
          "RU = mean over bands of the Table II improvement with it; SC = mean spectral angle "
          "between each mosaic tile's lamp-B spectrum at the longest of the 11 Fig. 6 exposures "
          "whose alpha stays under the threshold and the tile's true spectrum. Each criterion "
          "is scaled to [0, 1] over the thresholds (1 = best) and combined with the weights.", "",
          "| weights | chosen threshold (%) | training ms per band | spectral exposure (ms) |",
          "|---|---|---|---|"]
    w = tr["weights"]
    L.append(f"| **snr={w['snr']:g}, sc={w['sc']:g}, ru={w['ru']:g} (this run)** | "
             f"**{tr['chosen_threshold_percent']:g}** | "
             f"{', '.join(f'{v:g}' for v in tr['chosen']['selected_ms'])} | "
             f"{tr['chosen']['spectral_ms']:g} |")
    for name, pr in tr["presets"].items():
        L.append(f"| {name} | {pr['threshold_percent']:g} | "
                 f"{', '.join(f'{v:g}' for v in pr['selected_ms'])} | {pr['spectral_ms']:g} |")
    c = tr["chosen"]
    L += ["", f"At the chosen threshold: SNR {c['snr_db']:.1f} dB, RU {c['ru_pp']:+.3f} pp, SC "
              f"{c['sc_tile_deg']:.2f} deg per tile.", "", "![trade-off](tradeoff.png)", "",
          "## The same questions on the real EMVA 1288 sweep", ""]
    if em is None:
        L += [emva_note, ""]
    else:
        L += [f"`{em['source']}`: {em['frame_shape'][0]} x {em['frame_shape'][1]} px, "
              f"{em['bit_depth']}-bit, {em['n_light_steps']} usable light steps. Two-point FFC "
              f"trained at each candidate flat (2-frame mean less the 2-frame dark at the same "
              f"exposure) and tested at the {len(em['test_steps'])} other light steps with at "
              f"least {EMVA_MIN_SIGNAL_DN:g} DN of signal and at most "
              f"{100 * EMVA_MAX_CLIPPED:g} % clipped pixels; alpha from a joint calibration of the "
              f"sweep.", "",
              "| flat step | signal (DN) | clipped (%) | median alpha (%) | p95 alpha (%) "
              "| mean residual non-uniformity (%) |", "|---|---|---|---|---|---|"]
        for i, r in enumerate(em["candidates"]):
            tag = (" **best**" if i == em["best_index"] else "") + \
                  (" [alpha]" if i == em["selected_index"] else "")
            L.append(f"| {r['step']}{tag} | {r['signal_dn']:.1f} | "
                     f"{100 * r['clipped_fraction']:.2f} | {r['alpha_median_percent']:.3g} | "
                     f"{r['alpha_p95_percent']:.3g} | {r['mean_nonuniformity_percent']:.3f} |")
        b, s = em["best_index"], em["selected_index"]
        rb = em["candidates"][b]
        txt = (f"Without FFC the mean non-uniformity is "
               f"{em['raw_mean_nonuniformity_percent']:.3f} %. "
               f"The best flat is step {rb['step']} ({rb['signal_dn']:.0f} DN, "
               f"{rb['mean_nonuniformity_percent']:.3f} %).")
        if s is None:
            txt += f" No candidate has a median alpha under {em['threshold_percent']:g} %."
        else:
            rs = em["candidates"][s]
            txt += (f" alpha (median under {em['threshold_percent']:g} %) selects step "
                    f"{rs['step']} ({rs['signal_dn']:.0f} DN, "
                    f"{rs['mean_nonuniformity_percent']:.3f} %"
                    f", {rs['mean_nonuniformity_percent'] - rb['mean_nonuniformity_percent']:+.3f} "
                    "pp from the best).")
        L += ["", txt, "", "![EMVA](emva_ffc_levels.png)", ""]
    L += ["## Run time", "", "| part | seconds |", "|---|---|"]
    for k, v in timing.items():
        L.append(f"| {k.replace('_s', '')} | {v:.1f} |")
    L += ["", "Every number is in the CSV files beside this report; `summary.json` has them all.",
          ""]
    return "\n".join(L)


# -- the entry point ---------------------------------------------------------------------------

def run_paper_report(outdir, *, seed: int = 0, shape=(128, 128), emva_dir=None, weights=None,
                     threshold: float = THRESHOLD_PERCENT,
                     n_test_frames: int = N_TEST_FRAMES) -> dict:
    """Run the paper's experiments and write the report into ``outdir``.

    Parameters
    ----------
    outdir : path-like
        Folder for ``report.md``, the PNG figures, the CSV files and ``summary.json`` (created
        if missing; existing files of the same names are replaced atomically).
    seed : int
        Seeds the simulated sensor's fixed pattern and every capture.
    shape : (H, W)
        Simulated sensor size (a multiple of the 2 x 4 tile); 128 x 128 takes about 5 s (the
        whole report with the real-data part about 15 s on 2 cores).
    emva_dir : path-like, None or False
        The real EMVA 1288 sweep folder. None: look for ``shared/data/emva1288-cmos8-roi``
        (:func:`find_emva_dir`); False: skip the real-data part.
    weights : dict or str, optional
        Trade-off weights, e.g. ``"snr=1,sc=1,ru=1"`` (see :func:`parse_weights`).
    threshold : float
        alpha threshold (percent) of Tables I and II and Fig. 6 (the paper's 12 %).
    n_test_frames : int
        Independent test frames of Table II (mean and standard error over them).

    Returns
    -------
    dict
        ``simulated`` (every number of the simulated experiment), ``emva`` (or None),
        ``emva_note``, ``timing`` and ``files`` (name -> path).
    """
    t0 = time.perf_counter()
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    weights = parse_weights(weights)
    log.info("simulating the paper's experiment on a %s sensor (seed %s)", tuple(shape), seed)
    sim = simulate_paper_experiment(seed=seed, shape=shape, threshold=threshold,
                                    weights=weights, n_test_frames=n_test_frames)
    em, note = None, ""
    if emva_dir is False:
        note = "Skipped (real-data part switched off)."
    else:
        found = Path(emva_dir) if emva_dir is not None else find_emva_dir()
        if emva_dir is not None and not found.exists():
            raise FileNotFoundError(f"EMVA 1288 data folder {found} does not exist")
        if found is None:
            note = ("Skipped: the EMVA 1288 sweep was not found (no "
                    "shared/data/emva1288-cmos8-roi beside the repository or the working "
                    "directory, and HSIFFC_SHARED_DATA not set); pass its folder (`hsiffc paper "
                    "OUTDIR --emva DIR`) to run this part.")
        else:
            log.info("flat-field levels on the real EMVA 1288 sweep %s", found)
            em = emva_ffc_levels(found, threshold=threshold)
    t_fig = time.perf_counter()
    files = {}
    for name, fn, arg in (("fig2_alpha_tags.png", _plot_fig2, sim["fig2"]),
                          ("fig4_saturation_vs_rate.png", _plot_fig4, sim["fig4"]),
                          ("fig5_response_lamp_b.png", _plot_fig5, sim["fig5"]),
                          ("fig6_spectra.png", _plot_fig6, sim["fig6"]),
                          ("tradeoff.png", _plot_tradeoff, sim["tradeoff"])):
        fn(arg, outdir / name)
        files[name] = outdir / name
    if em is not None:
        _plot_emva(em, outdir / "emva_ffc_levels.png")
        files["emva_ffc_levels.png"] = outdir / "emva_ffc_levels.png"
    for name, text in _csvs(sim, em).items():
        atomic_write_text(outdir / name, text)
        files[name] = outdir / name
    timing = {**{k: v for k, v in sim["timing"].items()},
              **({f"emva_{k}": v for k, v in em["timing"].items()} if em else {}),
              "figures_s": time.perf_counter() - t_fig}
    timing["total_s"] = time.perf_counter() - t0
    atomic_write_text(outdir / "report.md", _markdown(sim, em, note, timing))
    files["report.md"] = outdir / "report.md"
    result = {"simulated": sim, "emva": em, "emva_note": note, "timing": timing,
              "files": {k: str(v) for k, v in files.items()}}
    summary = _summary(result)
    atomic_write_text(outdir / "summary.json", json.dumps(json_safe(summary), indent=1) + "\n")
    result["files"]["summary.json"] = str(outdir / "summary.json")
    return result


def _summary(result) -> dict:
    """JSON-safe digest (arrays of the figures dropped: they are in the CSVs)."""
    sim = result["simulated"]
    t1 = sim["table1"]
    drop5 = {"frames", "t_fine_ms", "leakage_fine_dn", "linear_fine_dn"}
    return {"hsiffc_version": __version__, "seed": sim["seed"], "shape": sim["shape"],
            "threshold_percent": sim["threshold_percent"], "light_w_m2": sim["light_w_m2"],
            "paper": PAPER_VALUES, "table1": t1.to_dict(),
            "table2": sim["table2"], "fig2": sim["fig2"], "fig4": sim["fig4"],
            "fig5": {k: v for k, v in sim["fig5"].items() if k not in drop5},
            "fig6": sim["fig6"],
            "tradeoff": {k: v for k, v in sim["tradeoff"].items() if k != "rows"},
            "emva": result["emva"], "emva_note": result["emva_note"],
            "timing": result["timing"], "files": result["files"]}
