"""Large arrays freed by one frame, reused by the next: glibc's allocator settings for a process
that corrects many frames.

A reconstructed 2048 x 1088 x 8 cube is 71 MB, and a pipeline makes three of them per frame
(data, DQ, alpha). glibc serves a request above its mmap threshold (128 kB, rising with use to
at most 32 MB) with fresh pages from the kernel, which the kernel zeroes on first touch, and
returns them to the kernel on ``free``. So every frame's cubes are new pages, zeroed, and
writing a cube takes about twice the time of writing the same cube into memory the process
already holds (``benchmarks/bench_pipeline.py`` measures both).

:func:`reuse_freed_memory` raises the threshold above the largest array a frame makes and
keeps freed memory in the process up to ``keep_mb``, so the next frame's cubes reuse the last
frame's pages. It changes the allocator of the whole process (every library in it), once, and
is not undone; memory that was freed is kept for reuse rather than given back (the resident
size stays at the peak of one frame's working set). ``hsiffc correct`` and the other commands
call it; a Python script that corrects many frames can call it at its start. Elsewhere than
glibc (macOS, Windows, musl) it does nothing and returns False.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["reuse_freed_memory"]

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_applied: tuple[int, int] | None = None


def reuse_freed_memory(*, largest_mb: int = 1024, keep_mb: int = 2048) -> bool:
    """Serve arrays up to ``largest_mb`` from the process's heap and keep up to ``keep_mb`` of
    freed memory for reuse (glibc ``mallopt``: ``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``).

    Parameters
    ----------
    largest_mb : int
        Requests up to this size (MiB) come from the heap, and their memory is reused after a
        ``free``; larger ones are still mapped afresh. At most 2048.
    keep_mb : int
        Freed memory at the top of the heap up to this size (MiB) stays in the process.

    Returns
    -------
    bool
        True where the settings are in force (glibc), False elsewhere.

    Raises
    ------
    ValueError
        ``largest_mb`` or ``keep_mb`` out of range.
    """
    global _applied
    if not 1 <= int(largest_mb) <= 2048:
        raise ValueError(f"largest_mb must be 1..2048 (MiB), got {largest_mb}")
    if not 0 <= int(keep_mb) <= 65536:
        raise ValueError(f"keep_mb must be 0..65536 (MiB), got {keep_mb}")
    wanted = (int(largest_mb), int(keep_mb))
    if _applied == wanted:
        return True
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = (mallopt(_M_MMAP_THRESHOLD, min(wanted[0] << 20, 2**31 - 1)) == 1
          and mallopt(_M_TRIM_THRESHOLD, min(wanted[1] << 20, 2**31 - 1)) == 1)
    if ok:
        _applied = wanted
    return ok
