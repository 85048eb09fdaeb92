"""Pipeline benchmark: dark, alpha mask, two-point FFC and reconstruction on 2048 x 1088 frames,
against a plain numpy two-point correction ``(raw - dark) * gain`` of the same frames."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from numba import njit, prange

from benchutil import figure, interleaved_medians, median_time, row
from hsiffc.calibrate import calibrate
from hsiffc.data.frame import Frame
from hsiffc.kernels import modelffc
from hsiffc.kernels.demosaic import interpolate_bands
from hsiffc.batch.memory import reuse_freed_memory
from hsiffc.reconstruct.demosaic import _alpha_plane, _ppi_window_max
from hsiffc.reconstruct.prepare import band_levels, prepare, pseudo_panchromatic
from hsiffc.simulate import PAPER_LIGHT_W_M2, MosaicSensor
from hsiffc.stages import Pipeline, create

SHAPE = (1088, 2048)
TRAIN = PAPER_LIGHT_W_M2["training"]

# The cube pipelines again in a child process with glibc's default allocator settings (no
# hsiffc.batch.memory.reuse_freed_memory): every frame's 71 MB cubes are then fresh pages.
_DEFAULT_ALLOCATOR_CHILD = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from benchutil import median_time
from hsiffc.data.frame import Frame
from hsiffc.data.mosaic import Mosaic
from hsiffc.stages import Pipeline
spec = json.loads(sys.argv[2])
test = Frame.from_raw(np.load(spec["raw"]), exposure_ms=spec["exposure_ms"], bit_depth=10,
                      mosaic=Mosaic.from_dict(spec["mosaic"]))
out = {}
for method, path in spec["pipelines"].items():
    pipe = Pipeline.load(path)
    out[method] = median_time(lambda: pipe.transform(test), repeat=spec["repeat"])
print(json.dumps(out))
"""


def _default_allocator_times(tmp: Path, pipes: dict, test_raw, exposure_ms, mosaic,
                             repeat: int) -> dict:
    """Median seconds per frame of each pipeline in ``pipes`` (method -> Pipeline) in a child
    process without the allocator setting (:mod:`hsiffc.batch.memory`)."""
    np.save(tmp / "test_raw.npy", test_raw)
    paths = {m: str(p.save(tmp / f"pipe_{m}.npz")) for m, p in pipes.items()}
    spec = {"raw": str(tmp / "test_raw.npy"), "exposure_ms": exposure_ms,
            "mosaic": mosaic.to_dict(), "pipelines": paths, "repeat": repeat}
    out = subprocess.run([sys.executable, "-c", _DEFAULT_ALLOCATOR_CHILD,
                          str(Path(__file__).resolve().parent), json.dumps(spec)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@njit(parallel=True, error_model="numpy")
def _fused_floor(raw, dark, a, b, flags, gain, out, alpha, dq):
    """Reads the six planes dark + alpha mask + two-point FFC with DQ need per pixel (raw,
    dark, a, b, the calibration's flags, gain) and writes its three (data, alpha, DQ) with
    next to no arithmetic: the speed even a single fused pass cannot beat on this machine
    (compiled here, not cached: a baseline of this benchmark, not of the package)."""
    for i in prange(raw.shape[0]):
        s = raw[i] - dark[i]
        out[i] = s * gain[i]
        alpha[i] = a[i] * b[i]
        dq[i] = flags[i] | np.uint32(s > 0)


@njit(parallel=True)
def _cube_floor(cube, cube_dq, cube_alpha):
    """Writes the three (H, W, B) cubes of a reconstruction once with constants: the floor of
    the reconstruction's output, whatever computes it."""
    for y in prange(cube.shape[0]):
        for x in range(cube.shape[1]):
            for band in range(cube.shape[2]):
                cube[y, x, band] = 1.0
                cube_dq[y, x, band] = 0
                cube_alpha[y, x, band] = 0.0


def _floors(raw32, dark, gain, n_bands: int, repeat: int) -> dict:
    """Same-run floors (fresh outputs each call, as the stages allocate theirs)."""
    n = raw32.size
    flat = [np.ascontiguousarray(v, np.float32).reshape(-1) for v in (raw32, dark, gain)]
    ab = np.full(n, 1e-3, np.float32)
    flags = np.zeros(n, np.uint32)

    def fused():
        _fused_floor(flat[0], flat[1], ab, ab, flags, flat[2], np.empty(n, np.float32),
                     np.empty(n, np.float32), np.empty(n, np.uint32))

    shape = raw32.shape + (n_bands,)

    def cubes():
        _cube_floor(np.empty(shape, np.float32), np.empty(shape, np.uint32),
                    np.empty(shape, np.float32))

    fused()
    cubes()
    return {"fused_floor_s": median_time(fused, repeat=repeat),
            "cube_floor_s": median_time(cubes, repeat=repeat)}


def _ppid_parts(frame, repeat: int) -> dict:
    """Where the PPID cube's time goes, each part alone on the frame the cube stage receives:
    checking the frame (prepare) with the band levels (medians: cached per prepared frame, so
    timed with a fresh one), the PPI image, the interpolation kernel (cube and DQ) and the
    alpha (the PPI window's max, one plane for every band), as
    :func:`hsiffc.reconstruct.demosaic` runs them."""
    mosaic = frame.mosaic
    p = prepare(frame.data, mosaic, frame.dq)
    shape = (*p.shape, mosaic.n_bands)

    def levels():
        return band_levels(prepare(frame.data, mosaic, frame.dq))  # medians are cached per p

    lv = levels()
    ppi, ppi_ok = pseudo_panchromatic(p, lv)

    def kernel():
        interpolate_bands(p.raw, p.dq, None, ppi, ppi_ok, lv, p.lattices(), mosaic.tile_shape,
                          np.empty(shape, np.float32), np.empty(shape, np.uint32), None)

    def alpha():
        return _ppi_window_max(_alpha_plane(frame.alpha, p.shape), mosaic)

    return {"prepare_and_band_levels": median_time(levels, repeat=repeat) * 1e3,
            "ppi_image": median_time(lambda: pseudo_panchromatic(p, lv), repeat=repeat) * 1e3,
            "interpolation": median_time(kernel, repeat=repeat) * 1e3,
            "alpha_window_max": median_time(alpha, repeat=repeat) * 1e3}


def _front_end_parts(front, frame, repeat: int) -> dict:
    """The fused front end's parts alone, as the pipeline's
    :class:`~hsiffc.stages.fusion.FusedFrontEnd` runs them: the pass of dark, alpha, DQ and the
    FFC's per-band test level (one kernel, :meth:`~hsiffc.stages.fusion.FusedFrontEnd.fused_pass`),
    and the two-point FFC's finish (the gain: one more pass). The finish gets the same DQ plane
    every time: it only adds flags to it where a value is not finite (idempotent), and a copy
    per call would be timed with it."""
    unit = front.plan.units[0]
    (_, dark), (_, mask), (_, ffc) = front.steps
    *_, dq, test_mean = unit.fused_pass(frame, 3)
    masked = mask.transform(dark.transform(frame))
    return {"dark_alpha_dq_pass": median_time(lambda: unit.fused_pass(frame, 3),
                                              repeat=repeat) * 1e3,
            "ffc_finish": median_time(lambda: ffc.corrected(masked, dq, test_mean),
                                      repeat=repeat) * 1e3}


def _parallel_equals_serial(default, frame) -> bool:
    """The model_ffc stage's output with the kernel's parallel build (what a frame this size
    runs) equals the serial build's, bit for bit (the test suite checks the serial build; the
    parallel one is left to this benchmark because its compile costs ~45 s on a clean
    machine)."""
    f = default.steps[0][1].transform(frame)
    f = default.steps[1][1].transform(f)
    stage = default.steps[2][1]
    par = stage.transform(f)
    kernel = modelffc.model_ffc_kernel
    saved = kernel.parallel
    kernel.parallel = kernel.serial  # Kernel picks .parallel for frames this size
    try:
        ser = stage.transform(f)
    finally:
        kernel.parallel = saved
    return bool(np.array_equal(par.data, ser.data) and np.array_equal(par.dq, ser.dq))


def main(quick: bool = False) -> dict:
    shape = (272, 512) if quick else SHAPE
    npx = shape[0] * shape[1]
    repeat = 3 if quick else 5
    # as in hsiffc correct: a frame's large arrays reuse the last frame's memory (a child
    # process measures the cube pipelines without it, below)
    allocator = reuse_freed_memory()
    print(f"Pipeline benchmark on {shape[1]} x {shape[0]} frames ({npx / 1e6:.2f} Mpx), median "
          f"of {repeat} runs" + (" -- QUICK MODE" if quick else "")
          + ("; allocator: freed memory reused (hsiffc.batch.memory)" if allocator else ""))
    sensor = MosaicSensor(shape, seed=0)
    # a calibration from a small sweep of the same sensor (its time is not part of this figure)
    sweep = sensor.sweep(np.round(np.geomspace(2, 400, 12), 3), "lamp A",
                         irradiance_w_m2=0.25 * TRAIN, n_frames=1, seed=1)
    cal = calibrate(sweep)
    del sweep
    tmp = Path(tempfile.mkdtemp())
    cal_path = cal.save(tmp / "cal.npz")
    train = Frame.list_from_sweep(sensor.sweep([19.35, 25.8], "lamp A", irradiance_w_m2=TRAIN,
                                               n_frames=4, seed=2))
    test_raw = sensor.capture(16.125, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"],
                              seed=3).frames[0]
    test = Frame.from_raw(test_raw, exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
    results = {"allocator_reuses_freed_memory": allocator}
    pipes = {}
    for method in ("bilinear", "ppid"):
        pipe = pipes[method] = Pipeline([
            ("dark", create("dark", match="scale")),
            ("mask", create("alpha_mask", calibration=str(cal_path))),
            ("ffc", create("two_point_ffc", calibration=str(cal_path))),
            ("cube", create("reconstruct", method=method))]).fit(train)
        t = median_time(lambda: pipe.transform(test), repeat=repeat)
        results[f"pipeline_{method}_mpx_s"] = npx / t / 1e6
        results[f"pipeline_{method}_s"] = t
    default_alloc = _default_allocator_times(tmp, pipes, test_raw, 16.125, sensor.mosaic,
                                             repeat)
    results["default_allocator_s"] = default_alloc
    stage_ms = {}
    front = Pipeline(pipe.steps[:3])
    # the plain numpy baseline: the same dark and gain, no flags, no alpha, no cube
    ffc = pipe.named_steps["ffc"]
    dark = pipe.named_steps["dark"].dark_for(16.125, shape)[0]
    gain = ffc.gain_
    raw32 = test_raw.astype(np.float32)
    # the front end, the same three stages one by one (each its own pass) and the baseline,
    # taken in turn (their ratio is a target)
    times = interleaved_medians({"front": lambda: front.transform(test),
                                 "unfused": lambda: front.transform(test, fuse=False),
                                 "plain": lambda: (raw32 - dark) * gain}, repeat=3 * repeat)
    t_front, t_unfused, t_plain = times["front"], times["unfused"], times["plain"]
    results["front_end_parts_ms"] = _front_end_parts(front, test, repeat)
    floors = _floors(raw32, dark, gain, sensor.mosaic.n_bands, repeat)
    results.update(floors)
    # hsiffc correct's default: dark and alpha mask from the calibration, model_ffc (leakage
    # inversion and the calibration's responsivity) instead of the two-point flat
    default = Pipeline([("dark", create("dark", calibration=cal).fit([])),
                        ("mask", create("alpha_mask", calibration=cal).fit([])),
                        ("ffc", create("model_ffc", calibration=cal).fit([]))])
    default.transform(test)  # compiled (or loaded from the cache) before timing
    t_default = median_time(lambda: default.transform(test), repeat=repeat)
    results["default_correct_mpx_s"] = npx / t_default / 1e6
    results["model_ffc_parallel_equals_serial"] = _parallel_equals_serial(default, test)
    f = test
    for name, stage in default.steps:
        stage_ms[f"default_{name}"] = median_time(lambda s=stage.prepare(), f=f: s.transform(f),
                                                  repeat=repeat) * 1e3
        f = stage.transform(f)
    results["dark_mask_ffc_mpx_s"] = npx / t_front / 1e6
    results["plain_numpy_two_point_mpx_s"] = npx / t_plain / 1e6
    for method in ("bilinear", "ppid"):
        results[f"ratio_plain_over_pipeline_{method}"] = results[f"pipeline_{method}_s"] / t_plain
    results["ratio_plain_over_dark_mask_ffc"] = t_front / t_plain
    results["dark_mask_ffc_unfused_mpx_s"] = npx / t_unfused / 1e6
    results["ratio_plain_over_default_correct"] = t_default / t_plain
    # where the time goes: every stage alone on the frame it receives in the pipeline, prepared
    # once as the pipeline's plan holds it (Stage.prepare), so only the per-frame work counts
    frame = test
    for name, stage in pipe.steps[:3] + [("cube_bilinear", create("reconstruct",
                                                                    method="bilinear")),
                                         ("cube_ppid", create("reconstruct", method="ppid"))]:
        stage_ms[name] = median_time(lambda s=stage.prepare(), f=frame: s.transform(f),
                                     repeat=repeat) * 1e3
        if not name.startswith("cube"):
            frame = stage.transform(frame)
    # the cube's cost depends on the flagged samples (never sources: a value whose nearest
    # samples are all flagged takes the wider support, value by value)
    results["flagged_fraction"] = float(np.count_nonzero(frame.dq)) / frame.dq.size
    # by the DQ rule, a cube value carries a flag exactly where its one-tile support (S1) holds
    # no unflagged sample: those values are estimated one by one from the twice-wide support
    cube_dq = create("reconstruct", method="bilinear").transform(frame).dq
    results["cube_values_from_wide_support"] = float(np.count_nonzero(cube_dq)) / cube_dq.size
    del cube_dq
    unflagged = frame.replace(dq=np.zeros_like(frame.dq))
    for method in ("bilinear", "ppid"):
        stage = create("reconstruct", method=method)
        stage_ms[f"cube_{method}_no_flags"] = median_time(
            lambda s=stage: s.transform(unflagged), repeat=repeat) * 1e3
    results["stage_ms"] = stage_ms
    results["ppid_parts_ms"] = _ppid_parts(frame, repeat)
    print(row("full pipeline, PPID reconstruction", results["pipeline_ppid_mpx_s"], "Mpx/s",
              f"{results['pipeline_ppid_s'] * 1e3:.0f} ms/frame, "
              f"{results['ratio_plain_over_pipeline_ppid']:.1f} x the plain numpy time"))
    print(row("full pipeline, bilinear reconstruction", results["pipeline_bilinear_mpx_s"],
              "Mpx/s", f"{results['pipeline_bilinear_s'] * 1e3:.0f} ms/frame, "
              f"{results['ratio_plain_over_pipeline_bilinear']:.1f} x the plain numpy time"))
    alloc_note = {}
    for method in ("ppid", "bilinear"):
        t_def = default_alloc[method]
        alloc_note[method] = (f"; in a process with glibc's default allocator settings (fresh "
                              f"pages for every cube): {npx / t_def / 1e6:.1f} Mpx/s, "
                              f"{t_def * 1e3:.0f} ms/frame")
        print(row(f"  {method}, default allocator (child process)", npx / t_def / 1e6, "Mpx/s",
                  f"{t_def * 1e3:.0f} ms/frame: every cube in fresh pages; x"
                  f"{t_def / results[f'pipeline_{method}_s']:.2f} the time with reuse"))
    print(row("dark + alpha mask + two-point FFC (no cube)", results["dark_mask_ffc_mpx_s"],
              "Mpx/s", f"{t_front * 1e3:.1f} ms/frame, "
              f"{results['ratio_plain_over_dark_mask_ffc']:.2f} x the plain numpy time"))
    fparts = results["front_end_parts_ms"]
    rest_ms = t_front * 1e3 - fparts["dark_alpha_dq_pass"] - fparts["ffc_finish"]
    print(row("  the same stages one by one (fuse=False)", results["dark_mask_ffc_unfused_mpx_s"],
              "Mpx/s", f"{t_unfused * 1e3:.1f} ms/frame; fused parts alone: dark + alpha + DQ "
              f"+ band level pass {fparts['dark_alpha_dq_pass']:.1f} ms, FFC gain "
              f"{fparts['ffc_finish']:.1f} ms, the rest (the two back to back, the frames, "
              f"the history) {rest_ms:.1f} ms"))
    print(row("dark + alpha mask + model_ffc (hsiffc correct's default)",
              results["default_correct_mpx_s"], "Mpx/s",
              f"{t_default * 1e3:.1f} ms/frame, "
              f"{results['ratio_plain_over_default_correct']:.1f} x the plain numpy time"))
    print(row("plain numpy (raw - dark) * gain", results["plain_numpy_two_point_mpx_s"], "Mpx/s",
              f"{t_plain * 1e3:.1f} ms/frame (baseline; timed in turn with the front end, "
              f"{3 * repeat} rounds)"))
    print("  where the time goes (each stage alone): " + ", ".join(
        f"{k} {v:.1f} ms" for k, v in stage_ms.items()))
    parts = results["ppid_parts_ms"]
    ppid_parts = ", ".join(f"{k.replace('_', ' ')} {v:.1f} ms" for k, v in parts.items())
    print(f"  PPID cube, each part alone: {ppid_parts}")
    speed = t_plain / t_front
    plain = results["plain_numpy_two_point_mpx_s"]
    breakdown = (f"; fused (one pass of dark, alpha, DQ and the FFC's per-band test level: "
                 f"{fparts['dark_alpha_dq_pass']:.1f} ms; the FFC's gain: "
                 f"{fparts['ffc_finish']:.1f} ms; the rest, the two back to back with the "
                 f"frames and history around them: {rest_ms:.1f} ms); "
                 f"the same stages one by one: {t_unfused * 1e3:.1f} ms; stages alone: "
                 + ", ".join(f"{k} {v:.1f} ms" for k, v in stage_ms.items()))
    fused_ratio = t_plain / results["fused_floor_s"]
    cube_ms = results["cube_floor_s"] * 1e3
    front_ms = t_front * 1e3
    best_bilinear = npx / (t_front + results["cube_floor_s"]) / 1e6
    print(row("floor: one pass moving the 6 planes in, 3 out", npx / results["fused_floor_s"]
              / 1e6, "Mpx/s", f"{results['fused_floor_s'] * 1e3:.2f} ms = {fused_ratio:.2f} x "
              "plain numpy"))
    print(row("floor: writing the three (H, W, 8) cubes", cube_ms, "ms",
              f"this front end + that floor: {best_bilinear:.0f} Mpx/s at best"))
    floor_note = (f"; floor: a single pass that only moves the 6 planes in (raw, dark, a, b, "
                  f"flags, gain) and 3 out (data, alpha, DQ) runs at {fused_ratio:.2f} x plain "
                  "numpy")
    cube_note = (f"; {100 * results['flagged_fraction']:.1f} % of this frame's pixels carry a "
                 f"DQ flag (they are never sources), and "
                 f"{100 * results['cube_values_from_wide_support']:.1f} % of the cube's values "
                 "have no unflagged sample within one tile (they carry a DQ flag) and are "
                 "estimated one by one from the twice-wide support: the bilinear cube takes "
                 f"{stage_ms['cube_bilinear']:.0f} ms, {stage_ms['cube_bilinear_no_flags']:.0f}"
                 f" ms with no flags (PPID {stage_ms['cube_ppid']:.0f} and "
                 f"{stage_ms['cube_ppid_no_flags']:.0f} ms); floor: writing the three fresh "
                 f"(H, W, 8) cubes alone takes {cube_ms:.0f} ms, so with this run's front end "
                 f"({front_ms:.1f} ms) the pipeline cannot pass {best_bilinear:.0f} Mpx/s")
    results["figures"] = [
        figure("dark + alpha mask + two-point FFC with DQ", results["dark_mask_ffc_mpx_s"],
               "Mpx/s", baseline=plain, baseline_name="plain numpy (raw - dark) * gain",
               ratio=speed, target=">= 0.5 x plain numpy", met=speed >= 0.5,
               note=f"ratio = speed relative to plain numpy{breakdown}{floor_note}"),
        figure("dark + alpha mask + model_ffc (hsiffc correct's default)",
               results["default_correct_mpx_s"], "Mpx/s", baseline=plain,
               baseline_name="plain numpy (raw - dark) * gain", ratio=t_plain / t_default,
               note="leakage inversion per pixel (float64); parallel build equals serial: "
               f"{results['model_ffc_parallel_equals_serial']}; stages alone: " + ", ".join(
                   f"{k.removeprefix('default_')} {v:.1f} ms" for k, v in stage_ms.items()
                   if k.startswith("default_"))),
        figure("full pipeline, bilinear cube (8 bands)", results["pipeline_bilinear_mpx_s"],
               "Mpx/s", baseline=plain, baseline_name="plain numpy (raw - dark) * gain",
               ratio=t_plain / results["pipeline_bilinear_s"], target=">= 100 Mpx/s",
               met=results["pipeline_bilinear_mpx_s"] >= 100,
               note="dark, alpha mask, two-point FFC, reconstruction with DQ and alpha cubes"
               " (allocator: freed memory reused, as in hsiffc correct: hsiffc.batch.memory)"
               + alloc_note["bilinear"] + cube_note),
        figure("full pipeline, PPID cube (8 bands)", results["pipeline_ppid_mpx_s"], "Mpx/s",
               baseline=plain, baseline_name="plain numpy (raw - dark) * gain",
               ratio=t_plain / results["pipeline_ppid_s"], target=">= 30 Mpx/s",
               met=results["pipeline_ppid_mpx_s"] >= 30,
               note="as above with PPID demosaicing (see the note above for the flags)"
               + alloc_note["ppid"] + f"; the PPID cube's parts alone: {ppid_parts}"),
    ]
    return results


if __name__ == "__main__":
    main()
