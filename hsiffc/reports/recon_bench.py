"""Spectral reconstruction measured against ground truth: every demosaicking method scored by
PSNR, SSIM and the spectral angle on scenes whose every band is known at every pixel.

    python3 -m hsiffc.reports.recon_bench OUT [--shared ../shared/data] [--quick]

The harness does not know the methods it scores: it makes scenes, their truth and their raw
frames, hands each frame to :func:`hsiffc.reconstruct.demosaic` (or
:func:`~hsiffc.reconstruct.tile_cube`) by name, and compares.

Scenes
------
A scene is a reflectance per pixel, a mixture of ``N_ENDMEMBERS`` measured spectra with
abundances from a natural image, times a shading from the same image:

* abundance maps: the image's colour channels, its grey level smoothed and a generated
  fractal noise (``1/f`` spectrum, seeded), pushed through a softmax whose sharpness is drawn
  per scene, so that materials meet at the image's edges and blend in its smooth parts;
  images from scikit-image's bundled samples (:data:`DEV_IMAGES` for development,
  :data:`EVAL_IMAGES` for evaluation: no image is in both), a random crop of each;
* shading: ``0.35 + 0.65 x`` the image's grey level (texture shared by every band);
* spectra (:func:`spectral_library`): the 24 ColorChecker patches (colour-science,
  ``SDS_COLOURCHECKERS["ISO 17321-1"]``, 380-780 nm) and the 14 CIE 1995 test colour samples
  (colour-science, ``colour.quality.datasets.SDS_TCS["CIE 1995"]``, 360-830 nm), each extended
  over the NIR by a smooth rise from its last value towards a plateau (paints reflect more in
  the NIR; the plateau is drawn per spectrum between its last value and 0.85, seeded); a
  vegetation spectrum (the ColorChecker "foliage" patch with a logistic red edge at 715 nm,
  width 12 nm, to 0.5 in the NIR) and a soil spectrum (a line from 0.08 at 400 nm to 0.38 at
  1000 nm), both synthetic.

Sensors and truth
-----------------
``imec-ssm5x5``: the 25 measured band responses of ``../shared/data/imec-ssm5x5`` (400-1000
nm, second-order lobes and the rejection filter included; :func:`hsiffc.spectral.read_imec_xml`)
on its 5 x 5 layout. ``vis-4x4``: :func:`hsiffc.spectral.imec_4x4_visible` (16 Fabry-Perot
bands, 470-620 nm) on a 4 x 4 layout; it needs no shared data. The light is a 3200 K blackbody.
The truth of band ``b`` at every pixel is its light rate (DN/ms) from
:func:`hsiffc.spectral.electron_rate` of the pixel's reflectance through the band's response;
the raw frame is :meth:`hsiffc.simulate.MosaicSensor.capture` of the same reflectances (the
simulator samples band ``mosaic.band_map`` at each pixel, adds shot and read noise and
quantises) with no fixed pattern (PRNU, DSNU, dark current and leakage off: demosaicking is
measured, not the flat field), dark-subtracted and divided by the exposure. Two light levels
(:data:`LIGHT_LEVELS`): the scene's 99th-percentile pixel at 60 % and at 6 % of full scale.
Then 0.1 % of the pixels (seeded) are flagged ``DEAD | DO_NOT_USE`` and their value set to 0
DN/ms (a method that used them would show it).

Metrics
-------
On the frame without a border of two tiles: PSNR and SSIM from ``skimage.metrics`` (data range
= the truth's maximum), per band and over the cube (SSIM over the cube: the mean of the bands);
the spectral angle (SAM, degrees) per pixel, its median and its 95th percentile (the 5 % worst
pixels). Separately: the PSNR and median SAM on edges (the 10 % of pixels with the largest
gradient of the truth's band mean) and near flagged pixels (within one tile of one), and for
``imec-ssm5x5`` the PSNR after the vendor correction matrix, against the truth corrected the
same way (the virtual bands). Each figure is the median over the scenes; speed (Mpx/s) is
timed on a 2048 x 1088 frame of each layout in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.dq import DQ
from ..data.mosaic import Mosaic
from ..reconstruct import DEMOSAIC_METHODS, demosaic, tile_cube, tile_origin
from ..simulate import MosaicSensor, SensorParams
from ..spectral import (BandSet, blackbody, colorchecker_reflectances, electron_rate,
                        imec_4x4_visible, read_imec_xml)

__all__ = ["DEV_IMAGES", "EVAL_IMAGES", "LIGHT_LEVELS", "METHODS", "PARAMS", "BenchSensor",
           "Scene", "frames_of", "main", "make_scene", "reconstruct", "render", "run",
           "sam_degrees", "score", "sensors", "spectral_library"]

#: scikit-image sample images the methods are developed on (never scored for the page)
DEV_IMAGES = ("camera", "brick", "coins", "chelsea")
#: scikit-image sample images of the evaluation scenes
EVAL_IMAGES = ("astronaut", "coffee", "rocket", "gravel", "grass", "retina")
DEV_SEED, EVAL_SEED = 1000, 2000
N_ENDMEMBERS = 5
#: light level name -> the scene's 99th-percentile pixel as a fraction of full scale
LIGHT_LEVELS = {"bright": 0.6, "dim": 0.06}
FLAG_FRACTION = 1e-3
EXPOSURE_MS = 10.0
IMEC_XML = "imec-ssm5x5/CMV2K-SSM5x5-600_875-5.5.9.2.xml"
#: what every method is compared against (the paper's figures: bilinear, the simple PPID)
METHODS = (*DEMOSAIC_METHODS, "tile")


@dataclass(frozen=True)
class BenchSensor:
    """A sensor of the benchmark: band responses, layout and (IMEC) correction matrix."""

    name: str
    bands: BandSet
    mosaic: Mosaic
    correction: np.ndarray | None = None


def sensors(shared: Path | None) -> list[BenchSensor]:
    """``vis-4x4`` always; ``imec-ssm5x5`` when ``shared`` holds the IMEC calibration."""
    out = [BenchSensor("vis-4x4", imec_4x4_visible(), Mosaic.square(4, name="4x4 VIS"))]
    xml = None if shared is None else Path(shared) / IMEC_XML
    if xml is not None and xml.is_file():
        cal = read_imec_xml(xml)
        out.insert(0, BenchSensor("imec-ssm5x5", cal.bands, cal.mosaic(),
                                  np.asarray(cal.correction_matrix, np.float64)))
    return out


# -- spectra -----------------------------------------------------------------------------------

def _extend(wl_table, values, wl, plateau):
    """A table spectrum on ``wl``: interpolated inside, held below, and rising smoothly from
    its last value towards ``plateau`` beyond (e-folding 60 nm)."""
    out = np.interp(wl, wl_table, values)
    end = wl_table[-1]
    last = float(np.mean(values[-3:]))
    beyond = wl > end
    out[beyond] = last + (plateau - last) * (1.0 - np.exp(-(wl[beyond] - end) / 60.0))
    out[wl < wl_table[0]] = float(np.mean(values[:3]))
    return out


def _plateau(rng, values):
    """The NIR plateau of a paint: between its last value and 0.85 (or the last value)."""
    last = float(np.mean(values[-3:]))
    return rng.uniform(last, max(last, 0.85))


def spectral_library(wl) -> tuple[np.ndarray, tuple[str, ...]]:
    """The reflectance spectra scenes are mixed from, ``(M, L)`` on ``wl`` (nm), and their
    names (sources in the module docstring)."""
    from colour.quality.datasets import SDS_TCS

    wl = np.asarray(wl, np.float64)
    rng = np.random.default_rng(7)
    cc, cc_names = colorchecker_reflectances(np.arange(380.0, 781.0, 5.0))
    spectra, names = [], []
    ccw = np.arange(380.0, 781.0, 5.0)
    for v, n in zip(cc, cc_names, strict=True):
        spectra.append(_extend(ccw, v, wl, _plateau(rng, v)))
        names.append(f"ColorChecker {n}")
    for n, sd in SDS_TCS["CIE 1995"].items():
        tw, tv = np.asarray(sd.wavelengths, float), np.asarray(sd.values, float)
        spectra.append(_extend(tw, tv, wl, _plateau(rng, tv)))
        names.append(f"CIE 1995 {n}")
    foliage = np.interp(wl, ccw, cc[list(cc_names).index("foliage")])
    edge = 1.0 / (1.0 + np.exp(-(wl - 715.0) / 12.0))
    spectra.append(foliage * (1 - edge) + 0.5 * edge)
    names.append("vegetation (foliage + red edge)")
    spectra.append(0.08 + 0.30 * (wl - 400.0) / 600.0)
    names.append("soil (linear)")
    return np.clip(np.array(spectra), 0.0, 1.0), tuple(names)


# -- scenes ------------------------------------------------------------------------------------

def _fractal(shape, rng, beta=2.0):
    """Seeded noise with a ``1/f^(beta/2)`` amplitude spectrum, scaled to [0, 1]."""
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    spec = (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape)) / f ** (beta / 2)
    spec[0, 0] = 0
    n = np.fft.irfft2(spec, s=shape)
    return (n - n.min()) / max(np.ptp(n), 1e-12)


def _image(name, shape, rng):
    """A random crop of scikit-image's sample ``name`` as float (H, W, 3) in [0, 1]."""
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)(), np.float64)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    img = img[:, :, :3] / max(img.max(), 1.0)
    import cv2
    # half size (area average): the optics' blur of a camera, not the sample's pixel noise
    img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    H, W = shape
    if img.shape[0] < H or img.shape[1] < W:
        s = max(H / img.shape[0], W / img.shape[1])
        img = cv2.resize(img, (int(np.ceil(img.shape[1] * s)), int(np.ceil(img.shape[0] * s))),
                         interpolation=cv2.INTER_CUBIC)
    y = rng.integers(0, img.shape[0] - H + 1)
    x = rng.integers(0, img.shape[1] - W + 1)
    return np.clip(img[y:y + H, x:x + W], 0.0, 1.0)


@dataclass(frozen=True)
class Scene:
    """A scene: reflectance of every pixel as abundances ``(H, W, K)`` times shading
    ``(H, W)`` over ``spectra`` ``(K, L)``."""

    name: str
    abundances: np.ndarray
    shading: np.ndarray
    spectra: np.ndarray
    spectra_names: tuple

    def reflectance(self) -> np.ndarray:
        """``(H * W, L)``: every pixel's reflectance spectrum."""
        a = self.abundances * self.shading[:, :, None]
        return a.reshape(-1, a.shape[-1]) @ self.spectra


def make_scene(image: str | None, shape, seed: int, wl, library=None) -> Scene:
    """A scene of ``shape`` from scikit-image's sample ``image`` (None: generated textures
    only, no scikit-image), seeded."""
    import cv2

    rng = np.random.default_rng(seed)
    lib, names = library if library is not None else spectral_library(wl)
    if image is None:
        img = np.stack([_fractal(shape, rng, b) for b in (2.2, 2.6, 3.0)], axis=2)
        blocks = (_fractal(shape, rng, 3.2) > 0.5).astype(np.float64)  # sharp edges
        img = 0.6 * img + 0.4 * blocks[:, :, None] * img[:, :, ::-1]
    else:
        img = _image(image, shape, rng)
    grey = img.mean(axis=2)
    feats = [img[:, :, 0], img[:, :, 1], img[:, :, 2],
             cv2.GaussianBlur(grey, (0, 0), 3.0), _fractal(shape, rng)]
    sharp = rng.uniform(3.0, 10.0)
    z = np.stack([(f - f.mean()) / max(f.std(), 1e-6) for f in feats], axis=2)
    z = z[:, :, rng.permutation(len(feats))[:N_ENDMEMBERS]] * sharp
    z -= z.max(axis=2, keepdims=True)
    ab = np.exp(z)
    ab /= ab.sum(axis=2, keepdims=True)
    pick = rng.choice(len(lib), N_ENDMEMBERS, replace=False)
    return Scene(f"{image or 'texture'}#{seed}", ab, 0.35 + 0.65 * grey, lib[pick],
                 tuple(names[i] for i in pick))


#: the simulated sensor: 12 bit, 0.3 DN per electron (a full well of about 13.5 ke- at full
#: scale), read noise 1 DN, no fixed pattern (PRNU, DSNU, dark current, leakage off)
PARAMS = SensorParams(prnu=0.0, dsnu_dn=0.0, dark_current_dn_per_ms=0.0,
                      leak_rate_dn_per_ms=0.0, bit_depth=12, conversion_gain_dn_per_e=0.3)


def frames_of(scene: Scene, sensor: BenchSensor, seed: int, levels=LIGHT_LEVELS):
    """The scene's truth ``(H, W, B)`` in DN/ms and, per light level, the raw rate frame
    ``(H, W)`` in DN/ms and its DQ (0.1 % flagged): ``(truth, {level: (frame, dq)})``."""
    H, W = scene.shading.shape
    wl = sensor.bands.wavelengths_nm
    illum = blackbody(3200.0, 1.0, wavelengths_nm=wl)
    refl = scene.reflectance()
    per_band = electron_rate(illum, sensor.bands, pixel_pitch_um=PARAMS.pixel_pitch_um,
                             reflectance=refl)  # e-/ms at 1 W/m^2
    out, truth = {}, {}
    rng = np.random.default_rng(seed)
    flagged = rng.random((H, W)) < FLAG_FRACTION
    dq = np.where(flagged, np.uint32(DQ.DEAD | DQ.DO_NOT_USE), np.uint32(0)).astype(np.uint32)
    params = PARAMS
    for i, (level, frac) in enumerate(levels.items()):
        k1 = per_band * params.conversion_gain_dn_per_e  # DN/ms at 1 W/m^2
        irr = frac * (params.full_scale_dn - params.dark_level_dn) / (
            np.percentile(k1, 99) * EXPOSURE_MS)
        sim = MosaicSensor((H, W), mosaic=sensor.mosaic, bands=sensor.bands, params=params,
                           seed=seed + i)
        labels = np.arange(H * W).reshape(H, W)
        cap = sim.capture(EXPOSURE_MS, illum.scaled(irr), reflectance=(labels, refl),
                          seed=seed + 17 * (i + 1))
        rate = (cap.frames[0].astype(np.float32) - np.float32(params.dark_level_dn)) / np.float32(
            EXPOSURE_MS)
        rate[flagged] = 0.0
        truth[level] = (k1 * irr).reshape(H, W, -1).astype(np.float32)
        out[level] = (rate, dq)
    return truth, out


# -- methods and metrics -----------------------------------------------------------------------

def reconstruct(method: str, frame, dq, mosaic: Mosaic) -> np.ndarray:
    """The cube ``(H, W, B)`` of ``method``; ``"tile"``'s one spectrum per tile is repeated
    over its tile's pixels (incomplete border tiles take their nearest complete tile)."""
    if method != "tile":
        return demosaic(frame, mosaic, method=method, dq=dq).cube
    cube, _ = tile_cube(frame, mosaic, dq=dq)
    ph, pw = mosaic.tile_shape
    oy, ox = tile_origin(frame.shape, mosaic)
    H, W = frame.shape
    iy = np.clip((np.arange(H) - oy) // ph, 0, cube.shape[0] - 1)
    ix = np.clip((np.arange(W) - ox) // pw, 0, cube.shape[1] - 1)
    return cube[iy][:, ix]


def _psnr_mask(t, e, mask, rng_):
    d = (t[mask] - e[mask]).astype(np.float64)
    mse = float(np.mean(d * d)) if d.size else float("nan")
    return float(10 * np.log10(rng_ ** 2 / mse)) if mse > 0 else float("inf")


def sam_degrees(t, e) -> np.ndarray:
    """Spectral angle (degrees) between the spectra of ``t`` and ``e`` at every pixel."""
    t = t.astype(np.float64)
    e = e.astype(np.float64)
    num = np.sum(t * e, axis=-1)
    den = np.linalg.norm(t, axis=-1) * np.linalg.norm(e, axis=-1)
    c = np.clip(num / np.where(den > 0, den, 1.0), -1.0, 1.0)
    return np.degrees(np.arccos(c))


def score(truth, est, dq, mosaic: Mosaic, correction=None) -> dict:
    """The figures of one reconstruction (module docstring), on the frame without a border of
    two tiles."""
    with np.errstate(divide="ignore"):  # a perfect reconstruction: PSNR inf
        return _score(truth, est, dq, mosaic, correction)


def _score(truth, est, dq, mosaic, correction):
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    ph, pw = mosaic.tile_shape
    m = 2 * max(ph, pw)
    t = truth[m:-m, m:-m].astype(np.float64)
    e = est[m:-m, m:-m].astype(np.float64)
    rng_ = float(t.max())
    B = t.shape[-1]
    psnr_b = [float(peak_signal_noise_ratio(t[:, :, b], e[:, :, b], data_range=rng_))
              for b in range(B)]
    ssim_b = [float(structural_similarity(t[:, :, b], e[:, :, b], data_range=rng_))
              for b in range(B)]
    sam = sam_degrees(t, e)
    import cv2
    mean = t.mean(axis=2).astype(np.float32)
    grad = np.hypot(cv2.Sobel(mean, cv2.CV_32F, 1, 0), cv2.Sobel(mean, cv2.CV_32F, 0, 1))
    edges = grad >= np.percentile(grad, 90)
    near = cv2.dilate((dq != 0).astype(np.uint8),
                      np.ones((2 * ph + 1, 2 * pw + 1), np.uint8))[m:-m, m:-m] > 0
    out = {"psnr_db": float(peak_signal_noise_ratio(t, e, data_range=rng_)),
           "psnr_band_db": psnr_b, "ssim": float(np.mean(ssim_b)), "ssim_band": ssim_b,
           "sam_median_deg": float(np.median(sam)),
           "sam_p95_deg": float(np.percentile(sam, 95)),
           "edges_psnr_db": _psnr_mask(t, e, edges, rng_),
           "edges_sam_median_deg": float(np.median(sam[edges])),
           "flat_psnr_db": _psnr_mask(t, e, ~edges, rng_),
           "near_flagged_psnr_db": _psnr_mask(t, e, near, rng_),
           "near_flagged_sam_median_deg": (float(np.median(sam[near])) if near.any()
                                           else float("nan"))}
    if correction is not None:
        tv, ev = t @ correction.T, e @ correction.T
        out["virtual_psnr_db"] = float(peak_signal_noise_ratio(tv, ev, data_range=float(
            np.abs(tv).max())))
    return out


def _speed(methods, mosaic: Mosaic, repeat: int) -> dict:
    """Mpx/s of each method on a 2048 x 1088 frame of ``mosaic`` with 0.1 % flagged pixels,
    the calls interleaved (a figure and its baseline see the same machine state)."""
    from ..batch.memory import reuse_freed_memory

    reuse_freed_memory()
    rng = np.random.default_rng(0)
    shape = (1088, 2048)
    raw = rng.uniform(20, 60, shape).astype(np.float32)
    dq = np.where(rng.random(shape) < FLAG_FRACTION, np.uint32(DQ.DEAD), np.uint32(0))
    times = {m: [] for m in methods}
    for _ in range(repeat + 1):
        for m in methods:
            t0 = time.perf_counter()
            reconstruct(m, raw, dq, mosaic)
            times[m].append(time.perf_counter() - t0)
    return {m: raw.size / float(np.median(v[1:])) / 1e6 for m, v in times.items()}


def run(shared: Path | None, *, half: str = "eval", shape=(160, 160), n_scenes: int | None = None,
        methods=METHODS, speed_repeat: int = 2, quiet: bool = False) -> dict:
    """Score every method on every scene of ``half`` ("eval" or "dev") for each sensor;
    returns the JSON document of the page (per-scene figures and medians)."""
    images = EVAL_IMAGES if half == "eval" else DEV_IMAGES
    seed0 = EVAL_SEED if half == "eval" else DEV_SEED
    if n_scenes is not None:
        images = images[:n_scenes]
    import os

    doc = {"half": half, "shape": list(shape), "methods": list(methods), "images": list(images),
           "light_levels": LIGHT_LEVELS, "sensors": {},
           "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    for sensor in sensors(shared):
        wl = sensor.bands.wavelengths_nm
        library = spectral_library(wl)
        per = {lv: {m: [] for m in methods} for lv in LIGHT_LEVELS}
        for i, image in enumerate(images):
            scene = make_scene(image, shape, seed0 + i, wl, library)
            truth, frames = frames_of(scene, sensor, seed0 + 100 + i)
            for lv, (frame, dq) in frames.items():
                for m in methods:
                    est = reconstruct(m, frame, dq, sensor.mosaic)
                    per[lv][m].append(score(truth[lv], est, dq, sensor.mosaic,
                                            sensor.correction))
            if not quiet:
                print(f"  {sensor.name}: scene {scene.name} done", flush=True)
        summary = {lv: {m: _median_figures(v) for m, v in ms.items()} for lv, ms in per.items()}
        speed = _speed(methods, sensor.mosaic, speed_repeat) if speed_repeat else {}
        doc["sensors"][sensor.name] = {
            "bands": sensor.mosaic.n_bands, "tile": list(sensor.mosaic.tile_shape),
            "band_centres_nm": [float(c) for c in sensor.bands.centres_nm],
            "scenes": [f"{im}#{seed0 + i}" for i, im in enumerate(images)],
            "per_scene": per, "summary": summary, "speed_mpx_s": speed}
    return doc


def _median_figures(rows: list[dict]) -> dict:
    out = {}
    for k, v in rows[0].items():
        if isinstance(v, list):
            out[k] = np.median(np.array([r[k] for r in rows]), axis=0).tolist()
        else:
            out[k] = float(np.median([r[k] for r in rows]))
    return out


# -- the page ----------------------------------------------------------------------------------

def render(doc: dict) -> str:
    """The Markdown report of :func:`run`'s document."""
    lines = ["# Spectral reconstruction against ground truth", ""]
    lines += [f"Evaluation scenes ({len(doc['images'])} per sensor, "
              f"{doc['shape'][1]} x {doc['shape'][0]} px, scikit-image samples "
              f"{', '.join(doc['images'])}; the methods were developed on other images and "
              "seeds). Each figure is the median over the scenes; PSNR and SSIM from "
              "`skimage.metrics` on the frame without a border of two tiles, SAM in degrees "
              "(median pixel and the 95th percentile: the 5 % worst). How the scenes, the truth "
              "and the frames are made: the module docstring of `hsiffc.reports.recon_bench`.",
              ""]
    for name, s in doc["sensors"].items():
        lines += [f"## {name} ({s['bands']} bands, {s['tile'][1]} x {s['tile'][0]} tile)", ""]
        for lv in doc["light_levels"]:
            frac = doc["light_levels"][lv]
            lines += [f"### {lv} light (99th-percentile pixel at {100 * frac:g} % of full "
                      "scale)", "",
                      "| method | PSNR (dB) | SSIM | SAM median (deg) | SAM 5 % worst (deg) | "
                      "PSNR on edges (dB) | PSNR near flagged (dB) | "
                      + ("PSNR after IMEC correction (dB) | " if name == "imec-ssm5x5" else "")
                      + "Mpx/s (2048 x 1088) |",
                      "|---|---|---|---|---|---|---|" + ("---|" if name == "imec-ssm5x5" else "")
                      + "---|"]
            for m, f in s["summary"][lv].items():
                sp = s["speed_mpx_s"].get(m)
                row = (f"| `{m}` | {f['psnr_db']:.2f} | {f['ssim']:.4f} | "
                       f"{f['sam_median_deg']:.3f} | {f['sam_p95_deg']:.3f} | "
                       f"{f['edges_psnr_db']:.2f} | {f['near_flagged_psnr_db']:.2f} | ")
                if name == "imec-ssm5x5":
                    row += f"{f['virtual_psnr_db']:.2f} | "
                row += (f"{sp:.1f} |" if sp is not None else "- |")
                lines.append(row)
            lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    """The command line (module docstring): writes ``recon_bench.md`` and ``.json`` to OUT."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="folder for recon_bench.md and recon_bench.json")
    ap.add_argument("--shared", type=Path, default=None,
                    help="the shared data folder (../shared/data) holding imec-ssm5x5; "
                         "without it only vis-4x4 is measured")
    ap.add_argument("--half", choices=("eval", "dev"), default="eval")
    ap.add_argument("--quick", action="store_true", help="two scenes, no timing")
    args = ap.parse_args(argv)
    if args.shared is not None and not (args.shared / IMEC_XML).is_file():
        print(f"note: {args.shared / IMEC_XML} not found: imec-ssm5x5 is skipped, only "
              "vis-4x4 is measured", file=sys.stderr)
    doc = run(args.shared, half=args.half, n_scenes=2 if args.quick else None,
              speed_repeat=0 if args.quick else 2)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "recon_bench.json").write_text(json.dumps(doc, indent=1) + "\n",
                                               encoding="utf-8")
    text = render(doc)
    (args.out / "recon_bench.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
