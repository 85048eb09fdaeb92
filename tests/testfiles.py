"""Hand-made test files shared by several test modules: a synthetic IMEC calibration XML,
PNG and TIFF files written byte by byte (bombs, damaged chunks), and the capped child process
that runs the command line under a memory bound. Public names: test modules import them from
here, never each other's private helpers (a module run alone then finds them too)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import textwrap
import zlib

import numpy as np


def synthetic_imec_xml(*, pattern=True, n_samples=11, root="sensor_calibration",
                       order=(2, 0, 3, 1)):
    """The text of a small IMEC sensor calibration XML: a 2 x 2 mosaic of 64 x 32 pixels,
    bands at 402-408 nm in pattern ``order`` (band 1 with ``n_samples`` response samples),
    ``pattern=False`` without its pattern size, ``root`` its root element."""
    wl = np.arange(400, 411)
    bands = []
    for pos in order:
        centre = 402 + 2 * pos
        comp = 100 * np.exp(-0.5 * ((wl - centre) / 1.0) ** 2)
        comp = comp[:n_samples] if pos == 1 else comp
        bands.append(f"""
      <band version="2" pattern_position_index="{pos}" selected="true">
        <peaks><peak version="0" order="1"><wavelength_nm>{centre}</wavelength_nm>
          <fwhm_nm>2.4</fwhm_nm><QE>100</QE></peak></peaks>
        <response_composition version="0" nr_elements="{comp.size}">
          <data>{", ".join(f"{v:.6g}" for v in comp)}</data></response_composition>
      </band>""")
    pat = "<pattern_width>2</pattern_width><pattern_height>2</pattern_height>" if pattern else ""
    corr = ", ".join(["0.01"] * 4)
    return f"""<?xml version="1.0" encoding="utf-8"?>
<{root} version="0">
  <sensor_info version="0"><width>64</width><height>32</height><adc_gain>1</adc_gain>
    <input_bpp>10</input_bpp><effective_bpp>10</effective_bpp><pixel_pitch>5.5</pixel_pitch>
  </sensor_info>
  <filter_info version="2" layout="MOSAIC">
    <filter_area version="0"><offset_x>1</offset_x><offset_y>2</offset_y>
      <width>60</width><height>28</height></filter_area>
    {pat}
    <calibration_info version="0"><measurement_range_start_nm>400</measurement_range_start_nm>
      <measurement_range_end_nm>410</measurement_range_end_nm>
      <measurement_resolution_nm>1</measurement_resolution_nm>
      <nr_measurements>11</nr_measurements></calibration_info>
    <spectral_correction_info version="1"><fwhm_virtual_filters_nm>3</fwhm_virtual_filters_nm>
      <virtual_bands><band version="0"><wavelength_nm>405</wavelength_nm>
        <custom_spectral_correction version="0" nr_elements="4"><data>{corr}</data>
        </custom_spectral_correction></band></virtual_bands></spectral_correction_info>
    <bands>{"".join(bands)}
    </bands>
  </filter_info>
</{root}>
"""


def bomb_tiff(path, height=32000, width=32000):
    """A tiny deflate TIFF whose header claims a height x width uint8 image (a few KB)."""
    strip = zlib.compress(b"\0" * width * 8, 9)
    nstrips = height // 8
    entries = []
    data_at = 8
    offsets_at = data_at + len(strip)
    counts_at = offsets_at + 4 * nstrips
    ifd_at = counts_at + 4 * nstrips
    tags = [(256, 4, 1, width), (257, 4, 1, height), (258, 3, 1, 8), (259, 3, 1, 8),
            (262, 3, 1, 1), (273, 4, nstrips, offsets_at), (277, 3, 1, 1), (278, 4, 1, 8),
            (279, 4, nstrips, counts_at)]
    for code, typ, count, value in tags:
        packed = struct.pack("<HHI", code, typ, count)
        packed += struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value)
        entries.append(packed)
    blob = b"II*\0" + struct.pack("<I", ifd_at) + strip
    blob += struct.pack(f"<{nstrips}I", *([data_at] * nstrips))
    blob += struct.pack(f"<{nstrips}I", *([len(strip)] * nstrips))
    blob += struct.pack("<H", len(entries)) + b"".join(entries) + struct.pack("<I", 0)
    path.write_bytes(blob)
    return path


def capped_child(code: str, *, extra_mb: int = 300) -> subprocess.CompletedProcess:
    """Run ``code`` in a child Python whose address space is capped (``RLIMIT_AS``) at what
    its imports (numba's LLVM library included) took plus ``extra_mb``
    MiB: an allocation past the cap fails there (a
    MemoryError, an internal error) instead of passing unnoticed."""
    prelude = textwrap.dedent(f"""
        import resource, sys
        import cv2, numpy, tifffile
        from hsiffc.cli import main
        import hsiffc.stages, hsiffc.io
        import numba, llvmlite.binding  # kernels load on first use, not with the stages
        llvmlite.binding.llvm_version_info  # maps LLVM's library before the cap
        size = int(open("/proc/self/status").read().split("VmSize:")[1].split()[0]) << 10
        cap = size + ({extra_mb} << 20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    """)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "NUMBA_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=120, env=env)


def capped_cli(argv, *, extra_mb: int = 300) -> tuple[int, str]:
    """Exit status and stderr of ``hsiffc ARGV`` run in a capped child (:func:`capped_child`)."""
    done = capped_child(f"sys.exit(main({[str(a) for a in argv]!r}))", extra_mb=extra_mb)
    return done.returncode, done.stderr


def hand_png(path, width, height, *, depth=8, colour=0, rows=None, chunks=None):
    """A PNG written by hand: ``rows`` (bytes of each row, filter byte first; zeros when not
    given, compressed without holding the image in memory) or ``chunks`` verbatim."""
    def chunk(kind, body):
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body)))
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    if chunks is None:
        if rows is None:  # zero rows: one compressed block of 1000 rows, repeated
            bpp = {0: 1, 2: 3, 4: 2, 6: 4}[colour] * depth // 8
            block = b"\0" * (1 + width * bpp) * min(height, 1000)
            c = zlib.compressobj(1)
            first = c.compress(block) + c.flush(zlib.Z_SYNC_FLUSH)
            end = c.flush(zlib.Z_FINISH)[:-4]
            adler = 1
            for _ in range(height // min(height, 1000)):
                adler = zlib.adler32(block, adler)
            idat = first + first[2:] * (height // min(height, 1000) - 1) + end
            idat += struct.pack(">I", adler)
        else:
            idat = zlib.compress(b"".join(rows))
        chunks = [(b"IHDR", ihdr), (b"IDAT", idat), (b"IEND", b"")]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(chunk(k, b) for k, b in chunks))
    return path
