"""The simulated paper experiment, part 1: calibration sweep (Fig. 4) and one pixel's response
under lamp B against the leakage and linear models (Fig. 5, Fig. 2)."""

from __future__ import annotations

import numpy as np

from ...leakage import model
from ...data.sweep import Sweep
from .config import FIG2_LAST_MS, FIG4_LEVELS, FIG5_EXPOSURES_MS, N_TRAIN_FRAMES, PAPER_VALUES

__all__ = ["calibration_sweep", "fig2_data", "fig4_data", "fig5_data", "pick_pixel"]


def calibration_sweep(sensor, train_w_m2, rng):
    """Exposure sweeps into dynamic saturation under 16 levels of lamp A (Fig. 4's data).

    Exposures per level: 8 from 1 ms up to the time the nominal sensor (band-1 k = 30 DN/ms at
    the training light, saturation 800 DN at 2 DN/ms, b 0.0125/DN) needs to reach its dynamic
    saturation level linearly, and 4 at 1.6-3.4 times that, deep in the plateau.
    """
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


def pick_pixel(cal, band_map, band=0):
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


def fig4_data(cal_sweep, cal, pix):
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


def fig5_data(sensor, cal, pix, fig5_w_m2, seed):
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


def fig2_data(f5):
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


