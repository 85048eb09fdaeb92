"""Compile time of the numba kernels: the first call on a machine (cold: compiled and written
to the disk cache) and in a later process (warm: loaded from the cache).

Each measurement runs in a fresh Python process with its own ``NUMBA_CACHE_DIR``: the cold
run starts from an empty folder, the warm run reuses it. Timed are the calls a correction
makes on a full 2048 x 1088 frame (closed form, inversion, alpha, model_ffc, bilinear and
PPID demosaicing of a frame with flagged samples, each its parallel build) and, separately,
the same calls on a 64 x 64 frame (their serial builds, what the test suite mostly compiles).
Import of hsiffc is timed apart. The cold run also counts the machine-code versions of the
block functions the interpolation and PPI kernels call: one each means both builds share it
(the check of the slow test
``test_each_block_function_compiles_once_for_the_serial_and_parallel_builds``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

from benchutil import figure, row

_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from hsiffc import model
from hsiffc.data.mosaic import Mosaic
from hsiffc.flatfield.model_based import model_ffc_apply
from hsiffc.reconstruct import demosaic
t_import = time.perf_counter() - t0
out = {"import_s": t_import}
for label, shape in (("frame", (1088, 2048)), ("small", (64, 64))):
    rng = np.random.default_rng(0)
    k = rng.uniform(0.5, 20, shape); a = np.full(shape, 2e-4); b = np.full(shape, 0.01)
    d = np.full(shape, 30.0)
    t0 = time.perf_counter()
    y = model.response(25.0, k, a, b, d)
    model.invert_response(y, 25.0, a, b, d, full_scale=1023.0)
    alpha = np.empty(shape, np.float32)
    model.leakage_percentage_paper_into(alpha, y.astype(np.float32), 25.0, a, b, d)
    model_ffc_apply(y, 25.0, a, b, d, np.ones(shape), gain_sweep=np.ones(shape),
                    full_scale_dn=1023.0)
    m = Mosaic.rectangular(2, 4)
    # flagged samples, 2 % of the pixels in even rows and 30 % in odd ones (the PPI fills the
    # flagged pixels of a row one by one or the whole row at once: both paths compile)
    p_row = np.where(np.arange(shape[0]) % 2 == 0, 0.02, 0.3)[:, None]
    dq = (rng.random(shape) < p_row).astype(np.uint32) * np.uint32(1024)
    for method in ("bilinear", "ppid"):
        demosaic(y.astype(np.float32), m, method=method, dq=dq, alpha=alpha)
    out[label + "_s"] = time.perf_counter() - t0
# machine code versions of the block functions the interpolation and PPI kernels call (not
# cached on disk: compiled into each build that calls them): one each, serial and parallel
from hsiffc.kernels import demosaic as kd, ppi as kp
out["callee_versions"] = {f.py_func.__name__: len(f.signatures) for f in (
    kd._interpolate_block, kp._window_block, kp.row_neighbour_sums, kp.pixel_neighbour_sums)}
print(json.dumps(out))
"""


def _run(cache_dir: str) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir,
           "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", _CHILD], env=env, check=True,
                          capture_output=True, text=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(quick: bool = False) -> dict:
    print("Kernel compile time (fresh processes, empty then reused NUMBA_CACHE_DIR)")
    with tempfile.TemporaryDirectory(prefix="hsiffc-numba-cache-") as cache:
        cold = _run(cache)
        warm = _run(cache)
    results = {"cold": cold, "warm": warm, "figures": []}
    for key, label in (("frame_s", "full-frame calls (parallel builds)"),
                       ("small_s", "64 x 64 calls (serial builds)")):
        print(row(f"first calls, {label}", cold[key], "s",
                  f"cold (compile + write cache); warm {warm[key]:.2f} s (load from cache)"))
        results["figures"].append(figure(
            f"first calls, {label}", cold[key], "s", baseline=warm[key],
            baseline_name="warm (cache loaded)", ratio=cold[key] / warm[key],
            note="cold = compiled and cached on first use on a machine; later processes "
                 "load the cache (the ratio is cold / warm)"))
    print(row("import hsiffc (model + reconstruct)", warm["import_s"], "s",
              f"cold run {cold['import_s']:.2f} s"))
    versions = cold["callee_versions"]
    results["block_functions_compiled_once"] = max(versions.values()) == 1
    print(f"  block functions compiled once for both builds: "
          f"{results['block_functions_compiled_once']} ({versions})")
    return results


if __name__ == "__main__":
    main()
