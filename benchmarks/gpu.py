"""GPU and CPU-scaling benchmark of the live correction (issue 42), one script for one device
call: equality of the GPU and CPU paths on the same frames, the GPU alone, raw in / cube out
through host memory with :meth:`~hsiffc.gpu.pipeline.GpuPipeline.stream`, and the CPU
pipeline at 1, 2, 4, 8 and 16 numba threads on the same machine.

Run (results as JSON and text under DIR; every section is written as soon as it is done, so
a run stopped by a time limit still leaves what it measured)::

    python3 benchmarks/gpu.py --out DIR [--shape 1088 2048] [--frames 60] [--quick]

Without a usable GPU the GPU sections record why and the CPU sections still run. Frames of
the simulator's 8-band 2 x 4 mosaic sensor (:class:`hsiffc.simulate.MosaicSensor`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

RESULTS: dict = {}


def save(out: Path) -> None:
    (out / "gpu_bench.json").write_text(json.dumps(RESULTS, indent=1, default=str))


def section(out: Path, name: str):
    def wrap(fn):
        t0 = time.perf_counter()
        try:
            RESULTS[name] = fn()
        except Exception as exc:  # noqa: BLE001 - record and go on with the next section
            RESULTS[name] = {"error": f"{type(exc).__name__}: {exc}",
                             "traceback": traceback.format_exc()[-3000:]}
        RESULTS.setdefault("section_s", {})[name] = round(time.perf_counter() - t0, 2)
        save(out)
        print(f"== {name} ({RESULTS['section_s'][name]} s): "
              f"{json.dumps(RESULTS[name], default=str)[:1500]}", flush=True)
        return fn
    return wrap


def median_s(fn, repeat: int, warm: int = 1) -> float:
    for _ in range(warm):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--shape", nargs=2, type=int, default=[1088, 2048])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--threads", nargs="*", type=int, default=[1, 2, 4, 8, 16])
    ap.add_argument("--skip-cpu", action="store_true")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shape = tuple(args.shape)
    npx = shape[0] * shape[1]

    import numba

    from hsiffc import gpu
    from hsiffc.frame import Frame
    from hsiffc.gpu import selfcheck

    @section(out, "environment")
    def _():
        env = {"python": sys.version.split()[0], "numpy": np.__version__,
               "numba": numba.__version__, "cpus": os.cpu_count(),
               "machine": platform.machine(), "shape": list(shape),
               "numba_threads_default": numba.config.NUMBA_NUM_THREADS}
        try:
            env["nvidia_smi"] = subprocess.run(
                ["nvidia-smi", "--query-gpu=name,memory.total,driver_version,clocks.sm",
                 "--format=csv,noheader"], capture_output=True, text=True,
                timeout=20).stdout.strip()
        except Exception as exc:  # noqa: BLE001
            env["nvidia_smi"] = f"unavailable: {exc}"
        env["gpu_available"] = gpu.available()
        env["gpu_why_not"] = gpu.why_unavailable()
        cuda = gpu.cuda_module()
        if cuda is not None:
            import numba_cuda
            env["numba_cuda"] = getattr(numba_cuda, "__version__", "?")
            if gpu.available() and not gpu.simulated():
                env["device"] = cuda.get_current_device().name
                env["device"] = env["device"].decode() if isinstance(env["device"], bytes) \
                    else env["device"]
        return env

    t0 = time.perf_counter()
    sensor, cal, raw = selfcheck.scene(shape)
    pipes = selfcheck.pipelines(cal)
    frame = Frame.from_raw(raw, exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
    RESULTS["scene_s"] = round(time.perf_counter() - t0, 1)
    # a few different frames for the stream (no cache effects from one frame)
    raws = [raw] + [sensor.capture(16.125, "lamp B", irradiance_w_m2=0.5 + 0.1 * i,
                                   seed=20 + i).frames[0] for i in range(3)]
    ok = gpu.available()

    if ok:
        @section(out, "gpu_device_only")
        def _():
            cuda = gpu.cuda_module()
            res = {}
            for name in ("correct", "correct+bilinear"):
                g = pipes[name].to("cuda")
                planes, _ = g._const(shape, 16.125, 10, sensor.mosaic)
                dev, _ = g._buffers(shape, planes.get("n_bands", 0), np.float32, np.uint32,
                                    False)
                d_raw = cuda.to_device(raw)
                d_dq = cuda.device_array((1, 1), np.uint32)
                st = cuda.stream()

                def run(n):
                    for _ in range(n):
                        g._launch(d_raw, d_dq, False, shape, 16.125, 10, sensor.mosaic, dev,
                                  0, False, False, st)
                    st.synchronize()
                run(3)  # compile and warm up
                reps = []
                for _ in range(5):
                    t = time.perf_counter()
                    run(20)
                    reps.append((time.perf_counter() - t) / 20)
                s = statistics.median(reps)
                res[name] = {"ms_per_frame": s * 1e3, "mpx_s": npx / s / 1e6,
                             "all_ms": [r * 1e3 for r in reps]}
            return res

        @section(out, "gpu_stream")
        def _():
            res = {}
            n = args.frames
            for name in ("correct+bilinear", "correct"):
                g = pipes[name].to("cuda")
                for dd, qd, copy, alpha in (("float32", "uint32", False, False),
                                            ("float16", "uint8", False, False),
                                            ("uint16", "uint8", False, False),
                                            ("float32", "uint32", True, False),
                                            ("float32", "uint32", False, True)):
                    if name == "correct" and (dd, copy, alpha) != ("float32", False, False):
                        continue
                    frames = (raws[i % len(raws)] for i in range(n + 4))
                    it = g.stream(frames, exposure_ms=16.125, bit_depth=10,
                                  mosaic=sensor.mosaic, data_dtype=dd, dq_dtype=qd,
                                  copy=copy, alpha=alpha)
                    for _ in range(4):  # warm up: buffers, compilation
                        next(it)
                    t = time.perf_counter()
                    k = 0
                    for item in it:
                        k += 1
                    s = (time.perf_counter() - t) / k
                    key = f"{name} {dd}/{qd}" + (" copy" if copy else "") + \
                        (" +alpha" if alpha else "")
                    res[key] = {"ms_per_frame": s * 1e3, "mpx_s": npx / s / 1e6,
                                "frames_s": 1 / s, "out_mb": item.data.nbytes / 1e6
                                + item.dq.nbytes / 1e6}
            return res

        @section(out, "equality")
        def _():
            res = {}
            for name, pipe in pipes.items():
                res[name] = selfcheck.compare(pipe, pipe.to("cuda"), frame)
            # compact types: the device's packing against pack_cpu of the CPU frame
            from hsiffc.gpu.pack import pack_cpu
            pipe = pipes["correct+bilinear"]
            cpu = pipe.transform(frame)
            for dd, qd in (("float16", "uint8"), ("uint16", "uint8")):
                item = next(iter(pipe.to("cuda").stream([frame], data_dtype=dd, dq_dtype=qd)))
                d, q = pack_cpu(cpu.data, cpu.dq, dd, qd)
                diff = np.abs(d.astype(np.float64) - item.data.astype(np.float64))
                res[f"pack {dd}/{qd}"] = {"max_abs_diff": float(diff.max()),
                                          "values_differ": int(np.count_nonzero(diff)),
                                          "dq_differ": int(np.count_nonzero(q != item.dq))}
            return res

    if not args.skip_cpu:
        @section(out, "cpu_threads")
        def _():
            from hsiffc.calibrate import calibrate
            from hsiffc.simulate import PAPER_LIGHT_W_M2
            from hsiffc.stages import Pipeline, create
            res = {}
            train = Frame.list_from_sweep(sensor.sweep([19.35, 25.8], "lamp A",
                                                       irradiance_w_m2=PAPER_LIGHT_W_M2[
                                                           "training"], n_frames=4, seed=2))
            cube_b = create("reconstruct", method="bilinear").fit([])
            cube_p = create("reconstruct", method="ppid").fit([])
            front = Pipeline([("dark", create("dark", calibration=cal)),
                              ("mask", create("alpha_mask", calibration=cal)),
                              ("ffc", create("two_point_ffc", calibration=cal))]).fit(train)
            base = pipes["correct"]
            work = {"front end": front, "default correct": base,
                    "+ bilinear": Pipeline(base.steps + [("cube", cube_b)]),
                    "+ ppid": Pipeline(base.steps + [("cube", cube_p)])}
            sweep = sensor.sweep(np.round(np.geomspace(2, 400, 20), 3), "lamp A",
                                 irradiance_w_m2=0.25 * PAPER_LIGHT_W_M2["training"],
                                 n_frames=1, seed=1)
            for p in work.values():  # compile every kernel first
                p.transform(frame)
            calibrate(sweep)
            maxt = numba.config.NUMBA_NUM_THREADS
            for n in args.threads:
                if n > maxt:
                    continue
                numba.set_num_threads(n)
                row = {}
                for name, p in work.items():
                    s = median_s(lambda: p.transform(frame), 3 if args.quick else 5)
                    row[name] = {"ms": s * 1e3, "mpx_s": npx / s / 1e6}
                t = time.perf_counter()
                calibrate(sweep)
                row["calibrate 20 exposures"] = {"s": time.perf_counter() - t}
                res[str(n)] = row
                save(out)
            numba.set_num_threads(maxt)
            return res

    # the text summary
    lines = [f"hsiffc GPU benchmark, frames {shape[1]} x {shape[0]} ({npx / 1e6:.2f} Mpx)"]
    env = RESULTS.get("environment", {})
    lines.append(f"device: {env.get('device', env.get('gpu_why_not'))}; nvidia-smi: "
                 f"{env.get('nvidia_smi')}; CPUs {env.get('cpus')}; numba {env.get('numba')}, "
                 f"numba-cuda {env.get('numba_cuda')}, numpy {env.get('numpy')}")
    for key in ("gpu_device_only", "gpu_stream"):
        for name, r in RESULTS.get(key, {}).items():
            if isinstance(r, dict) and "mpx_s" in r:
                lines.append(f"{key:16s} {name:40s} {r['ms_per_frame']:8.3f} ms "
                             f"{r['mpx_s']:9.1f} Mpx/s")
    for name, r in RESULTS.get("equality", {}).items():
        lines.append(f"equality {name}: {r}")
    for n, row in RESULTS.get("cpu_threads", {}).items():
        if isinstance(row, dict) and "front end" in row:
            lines.append(f"cpu {n:>2} threads: " + ", ".join(
                f"{k} {v['mpx_s']:.0f} Mpx/s" if "mpx_s" in v else f"{k} {v['s']:.2f} s"
                for k, v in row.items()))
    (out / "gpu_bench.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
