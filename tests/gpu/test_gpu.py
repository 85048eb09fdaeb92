"""The GPU path (hsiffc.gpu): refused in one line without a GPU, and its kernels equal to the
CPU path in numba's CUDA simulator (a child process with NUMBA_ENABLE_CUDASIM=1: the same
kernels, run on the CPU)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hsiffc import gpu
from hsiffc.cli import main
from hsiffc.data.dq import DQ
from hsiffc.gpu.pack import pack_cpu
from hsiffc.kernels.select import medians_of
from hsiffc.reconstruct.prepare import median_in_place

REPO = Path(__file__).resolve().parents[2]

needs_no_gpu = pytest.mark.skipif(gpu.available(), reason="a GPU is usable here")

#: first line of every simulator child: numba's CUDA simulator runs each simulated thread as a
#: Python thread while the launching thread polls them in a loop that holds the GIL for the
#: interpreter's switch interval (5 ms). Switching every 0.2 ms hands it on sooner: the child
#: of test_simulated_gpu_cube_equals_cpu took 52 s of CPU (user + system) with the default, 27
#: to 30 s with 0.2 ms, 39 s with 0.02 ms (/usr/bin/time, warm numba cache, load average 3-4)
SIMULATOR_SWITCH = "import sys; sys.setswitchinterval(2e-4)\n"


@needs_no_gpu
def test_device_cuda_without_a_gpu_is_one_line(tmp_path):
    with pytest.raises(gpu.GpuUnavailableError) as err:
        gpu.require("--device cuda")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("--device cuda: ")
    assert "GPU" in msg or "numba" in msg


@needs_no_gpu
def test_cli_device_cuda_exit_2_one_line(tmp_path, capsys):
    rc = main(["correct", str(tmp_path / "x.tif"), "--calibration", str(tmp_path / "c.npz"),
               "-o", str(tmp_path / "out"), "--device", "cuda"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--device cuda" in err


def test_pipeline_to_cpu_is_itself_and_bad_device_refused():
    from hsiffc.errors import ParameterError
    from hsiffc.stages import Pipeline, create

    pipe = Pipeline([("dark", create("dark")), ("mask", create("alpha_mask"))])
    assert pipe.to("cpu") is pipe
    with pytest.raises(ParameterError, match="device='tpu'"):
        pipe.to("tpu")


def test_pack_rules_flag_what_they_clip():
    data = np.array([[-3.0, 0.4, 70000.0, 65504.0, 1e6, -1e6, 12.5, 13.5]], np.float32)
    dq = np.array([[0, 0, 0, 0, 0, 0, int(DQ.OUT_OF_DOMAIN), 0]], np.uint32)
    u16, q16 = pack_cpu(data, dq, "uint16", "uint8")
    assert u16.dtype == np.uint16 and q16.dtype == np.uint8
    assert u16.tolist() == [[0, 0, 65535, 65504, 65535, 0, 13, 14]]  # floor(v + 0.5)
    assert q16[0, 0] == DQ.BELOW_DARK and q16[0, 2] == DQ.SATURATED and q16[0, 1] == 0
    assert q16[0, 6] == DQ.DO_NOT_USE  # OUT_OF_DOMAIN (bit 11) folded into DO_NOT_USE
    h, qh = pack_cpu(data, dq, "float16", "uint32")
    assert h.dtype == np.float16 and np.isfinite(h).all()
    assert qh[0, 4] == DQ.SATURATED and qh[0, 5] == DQ.SATURATED and qh[0, 3] == 0
    assert qh[0, 6] == DQ.OUT_OF_DOMAIN  # uint32: nothing folded


def test_parallel_band_medians_equal_numpy_partition():
    rng = np.random.default_rng(4)
    for n in (0, 1, 2, 7, 10, 1001):
        rows = [rng.normal(100, 30, n).astype(np.float32), np.round(rng.normal(5, 2, n))]
        buf = np.zeros((2, max(n, 1)), np.float32)
        for i, r in enumerate(rows):
            buf[i, :n] = r
        want = [median_in_place(np.asarray(r, np.float32).copy()) for r in rows]
        assert medians_of(buf, np.array([n, n])).tolist() == want


_CHILD = r"""
import json, sys
import numpy as np
from hsiffc.data.frame import Frame
from hsiffc.gpu import available, selfcheck
from hsiffc.gpu.pack import pack_cpu
from hsiffc.gpu.pipeline import GpuPipeline
assert available()
GpuPipeline.block = (8, 4)  # few simulated threads per block: the simulator runs each in Python
shape = tuple(int(v) for v in sys.argv[2].split("x"))
sensor, cal, raw = selfcheck.scene(shape, n_exposures=8)
frame = Frame.from_raw(raw, exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
holed = selfcheck.holed(frame)
pipes = selfcheck.pipelines(cal)
more = selfcheck.more_pipelines(sensor, cal)
out = {}
for name in sys.argv[1].split(","):
    if name in more:  # two-point FFC + nearest on the holed frame; PPID on a block so large
        pipe = more[name]  # that the PPI is undefined at its centre
        test = selfcheck.hollow(frame) if "ppid" in name else holed
        out[name + (" hollow" if "ppid" in name else " holed")] = selfcheck.compare(
            pipe, pipe.to("cuda"), test)
        continue
    pipe = pipes[name]
    g = pipe.to("cuda")
    out[name + " holed"] = selfcheck.compare(pipe, g, holed)
    cpu = pipe.transform(holed)
    item, = g.stream([holed], data_dtype="uint16", dq_dtype="uint8", copy=False)
    d, q = pack_cpu(cpu.data, cpu.dq, "uint16", "uint8")
    out[name + " stream uint16/uint8"] = bool(np.array_equal(item.data, d)
                                              and np.array_equal(item.dq, q))
    if len(sys.argv) > 3:  # raw arrays in, float16 out, on the GPU and the CPU
        plain = pipe.transform(frame)
        d, q = pack_cpu(plain.data, plain.dq, "float16", "uint32")
        opts = dict(exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic, data_dtype="float16")
        item, = g.stream([raw], **opts)
        out[name + " raw float16"] = bool(np.array_equal(item.data, d) and np.array_equal(item.dq, q))
        item, = pipe.stream([raw], **opts)
        out[name + " cpu stream"] = bool(np.array_equal(item.data, d))
if len(sys.argv) <= 3:  # PPID's band levels: numpy's pairwise mean, for several band counts
    from hsiffc.gpu import cuda_module, kernels
    cuda = cuda_module()
    rng = np.random.default_rng(1)
    same = []
    for n in (1, 3, 8, 13, 25, 32):
        for med in (rng.uniform(1, 900, n).astype(np.float32),
                    np.r_[rng.uniform(1, 9, n - 1), -1.0][:n].astype(np.float32)):
            lv, inv = np.zeros(n), np.zeros(n, np.float32)
            kernels.band_levels[1, 1](med, lv, inv)
            m = med.astype(np.float64)
            want = (m / m.mean() if np.all(m > 0) else np.ones(n))
            same.append(bool(np.array_equal(lv, want)
                             and np.array_equal(inv, (1.0 / want).astype(np.float32))))
    out["band levels"] = same
    # the exact band medians (radix select) against the CPU's, on frames with ties, negative
    # values and flagged samples (odd and even counts per band)
    from hsiffc.reconstruct.prepare import band_medians, prepare
    g = pipes["mask+bilinear"].to("cuda")
    planes, _ = g._const(shape, 16.125, 10, sensor.mosaic)
    bufs, _ = g._buffers(shape, planes, np.float32, np.uint32, False)
    meds = []
    for k, data in enumerate((rng.normal(300, 80, shape), np.round(rng.normal(3, 2, shape)),
                              rng.normal(0, 1e-3, shape) * rng.choice([1, 1e6], shape))):
        data = data.astype(np.float32)
        dq = (rng.random(shape) < 0.1 * k).astype(np.uint32)
        bufs["frame"].copy_to_device(data)
        bufs["fdq"].copy_to_device(dq)
        dev = g._medians(planes, bufs, 0, always=True).copy_to_host()
        want = band_medians(prepare(data, sensor.mosaic, dq), range(planes["n_bands"]))
        meds.append(bool(np.array_equal(dev.astype(np.float64), want)))
    out["band medians"] = meds
if len(sys.argv) <= 3:  # the spectral correction matrix after the cube
    from hsiffc.stages import Pipeline
    pipe = selfcheck.matrix_pipeline(Pipeline(pipes["mask+bilinear"].steps[:2]))
    out["matrix holed"] = selfcheck.compare_matrix(pipe, pipe.to("cuda"), holed)
print("RESULT " + json.dumps(out))
"""


def _simulate(names: str, shape: str, *more: str) -> dict:
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    run = subprocess.run([sys.executable, "-c", SIMULATOR_SWITCH + _CHILD, names, shape, *more],
                         capture_output=True, text=True,
                         env=env, cwd=REPO, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    line = [x for x in run.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def _assert_equal(res: dict) -> None:
    for key, r in res.items():
        if isinstance(r, dict) and "err_in_eps_of_terms" in r:  # float32 sums, any order
            assert r["err_in_eps_of_terms"] <= 4.0, (key, r)
            assert r["dq_differ"] == 0 and r["alpha_differ"] == 0, (key, r)
            assert r["history_equal"] and r["meta_equal"], (key, r)
        elif isinstance(r, dict):  # the simulator runs the kernels in float arithmetic of the
            assert r["data_ulps_of_value"] == 0.0, (key, r)  # CPU: equal bit for bit
            assert r["dq_differ"] == 0 and r.get("alpha_differ", 0) == 0, (key, r)
            assert r["history_equal"] and r["meta_equal"], (key, r)
        elif isinstance(r, list):
            assert all(r), (key, r)
        else:
            assert r, key


def test_simulated_gpu_cube_equals_cpu():
    """Dark + alpha mask + bilinear cube on a frame with a block of DEAD pixels (the
    twice-wide tent and the band medians on the device, found only because values need
    them, and filled there), also streamed in compact types, and with a spectral correction
    matrix after the cube (within float32 rounding of its terms: BLAS sums in another
    order); the two-point FFC (eq. 5's band levels summed on the device) with a nearest cube;
    PPID (band levels, PPI, its alpha window, the PPI-undefined fallback) on a larger block;
    the band levels' mean against numpy's for 1 to 32 bands. All bit for bit in the
    simulator (its arithmetic is the CPU's)."""
    _assert_equal(_simulate("mask+bilinear,two_point+nearest,mask+ppid", "12x16"))


@pytest.mark.slow
def test_simulated_gpu_model_ffc_equals_cpu():
    """The default correction (model FFC through invert_point) with and without the cube,
    from frames and from raw arrays; slow: the scalar inversion compiles for the CPU in the
    child and the simulator runs every thread in Python (minutes). The default run covers the
    mask and cube kernels above; benchmarks/gpu.py checks the model FFC on a device."""
    _assert_equal(_simulate("correct,correct+bilinear", "16x24", "raw"))


def test_results_page_is_what_the_benchmark_measured():
    """docs/results/gpu.md is rendered from the committed outputs of benchmarks/gpu.py."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_gpu", REPO / "benchmarks" / "gpu.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    runs = mod.page_runs(REPO / "docs" / "results" / "gpu")
    assert (REPO / "docs" / "results" / "gpu.md").read_text() == mod.render_page(runs), (
        "docs/results/gpu.md is stale or edited: python3 benchmarks/gpu.py --page "
        "docs/results/gpu.md")
    gpu_run = runs[mod.PAGE_RUNS["gpu"]]
    assert "H100" in gpu_run["environment"]["nvidia_smi"]
    assert gpu_run["equality"]["within tolerance"] is True
    for name in mod.PAGE_RUNS["cpu"]:  # full runs: every thread count measured
        assert {"1", "2", "4", "8", "16"} <= set(runs[name]["cpu_threads"])


def test_plan_refuses_steps_the_gpu_does_not_run_in_one_line():
    from hsiffc.errors import ParameterError
    from hsiffc.gpu.pipeline import plan
    from hsiffc.stages import Pipeline, create

    dark, mask = ("dark", create("dark")), ("mask", create("alpha_mask"))
    cases = {"resolution='tile'": [dark, mask, ("cube", create("reconstruct",
                                                               resolution="tile"))],
             "polynomial_ffc": [dark, mask, ("ffc", create("polynomial_ffc"))],
             "step 'mask' is not dark": [mask]}
    for word, steps in cases.items():
        with pytest.raises(ParameterError) as err:  # plan reads only .steps (a Pipeline
            plan(SimpleNamespace(steps=steps))  # would refuse the unfitted stages first)
        assert word in str(err.value) and "\n" not in str(err.value)
        assert "device='cpu'" in str(err.value)


_EDGES = r"""
import json
import numpy as np
from hsiffc.data.frame import Frame
from hsiffc.gpu import selfcheck
from hsiffc.gpu.pipeline import GpuPipeline
GpuPipeline.block = (8, 4)
sensor, cal, raw = selfcheck.scene((12, 16), n_exposures=8)
pipe = selfcheck.pipelines(cal)["mask+bilinear"]
g = pipe.to("cuda")
same = lambda a, b: bool(np.array_equal(a.data, b.data) and np.array_equal(a.dq, b.dq))
out = {}
f0 = Frame.from_raw(raw, exposure_ms=0.0, bit_depth=10, mosaic=sensor.mosaic)
out["exposure 0 (the CPU's own case)"] = same(g.transform(f0), pipe.transform(f0))
rf = raw.astype(np.float32)
rf[3, 5], rf[7, 2] = np.nan, np.inf
cpu, = pipe.stream([rf], exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
out["non-finite raw"] = [same(i, cpu) for i in g.stream([rf, rf], exposure_ms=16.125,
                                                       bit_depth=10, mosaic=sensor.mosaic)]
fr = [Frame.from_raw(raw, exposure_ms=e, bit_depth=10, mosaic=sensor.mosaic)
      for e in (16.125, 8.0, 16.125)]
views = [(i.data.copy(), i.dq.copy()) for i in g.stream(fr, copy=False)]
out["two slots, two exposures"] = [bool(np.array_equal(d, pipe.transform(f).data)
                                        and np.array_equal(q, pipe.transform(f).dq))
                                   for (d, q), f in zip(views, fr)]
print("RESULT " + json.dumps(out))
"""


@pytest.mark.slow
def test_simulated_gpu_stream_edges():
    """A 0 ms exposure goes through the CPU pipeline inside the stream; non-finite raw values
    as Frame.from_raw reads them; frames of two exposures alternate between the two slots."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    run = subprocess.run([sys.executable, "-c", SIMULATOR_SWITCH + _EDGES],
                         capture_output=True, text=True,
                         env=env, cwd=REPO, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    res = json.loads([x for x in run.stdout.splitlines() if x.startswith("RESULT ")][-1][7:])
    _assert_equal(res)


_BATCH = r"""
import json, sys
from dataclasses import replace
from pathlib import Path
import numpy as np
from hsiffc.batch import correct_batch
from hsiffc.gpu import selfcheck
from hsiffc.gpu.pipeline import GpuPipeline
from hsiffc.io import read_corrected, write_sweep
from hsiffc.simulate import PAPER_LIGHT_W_M2
GpuPipeline.block = (8, 4)
tmp = Path(sys.argv[1])
sensor, cal, _ = selfcheck.scene((12, 16), n_exposures=8)
cal_path = cal.save(tmp / "cal.npz")
cube = sensor.sweep([16.125], "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"], n_frames=2,
                    darks=False, seed=5)
write_sweep(tmp / "in" / "f.tif", replace(cube, meta={}))
out, got = {}, {}
for dev in ("cpu", "cuda"):
    s = correct_batch([tmp / "in"], tmp / dev, cal_path, ffc="none", cube="bilinear",
                      device=dev, hash_inputs=False)
    out[dev + " done"] = s.exit_status == 0 and len(s.done) == 1
    got[dev] = read_corrected(tmp / dev / "f.corrected.tif")
c, g = got["cpu"], got["cuda"]
out["cube shape"] = list(c.data.shape) == [2, 12, 16, 8]
out["equal"] = [bool(np.array_equal(c.data, g.data)), bool(np.array_equal(c.dq, g.dq)),
                bool(np.array_equal(c.alpha, g.alpha))]
out["device recorded"] = g.provenance["pipeline"]["device"] == "cuda"
print("RESULT " + json.dumps(out))
"""


@pytest.mark.slow
def test_simulated_batch_device_cuda_writes_the_cpu_outputs(tmp_path):
    """hsiffc correct's batch with device='cuda' (dark + alpha mask + bilinear cube, two
    frames) writes the outputs the CPU writes, bit for bit in the simulator, and records the
    device in the provenance (slow: 30 s; the default run checks the wiring below)."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    run = subprocess.run([sys.executable, "-c", SIMULATOR_SWITCH + _BATCH, str(tmp_path)],
                         capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    res = json.loads([x for x in run.stdout.splitlines() if x.startswith("RESULT ")][-1][7:])
    _assert_equal(res)


def test_batch_device_cuda_refusals_are_one_line(tmp_path):
    """Without a GPU, --device cuda names what is missing; with one (or the simulator), a
    batch on several processes is refused before anything is read."""
    from hsiffc.batch import BatchError, correct_batch

    x = tmp_path / "x.tif"
    with pytest.raises(BatchError, match="--device must be cpu or cuda"):
        correct_batch([x], tmp_path / "o", tmp_path / "c.npz", device="tpu")
    if not gpu.available():
        with pytest.raises(gpu.GpuUnavailableError) as err:
            correct_batch([x], tmp_path / "o", tmp_path / "c.npz", device="cuda", workers=2)
        assert "\n" not in str(err.value) and str(err.value).startswith("--device cuda: ")
    else:
        with pytest.raises(BatchError, match="drop --workers"):
            correct_batch([x], tmp_path / "o", tmp_path / "c.npz", device="cuda", workers=2)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_benchmark_script_runs_end_to_end_in_the_simulator(tmp_path):
    """benchmarks/gpu.py --smoke, the one script a GPU session runs, goes through every
    section on a 12 x 16 frame in numba's CUDA simulator (minutes: every simulated thread
    runs in Python), and its equality section finds the GPU within tolerance."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    run = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu.py"), "--out",
                          str(tmp_path), "--smoke"], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=3000)
    assert run.returncode == 0, (run.stdout[-2000:], run.stderr[-2000:])
    res = json.loads((tmp_path / "gpu_bench.json").read_text())
    for key in ("gpu_device_only", "gpu_stream", "equality", "cpu_threads", "cpu_crossover"):
        assert key in res and "error" not in res[key], key
    assert res["equality"]["within tolerance"] is True
    assert {"correct+bilinear", "two_point+nearest", "correct+ppid"} <= set(res["gpu_device_only"])
    assert set(res["cpu_threads"]["efficiency"]) == {"1", "2"}


def test_batch_device_cuda_runs_the_pipeline_moved_to_the_device(monkeypatch, demo_result,
                                                                sample_cubes, tmp_path):
    """The batch's wiring without a GPU: with device='cuda' every frame goes through the
    pipeline hsiffc.gpu.to_device returns (here a stand-in that records the frames and
    corrects on the CPU), and the provenance names the device."""
    import hsiffc.gpu as gpu_pkg
    from hsiffc.batch import correct_batch
    from hsiffc.batch.context import forget_contexts
    from hsiffc.io import read_corrected

    seen = []

    class Moved:
        def __init__(self, pipe):
            self.pipe = pipe

        def transform(self, frame):
            seen.append(frame.data.shape)
            return self.pipe.transform(frame)

    monkeypatch.setattr(gpu_pkg, "require", lambda what="--device cuda": None)
    monkeypatch.setattr(gpu_pkg, "to_device",
                        lambda pipe, device: Moved(pipe) if device == "cuda" else pipe)
    forget_contexts()
    cal = demo_result.calibration.save(tmp_path / "cal.npz")
    summary = correct_batch([sample_cubes / "test_2200K.tif"], tmp_path / "out", cal,
                            ffc="none", device="cuda", hash_inputs=False)
    forget_contexts()
    assert summary.exit_status == 0 and len(summary.done) == 1
    out = read_corrected(summary.done[0]["output"])
    assert len(seen) == out.data.shape[0] > 0
    assert out.provenance["pipeline"]["device"] == "cuda"


_CAPTURE = r"""
import json, sys
import numpy as np
from hsiffc.data.frame import Frame
from hsiffc.gpu import selfcheck, kernels
from hsiffc.gpu.pipeline import GpuPipeline
from hsiffc.stages import Pipeline
GpuPipeline.block = (8, 4)
seen = {}

def desc(a):
    if isinstance(a, tuple):  # a kernel's operands as a named tuple (hsiffc.gpu.kernels)
        return ["tuple", type(a).__name__, [desc(x) for x in a]]
    if hasattr(a, "_ary"):
        a = a._ary
    if isinstance(a, np.ndarray):
        return ["array", a.dtype.str, a.ndim, "C" if a.flags.c_contiguous else "A"]
    if isinstance(a, (bool, np.bool_)):
        return ["bool"]
    if isinstance(a, (int, np.integer)):
        return ["int", np.asarray(a).dtype.str if isinstance(a, np.integer) else "<i8"]
    if isinstance(a, (float, np.floating)):
        return ["float", np.asarray(a).dtype.str if isinstance(a, np.floating) else "<f8"]
    return ["other", repr(type(a))]

class Spy:
    def __init__(self, name, k):
        self.name, self.k = name, k
    def __getitem__(self, cfg):
        launch = self.k[cfg]
        def run(*args):
            seen.setdefault(self.name, set()).add(json.dumps([desc(a) for a in args]))
            return launch(*args)
        return run

for name in ["correct", "bilinear", "pack2d", "median_hist", "median_select", "median_finish",
             "median_mean", "correction_matrix", "fill_missing", "band_levels", "ppi_values",
             "ppi_window", "window_max", "band_sums", "two_point_ratio", "two_point_apply"]:
    setattr(kernels, name, Spy(name, getattr(kernels, name)))
shape = (12, 16)
sensor, cal, raw = selfcheck.scene(shape, n_exposures=8)
frame = Frame.from_raw(raw, exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
holed = selfcheck.holed(frame)
pipes = selfcheck.pipelines(cal)
pipes.update(selfcheck.more_pipelines(sensor, cal))
pipes["matrix"] = selfcheck.matrix_pipeline(Pipeline(pipes["mask+bilinear"].steps[:2]))
for name, pipe in pipes.items():
    if name.startswith("correct"):
        continue  # model FFC: slow in the simulator; its types are those of mask+...
    g = pipe.to("cuda")
    for dd, qd, al in (("float32", "uint32", True), ("float16", "uint8", False), ("uint16", "uint8", False)):
        list(g.stream([holed], data_dtype=dd, dq_dtype=qd, alpha=al))
json.dump({k: sorted(v) for k, v in seen.items()}, open(sys.argv[1], "w"), indent=0)
print({k: len(v) for k, v in seen.items()})
"""

_COMPILE = r"""
import json, sys, time
import numpy as np
from hsiffc.gpu import cuda_module
cuda = cuda_module()
from numba import types
from numba.np.numpy_support import from_dtype
from hsiffc.gpu import kernels
sigs = json.load(open(sys.argv[1]))
def ty(d):
    if d[0] == "tuple":
        return types.NamedTuple([ty(x) for x in d[2]], getattr(kernels, d[1]))
    if d[0] == "array":
        return types.Array(from_dtype(np.dtype(d[1])), d[2], d[3])
    if d[0] == "bool":
        return types.boolean
    if d[0] in ("int", "float"):
        return from_dtype(np.dtype(d[1]))
    raise TypeError(d)
bad = 0
for name, lst in sigs.items():
    fn = getattr(kernels, name).py_func
    for s in lst:
        sig = tuple(ty(d) for d in json.loads(s))
        t = time.time()
        try:
            ptx, _ = cuda.compile_ptx(fn, sig, cc=(9, 0))
            print(f"ok  {name} ({time.time() - t:.1f} s, {len(ptx)} chars)", flush=True)
        except Exception as e:
            bad += 1
            print(f"ERR {name}: {type(e).__name__}: {str(e)[:1500]}", flush=True)
sys.exit(1 if bad else 0)
"""


@pytest.mark.slow
def test_kernels_compile_for_sm90_with_the_types_the_pipeline_passes(tmp_path):
    """Every kernel launch of the GPU pipelines (all output types, two-point, nearest, PPID,
    the matrix; recorded in the simulator) compiles to PTX for compute capability 9.0 (H100,
    H200) with NVVM, without a GPU. 'correct' is left out: it calls the CPU's scalar model
    functions, whose device compilation needs a driver (it ran on the H200)."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    sigs = tmp_path / "sigs.json"
    run = subprocess.run([sys.executable, "-c", SIMULATOR_SWITCH + _CAPTURE, str(sigs)],
                         capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=1800)
    assert run.returncode == 0, run.stderr[-3000:]
    launches = json.loads(sigs.read_text())
    assert {"bilinear", "ppi_window", "two_point_apply", "fill_missing"} <= set(launches)
    launches.pop("correct", None)
    sigs.write_text(json.dumps(launches))
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    probe = subprocess.run([sys.executable, "-c", "import numpy as np; np.row_stack = "
                            "np.vstack; from numba.cuda.cudadrv import nvvm; "
                            "assert nvvm.is_available()"], env=env, capture_output=True)
    if probe.returncode:
        pytest.skip("NVVM (the CUDA toolkit's compiler library) is not installed here")
    run = subprocess.run([sys.executable, "-c", _COMPILE, str(sigs)], capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=1800)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]


_UNCERTAIN_CHILD = r"""
import json, numpy as np
from hsiffc.data.dq import DQ
from hsiffc.gpu import cuda_module, kernels
from hsiffc.kernels.bits import or_into_flag_uncertain
cuda = cuda_module()
rng = np.random.default_rng(3)
shape = (6, 10)
value = rng.uniform(-50, 400, shape).astype(np.float32)
value[0, :3] = (np.nan, 0.0, -0.0)
c = rng.uniform(0, 40, shape).astype(np.float32)
e = rng.uniform(-1e-3, 2e-3, shape).astype(np.float32)
dq = rng.choice(np.array([0, 2, 32], np.uint32), shape)
want = or_into_flag_uncertain(dq.copy(), np.zeros(shape, np.uint32), np.zeros(shape, np.uint32),
                              value, c, e, int(DQ.UNCERTAIN))
d_dq = cuda.to_device(dq)
kernels.flag_uncertain[(3, 2), (4, 4)](cuda.to_device(value), d_dq, cuda.to_device(c),
                                       cuda.to_device(e), np.uint32(DQ.UNCERTAIN))
got = d_dq.copy_to_host()
print("RESULT " + json.dumps({"equal": bool(np.array_equal(got, want)),
                              "flagged": int(((want & int(DQ.UNCERTAIN)) != 0).sum())}))
"""


def test_simulated_gpu_flags_uncertain_as_the_cpu():
    """The model FFC's UNCERTAIN flag (c > e signal^2) set on the device as
    hsiffc.kernels.bits sets it on the CPU, bit for bit, keeping the bits already there."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    run = subprocess.run([sys.executable, "-c", SIMULATOR_SWITCH + _UNCERTAIN_CHILD],
                         capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    res = json.loads([x for x in run.stdout.splitlines() if x.startswith("RESULT ")][-1][7:])
    assert res["equal"]
    assert 0 < res["flagged"] < 60
