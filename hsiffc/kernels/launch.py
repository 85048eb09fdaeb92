"""One kernel source, two compilations: parallel for frames, serial for small inputs.

A parallel launch costs tens of microseconds (more on a loaded machine), far more than a
kernel spends on a few pixels, and tests and scalar calls are mostly tiny. :class:`Kernel`
compiles the same loop twice (``prange`` runs as ``range`` in the serial build) and picks by
size. The serial build gets its own name so that numba's disk cache keeps the two apart.

Threads sized to the work: from ``parallel_min`` elements the parallel build runs on one
thread per ``parallel_min // 2`` elements (the share of each of two threads where two start
to pay), at most numba's thread count of the calling thread (``numba.set_num_threads``,
which a batch worker sets to ``cores // workers``). So a 256 x 256 frame runs on 2 threads
of a 16-core machine, not 16 that each wait for the slowest to start for 4096 pixels.
Where two threads start to beat one is measured by ``benchmarks/gpu.py`` (its
``cpu_crossover`` section); :data:`PARALLEL_MIN` is twice the cheapest kernel's crossover
there, a margin for a busy machine, where a parallel region waits for its slowest thread.

Cache freshness: numba invalidates a cached kernel when *its own* source file changes, not
when a function it inlined from another file does. Both builds are therefore named with a
digest of every source they can inline (this package and :mod:`hsiffc.data.dq`), so editing any of
them compiles afresh instead of loading stale machine code.
"""

from __future__ import annotations

import hashlib
import operator
import types
from pathlib import Path

from numba import get_num_threads, njit, set_num_threads

__all__ = ["JIT_OPTIONS", "Kernel", "PARALLEL_MIN", "PARALLEL_OPTIONS", "SOURCE_DIGEST"]

#: Below this many elements a kernel runs serially on the calling thread.
PARALLEL_MIN = 65536
#: Options of every cached kernel: IEEE arithmetic (no fastmath), numpy's error model (0/0 is
#: NaN, not an exception: that lets LLVM vectorise the loops), machine code cached on disk.
JIT_OPTIONS = {"cache": True, "fastmath": False, "error_model": "numpy"}
#: Parallel options of the parallel builds: no loop fusion. numba fuses adjacent ``prange``
#: loops of the same length, which merges a kernel's branch-free vector pass with its scalar
#: repair pass, and the fused loop (with a call in it) is no longer vectorised, several times
#: slower than the two loops apart.
PARALLEL_OPTIONS = {"fusion": False}


def _source_digest() -> str:
    here = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(here.glob("*.py")) + [here.parent / "data" / "dq.py"]:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


SOURCE_DIGEST = _source_digest()


def _renamed(fn, suffix):
    clone = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + suffix,
                               fn.__defaults__, fn.__closure__)
    clone.__qualname__ = fn.__qualname__ + suffix
    clone.__module__ = fn.__module__
    clone.__doc__ = fn.__doc__
    return clone


class Kernel:
    """A loop compiled parallel and serial; calling it runs the build that suits the size.

    Parameters
    ----------
    fn : function
        The loop (``prange`` over blocks or elements).
    size_arg : int or (int, int)
        Index of the argument whose ``.size`` decides (usually the output array); ``(i, j)``:
        member ``j`` of argument ``i`` (a kernel that takes its operands as named tuples).
    parallel_min : int
        Size from which the parallel build runs (default :data:`PARALLEL_MIN`). A kernel that
        does little per element may ask for more: a parallel region waits for its slowest
        thread, and on a busy machine (a batch's reader and writer threads) a thread that
        lost its core can hold a sub-millisecond job for a whole time slice.
    """

    def __init__(self, fn, size_arg: int, parallel_min: int = PARALLEL_MIN):
        self.parallel = njit(parallel=PARALLEL_OPTIONS, **JIT_OPTIONS)(
            _renamed(fn, "_" + SOURCE_DIGEST))
        self.serial = njit(**JIT_OPTIONS)(_renamed(fn, "_serial_" + SOURCE_DIGEST))
        self.size_arg = size_arg
        self._sized = (operator.itemgetter(size_arg) if isinstance(size_arg, int) else
                       lambda args, i=size_arg[0], j=size_arg[1]: args[i][j])
        self.parallel_min = int(parallel_min)
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__

    def threads(self, size: int) -> int:
        """Threads a call on ``size`` elements runs on: 1 (the serial build) below
        ``parallel_min``, from there one per ``parallel_min // 2`` elements, at most the
        calling thread's numba thread count."""
        if size < self.parallel_min:
            return 1
        return min(get_num_threads(), max(2, size // max(1, self.parallel_min // 2)))

    def __call__(self, *args):
        n = self.threads(self._sized(args).size)
        if n <= 1:
            return self.serial(*args)
        have = get_num_threads()
        if n >= have:
            return self.parallel(*args)
        set_num_threads(n)  # this thread's count only (numba keeps it per thread)
        try:
            return self.parallel(*args)
        finally:
            set_num_threads(have)
