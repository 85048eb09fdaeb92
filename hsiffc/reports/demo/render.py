"""The demo's result as text (what ``hsiffc demo`` prints) and as a figure."""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps

from ...leakage import model
from ..figures import new_figure

__all__ = ["demo_figure", "render_text"]


def _alpha_str(a) -> str:
    if not np.isfinite(a):
        return "  -"
    return f"{a:6.2f}" if a < 1000 else " >1000"


def render_text(res) -> str:
    """The demo's tables as plain text: band means with alpha, the fitted dynamic saturation
    per band, and the correction pipeline on the test frames."""
    t, y, alpha, fits = res.exposure_ms, res.band_mean_dn, res.alpha_percent, res.fits
    n_bands, fs, wl = y.shape[1], res.full_scale_dn, res.wavelengths_nm
    order = res.band_order  # bands by wavelength, numbered from 1 (band_labels)
    L = [f"Mean response per band (DN; full scale {fs} DN) and leakage percentage alpha (%); "
         "bands: " + ", ".join(res.band_labels[i] for i in order),
         "exposure_ms " + " ".join(f"{'b' + str(k + 1):>14}" for k in range(n_bands))]
    for j in range(len(t)):
        cells = " ".join(f"{y[j, i]:7.1f}{_alpha_str(alpha[j, i]):>7}" for i in order)
        L.append(f"{t[j]:11.3f} {cells}")
    L += ["", "Dynamic saturation per band (leakage model fitted to the band mean)",
          f"{'band':>4} {'nm':>6} {'k DN/ms':>8} {'plateau':>8} {'model sat':>9} "
          f"{'below FS':>8} {'rms leak':>8} {'rms lin':>8}"]
    for k, i in enumerate(order):
        f = fits[i]
        L.append(f"{k + 1:>4} {wl[i]:>6.0f} {f['k']:>8.2f} {y[:, i].max():>8.1f} "
                 f"{f['saturation_dn']:>9.1f} {fs - y[:, i].max():>8.1f} {f['rms_dn']:>8.2f} "
                 f"{f['rms_linear_dn']:>8.2f}")
    below = res.bands_below_full_scale
    L += ["", f"{len(below)} of {n_bands} bands level off below full scale ({fs} DN): the "
          "light-dependent dynamic saturation that the leakage model predicts. A fixed full-scale "
          "test would call all of their samples valid; alpha flags the leaking ones."]
    c = res.correction
    if c:
        L += ["", "== Correction: calibrate, then (1) the paper's pipeline: select by alpha, dark + "
              "mask + two-point FFC + reconstruction; (2) model_ffc from the calibration alone "
              "(what 'hsiffc correct' applies by default) ==",
              "two-point training exposure per band (longest with median alpha under 12 %): "
              + ", ".join(f"{c['training_ms'][i]:g} ms" for i in order),
              f"test frame {c['test_exposure_ms']:g} ms under {c['test_illumination']}: "
              "non-uniformity (eq. 6 on one frame, temporal noise included, %) per band, "
              f"raw less the two-point pipeline's dark and corrected, on the same "
              f"{c['uniformity_pixels']} pixels",
              f"{'band':>6} {'raw-dark':>8} {'two-point':>10} {'model_ffc':>10}"]
        u = list(zip(c["uniformity_raw_less_dark"], c["uniformity_corrected"],
                     c["uniformity_model_ffc"]))
        for k, i in enumerate(order):
            L.append(f"{k + 1:>6} {u[i][0]:>8.3f} {u[i][1]:>10.3f} {u[i][2]:>10.3f}")
        for s in c.get("fixed_pattern", ()):
            L += _fixed_pattern_table(s, order)
        L.append(f"cube {tuple(c['cube_shape'])} (H, W, bands) with wavelengths "
                 f"{[round(w) for w in c['cube_wavelengths_nm']]} nm; "
                 f"{100 * c['flagged_fraction']:.2f} % of pixels flagged (kept, not deleted)")
    return "\n".join(L)


def _fixed_pattern_table(s, order) -> list:
    """Lines of one test step's fixed-pattern table: raw, two-point, model_ffc per band (in
    ``order``, band indices by wavelength, numbered from 1)."""
    b, a = s["before"], s["after"]
    m = s.get("model_ffc")
    L = ["", f"fixed-pattern non-uniformity (EMVA 1288, temporal noise taken out; %) of the "
         f"{s['n_frames']} test frames at {s['exposure_ms']:g} ms, per band ({s['n_pixels']} "
         "pixels unflagged in every frame and correction)",
         f"{'band':>6} {'raw':>8} {'two-point':>10} {'model_ffc':>10} {'signal DN':>10}"]
    mp = m["fpn_percent"] if m else [float("nan")] * len(b["fpn_percent"])
    for k, i in enumerate(order):
        L.append(f"{k + 1:>6} {b['fpn_percent'][i]:>8.3f} {a['fpn_percent'][i]:>10.3f} "
                 f"{mp[i]:>10.3f} {b['mean_dn'][i]:>10.1f}")
    pm = m["pooled_fpn_percent"] if m else float("nan")
    L.append(f"{'all':>6} {b['pooled_fpn_percent']:>8.3f} {a['pooled_fpn_percent']:>10.3f} "
             f"{pm:>10.3f}   (RMS over bands; eq. 6 on single frames: "
             f"{b['pooled_eq6_percent']:.3f} -> {a['pooled_eq6_percent']:.3f} / "
             f"{m['pooled_eq6_percent'] if m else float('nan'):.3f})")
    return L


def demo_figure(res):
    """Band means against exposure with the fitted leakage model (solid) and the linear model
    (dotted): every band levels off below full scale. Returns a new Figure."""
    t, y, fits, fs = res.exposure_ms, res.band_mean_dn, res.fits, res.full_scale_dn
    fig, ax = new_figure((8, 5), dpi=110)
    tt = np.linspace(0, t.max() * 1.05, 300)
    colours = colormaps["viridis"](np.linspace(0, 0.95, y.shape[1]))
    labels = res.band_labels
    for k, i in enumerate(res.band_order):
        f = fits[i]
        ax.plot(t, y[:, i], "o", ms=3.5, color=colours[k], label=labels[i])
        ax.plot(tt, model.response(tt, f["k"], f["a"], f["b"], f["dark"]), "-", lw=1,
                color=colours[k])
        ax.plot(tt, f["dark"] + f["k"] * tt, ":", lw=0.8, color=colours[k])
    ax.axhline(fs, color="k", lw=0.8, ls="--")
    ax.text(tt[2], fs + 8, f"full scale {fs} DN", fontsize=8)
    ax.set_ylim(0, fs * 1.12)
    ax.set_xlabel("exposure (ms)")
    ax.set_ylabel("mean raw response (DN)")
    ax.set_title("Dynamic saturation below full scale (points: data, solid: leakage model, "
                 "dotted: linear)", fontsize=9)
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    return fig
