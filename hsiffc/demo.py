"""``hsiffc demo``: the main job shown on the bundled sample cubes.

At this stage of the project the demo reads the 2900 K exposure sweep, fits the leakage model to
each band's mean response, and shows that every band levels off *below* full scale at a level that
depends on its light (dynamic saturation), with the leakage percentage alpha of every exposure.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from . import model
from .atomic import atomic_path, atomic_write_text
from .errors import DataFormatError

log = logging.getLogger(__name__)

SWEEP_NAME = "sweep_2900K.tif"


def fit_curve(t_ms, y_dn, dark_dn):
    """Fit the leakage model (k, a, b) to one mean response curve with a known dark level.

    Returns a dict with ``k``, ``a``, ``b``, ``dark``, ``saturation_dn``, ``rms_dn`` and the linear
    fit (``k_linear``, ``rms_linear_dn``) made on the samples below half the plateau.
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


def run_demo(samples: Path, outdir: Path) -> int:
    from .io import read_sweep

    samples = Path(samples)
    path = samples / SWEEP_NAME
    if not path.exists():
        raise DataFormatError(
            f"sample sweep {SWEEP_NAME} not found; run from the repository root or pass the "
            "sample folder (hsiffc demo path/to/sample_cubes); regenerate it with "
            "'python sample_cubes/make_samples.py'", path=samples)
    sweep = read_sweep(path)
    if sweep.mosaic is None:
        raise DataFormatError("the sweep has no mosaic layout in its metadata", path=path)
    print(sweep.summary())
    means = sweep.step_means()
    light = means["kind"] == "light"
    dark = means["kind"] == "dark"
    band_map = sweep.mosaic.band_map(sweep.frame_shape)
    n_bands = sweep.mosaic.n_bands
    t = means["exposure_ms"][light]
    # band means of every light step, and one dark level per band (darks are flat in exposure)
    y = np.stack([[f[band_map == bnd].mean() for bnd in range(n_bands)]
                  for f in means["data"][light]])  # (steps, bands)
    d = np.array([np.mean([f[band_map == bnd].mean() for f in means["data"][dark]])
                  for bnd in range(n_bands)]) if dark.any() else np.zeros(n_bands)
    fs = sweep.full_scale_dn
    wl = sweep.mosaic.wavelengths_nm or tuple(float("nan") for _ in range(n_bands))

    fits = [fit_curve(t, y[:, i], d[i]) for i in range(n_bands)]
    alpha = np.stack([model.leakage_percentage_paper(y[:, i], t, f["a"], f["b"], f["dark"])
                      for i, f in enumerate(fits)], axis=1)

    print(f"\nMean response per band (DN; full scale {fs} DN) and leakage percentage alpha (%)")
    head = "exposure_ms " + " ".join(f"{'b' + str(i + 1):>14}" for i in range(n_bands))
    print(head)
    for j in range(len(t)):
        cells = " ".join(f"{y[j, i]:7.1f}{_alpha_str(alpha[j, i]):>7}" for i in range(n_bands))
        print(f"{t[j]:11.3f} {cells}")
    print("\nDynamic saturation per band (leakage model fitted to the band mean)")
    print(f"{'band':>4} {'nm':>6} {'k DN/ms':>8} {'plateau':>8} {'model sat':>9} {'below FS':>8} "
          f"{'rms leak':>8} {'rms lin':>8}")
    for i, f in enumerate(fits):
        print(f"{i + 1:>4} {wl[i]:>6.0f} {f['k']:>8.2f} {y[:, i].max():>8.1f} "
              f"{f['saturation_dn']:>9.1f} {fs - y[:, i].max():>8.1f} {f['rms_dn']:>8.2f} "
              f"{f['rms_linear_dn']:>8.2f}")
    below = [i + 1 for i in range(n_bands) if y[:, i].max() < fs - 5]
    print(f"\n{len(below)} of {n_bands} bands level off below full scale ({fs} DN): the light-"
          "dependent dynamic saturation that the leakage model predicts. A fixed full-scale test "
          "would call all of their samples valid; alpha flags the leaking ones.")

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    summary = {"sweep": str(path), "full_scale_dn": fs, "exposure_ms": t.tolist(),
               "band_mean_dn": y.tolist(), "alpha_percent": np.where(np.isfinite(alpha), alpha,
                                                                    None).tolist(),
               "bands": [{"band": i + 1, "wavelength_nm": wl[i], **f,
                          "plateau_dn": float(y[:, i].max())} for i, f in enumerate(fits)]}
    atomic_write_text(outdir / "demo_summary.json", json.dumps(summary, indent=2) + "\n")
    png = outdir / "dynamic_saturation.png"
    _plot(png, t, y, fits, fs, wl)
    print(f"\nwrote {png} and {outdir / 'demo_summary.json'}")
    correction = run_correction(samples, outdir, sweep)
    summary["correction"] = correction
    atomic_write_text(outdir / "demo_summary.json", json.dumps(summary, indent=2) + "\n")
    return 0


def run_correction(samples: Path, outdir: Path, sweep) -> dict:
    """Calibrate, select the training exposure by alpha, fit the correction pipeline on the
    training flats and darks, and correct the 2200 K test frames (printed and returned)."""
    from .calibrate import calibrate
    from .ffc import uniformity_per_band
    from .frame import Frame
    from .io import read_sweep
    from .stages import Pipeline, create

    print("\n== Correction pipeline: calibrate, select by alpha, dark + mask + two-point FFC "
          "+ reconstruction ==")
    cal = calibrate(sweep)
    cal_path = cal.save(outdir / "calibration.npz", overwrite=True)
    train = (Frame.list_from_sweep(read_sweep(samples / "training_2900K.tif"))
             + Frame.list_from_sweep(read_sweep(samples / "darks.tif")))
    tests = Frame.list_from_sweep(read_sweep(samples / "test_2200K.tif"))
    pipe = Pipeline([("dark", create("dark")),
                     ("mask", create("alpha_mask", calibration=str(cal_path),
                                     threshold_percent=12.0)),
                     ("ffc", create("two_point_ffc", calibration=str(cal_path),
                                    threshold_percent=12.0)),
                     ("cube", create("reconstruct", method="ppid"))])
    pipe.fit(train)
    pipe.save(outdir / "pipeline.npz", overwrite=True)
    ffc = pipe.named_steps["ffc"]
    from .validity import AlphaTable

    table = ffc.alpha_table_
    print(AlphaTable(np.array(table["exposures_ms"]), np.array(table["alpha_percent"], float),
                     tuple(table["wavelengths_nm"] or ()), table["statistic"], table["method"]
                     ).select(12.0).to_text())
    test = tests[0]
    band_map = test.band_map()
    before = uniformity_per_band(test.data, band_map)
    flat_only = Pipeline(pipe.steps[:3]).transform(test)
    after = uniformity_per_band(flat_only.data, band_map, dq=flat_only.dq)
    cube = pipe.transform(test)
    print(f"\ntest frame {test.exposure_ms:g} ms under {test.meta.get('illumination')}: "
          "non-uniformity (eq. 6, %) per band")
    print(f"{'band':>6} {'raw':>8} {'corrected':>10}")
    for i in range(len(before)):
        print(f"{i + 1:>6} {before[i]:>8.3f} {after[i]:>10.3f}")
    flagged = float((flat_only.dq != 0).mean())
    print(f"cube {cube.data.shape} (H, W, bands) with wavelengths "
          f"{[round(w) for w in cube.meta['wavelengths_nm']]} nm; {100 * flagged:.2f} % of "
          "pixels flagged (kept, not deleted)")
    print(f"wrote {cal_path} and {outdir / 'pipeline.npz'}")
    return {"training_ms": ffc.selected_ms_, "uniformity_raw": before.tolist(),
            "uniformity_corrected": after.tolist(), "flagged_fraction": flagged,
            "cube_shape": list(cube.data.shape)}


def _alpha_str(a):
    if not np.isfinite(a):
        return "  -"
    return f"{a:6.2f}" if a < 1000 else " >1000"


def _plot(path, t, y, fits, fs, wl):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5), dpi=110)
    tt = np.linspace(0, t.max() * 1.05, 300)
    colours = plt.cm.viridis(np.linspace(0, 0.95, y.shape[1]))
    for i, f in enumerate(fits):
        ax.plot(t, y[:, i], "o", ms=3.5, color=colours[i], label=f"band {i + 1} ({wl[i]:.0f} nm)")
        ax.plot(tt, model.response(tt, f["k"], f["a"], f["b"], f["dark"]), "-", lw=1,
                color=colours[i])
        ax.plot(tt, f["dark"] + f["k"] * tt, ":", lw=0.8, color=colours[i])
    ax.axhline(fs, color="k", lw=0.8, ls="--")
    ax.text(tt[2], fs + 8, f"full scale {fs} DN", fontsize=8)
    ax.set_ylim(0, fs * 1.12)
    ax.set_xlabel("exposure (ms)")
    ax.set_ylabel("mean raw response (DN)")
    ax.set_title("Dynamic saturation below full scale (points: data, solid: leakage model, "
                 "dotted: linear)", fontsize=9)
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
