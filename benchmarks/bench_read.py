"""Reading benchmark: hsiffc's streaming reader against tifffile alone, same files, same run.

A stack of 2048 x 1088 frames (12-bit values in uint16, and 8-bit) written by tifffile with LZW
compression, plain TIFF without hsiffc metadata (exposure and bit depth given as options, as a
user of camera files would). Baselines:

* ``tifffile pages``: ``for page in TiffFile(path).pages: page.asarray()``, the same streaming
  access (one frame in memory);
* ``tifffile imread``: ``tifffile.imread(path)``, the whole stack at once.

hsiffc: ``for raw, meta in open_source(path, ...)`` (header parse, limits, structure checks,
metadata resolution, per-frame bit-depth check) and ``open_source(...).to_sweep()``.
Ratios are throughput hsiffc / tifffile (>= 0.9 is the target).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import tifffile

from benchutil import figure, median_time, row
from hsiffc.io import open_source

SHAPE = (1088, 2048)


def _stack(path: Path, n: int, dtype, bits: int) -> Path:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    base = (2 ** bits * 0.3 * (1 + 0.3 * np.sin(xx / 90.0) * np.cos(yy / 70.0)))
    with tifffile.TiffWriter(path) as tw:
        for _ in range(n):
            frame = np.clip(base + rng.normal(0, 2 ** bits / 200, SHAPE), 0, 2 ** bits - 1)
            tw.write(frame.astype(dtype), compression="lzw", photometric="minisblack",
                     metadata=None)
    return path


def main(quick: bool = False) -> dict:
    n = 4 if quick else 10
    repeat = 3 if quick else 5
    results = {}
    figures = []
    print(f"Reading benchmark: {n} LZW frames of {SHAPE[1]} x {SHAPE[0]}, median of {repeat} "
          "runs")
    with tempfile.TemporaryDirectory() as tmp:
        for dtype, bits in ((np.uint16, 12), (np.uint8, 8)):
            path = _stack(Path(tmp) / f"stack{bits}.tif", n, dtype, bits)
            mb = n * SHAPE[0] * SHAPE[1] * np.dtype(dtype).itemsize / 2 ** 20

            def pages():
                with tifffile.TiffFile(path) as tf:
                    for page in tf.pages:
                        page.asarray()

            def stream():
                with open_source(path, exposure_ms=10.0, bit_depth=bits) as src:
                    for raw, _ in src:
                        pass

            def whole():
                with open_source(path, exposure_ms=10.0, bit_depth=bits) as src:
                    src.to_sweep()

            t_pages = median_time(pages, repeat=repeat)
            t_imread = median_time(lambda: tifffile.imread(path), repeat=repeat)
            t_stream = median_time(stream, repeat=repeat)
            t_whole = median_time(whole, repeat=repeat)
            key = f"{bits}bit"
            results[f"tifffile_pages_{key}_mb_s"] = mb / t_pages
            results[f"tifffile_imread_{key}_mb_s"] = mb / t_imread
            results[f"hsiffc_stream_{key}_mb_s"] = mb / t_stream
            results[f"hsiffc_sweep_{key}_mb_s"] = mb / t_whole
            results[f"stream_vs_pages_{key}"] = t_pages / t_stream
            results[f"sweep_vs_imread_{key}"] = t_imread / t_whole
            print(row(f"{key}: tifffile pages (stream)", mb / t_pages, "MB/s"))
            print(row(f"{key}: tifffile imread (whole stack)", mb / t_imread, "MB/s"))
            print(row(f"{key}: hsiffc open_source, stream", mb / t_stream, "MB/s",
                      f"x{t_pages / t_stream:.2f} of tifffile pages"))
            print(row(f"{key}: hsiffc open_source().to_sweep()", mb / t_whole, "MB/s",
                      f"x{t_imread / t_whole:.2f} of tifffile imread"))
            figures += [
                figure(f"read a {key} LZW stack, streaming", mb / t_stream, "MB/s",
                       baseline=mb / t_pages, baseline_name="tifffile pages, streaming",
                       ratio=t_pages / t_stream, target=">= 0.9 x tifffile",
                       met=t_pages / t_stream >= 0.9, note="ratio = throughput hsiffc / tifffile"),
                figure(f"read a {key} LZW stack, whole", mb / t_whole, "MB/s",
                       baseline=mb / t_imread, baseline_name="tifffile.imread",
                       ratio=t_imread / t_whole, target=">= 0.9 x tifffile",
                       met=t_imread / t_whole >= 0.9, note="ratio = throughput hsiffc / tifffile")]
    results["figures"] = figures
    return results


if __name__ == "__main__":
    main()
