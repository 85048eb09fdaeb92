"""The cube kernel (:data:`hsiffc.gpu.kernels.bilinear`) alone on a GPU at several register
caps: its device time per 2048 x 1088 x 8 cube (CUDA events around 20 launches, 3 repeats)
and whether its values and DQ equal the shipped kernel's bit for bit. The cap
``max_registers=64`` in :mod:`hsiffc.gpu.kernels` was chosen from this sweep
(docs/results/gpu/bilinear_h100.txt); rerun it on another GPU before changing the cap::

    python3 benchmarks/gpu_registers.py [--caps 0 96 80 64 48 40]

(0: no cap). Needs numba-cuda and a GPU; the profile in the same file was taken with
``ncu --kernel-name regex:bilinear --launch-skip 3 --launch-count 1 --section ...`` around
this script.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--caps", nargs="*", type=int, default=[0, 96, 80, 64, 48, 40])
    ap.add_argument("--shape", nargs=2, type=int, default=[1088, 2048])
    args = ap.parse_args()

    from hsiffc import gpu
    from hsiffc.data.frame import Frame
    from hsiffc.gpu import kernels, selfcheck
    from hsiffc.gpu.pipeline import DeviceFrame, OutputTypes

    gpu.require()
    cuda = gpu.cuda_module()
    shape = tuple(args.shape)
    sensor, cal, raw = selfcheck.scene(shape)
    g = selfcheck.pipelines(cal)["correct+bilinear"].to("cuda")
    frame = Frame.from_raw(raw, exposure_ms=16.125, bit_depth=10, mosaic=sensor.mosaic)
    planes, _ = g._const(shape, 16.125, 10, sensor.mosaic)
    dev, _ = g._buffers(shape, planes, np.float32, np.uint32, False)
    d_raw = cuda.to_device(np.ascontiguousarray(frame.data))
    d_dq = cuda.to_device(np.ascontiguousarray(frame.dq))
    st = cuda.stream()
    g._launch(DeviceFrame(d_raw, d_dq, True, shape, 16.125, 10, sensor.mosaic), dev,
              OutputTypes(0, False, False), st)
    st.synchronize()
    ref = dev["out"].copy_to_host(), dev["out_dq"].copy_to_host()
    shipped = kernels.bilinear
    e0, e1 = cuda.event(), cuda.event()
    try:
        for cap in args.caps:
            kernels.bilinear = cuda.jit(**({"max_registers": cap} if cap else {}))(
                shipped.py_func)
            g._bilinear(planes, dev, 0, False, False, None, st)
            st.synchronize()
            same = all(np.array_equal(a, b.copy_to_host(), equal_nan=True)
                       for a, b in zip(ref, (dev["out"], dev["out_dq"])))
            ms = []
            for _ in range(3):
                e0.record(st)
                for _ in range(20):
                    g._bilinear(planes, dev, 0, False, False, None, st)
                e1.record(st)
                e1.synchronize()
                ms.append(round(e0.elapsed_time(e1) / 20, 3))
            print(f"max_registers {cap or None} bilinear device ms {ms} equal {same}",
                  flush=True)
    finally:
        kernels.bilinear = shipped
    return 0


if __name__ == "__main__":
    sys.exit(main())
