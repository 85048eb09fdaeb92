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

Cache freshness, the one mechanism for every cached CPU kernel: numba invalidates a cached
kernel when *its own* source file changes, not when a function it compiled in from another file
does. Every build cached on disk is therefore named with a digest of every source it can
compile in (this package and :mod:`hsiffc.data.dq`): :class:`Kernel`'s two builds, and the
entry points compiled once by :func:`cached_jit`. Editing any of those files compiles afresh
instead of loading stale machine code. Only entry points (called from Python) are cached; the
functions they call are compiled into them (``cache=False``).

Nothing is compiled, hashed or read at import: the digest is computed on the first build of
the process (:func:`source_digest`, a few milliseconds), and a kernel builds its numba
dispatchers on its first call.
"""

from __future__ import annotations

import functools
import hashlib
import operator
import types
from pathlib import Path

from numba import get_num_threads, njit, set_num_threads

__all__ = ["JIT_OPTIONS", "CachedJit", "Kernel", "PARALLEL_MIN", "PARALLEL_OPTIONS",
           "SOURCE_DIGEST", "cached_jit", "digest_named", "source_digest"]

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


@functools.cache
def source_digest() -> str:
    """12 hex digits of SHA-256 over the sources a cached kernel can compile in: every
    ``hsiffc/kernels/*.py`` and ``hsiffc/data/dq.py`` (names and contents). Computed once per
    process, on the first build (not at import)."""
    here = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(here.glob("*.py")) + [here.parent / "data" / "dq.py"]:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def __getattr__(name: str):
    """``SOURCE_DIGEST``: :func:`source_digest`, computed when first asked for (PEP 562)."""
    if name == "SOURCE_DIGEST":
        return source_digest()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _renamed(fn, suffix):
    clone = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + suffix,
                               fn.__defaults__, fn.__closure__)
    clone.__qualname__ = fn.__qualname__ + suffix
    clone.__module__ = fn.__module__
    clone.__doc__ = fn.__doc__
    return clone


def digest_named(fn, **options):
    """``njit(**options)`` of a copy of ``fn`` named ``<name>_<source digest>``: numba's disk
    cache (``cache=True`` in ``options``) keys a build by its function's name, so a build of
    other sources never loads this one's machine code. Computes the digest (once)."""
    return njit(**options)(_renamed(fn, "_" + source_digest()))


class CachedJit:
    """An entry point compiled once (no serial/parallel pair), cached on disk under the digest
    name (:func:`digest_named`) and built on its first call. Made by :func:`cached_jit`.

    Attributes
    ----------
    dispatcher : numba dispatcher
        The build (made when first asked for).
    """

    def __init__(self, fn, options: dict):
        self.fn = fn
        self.options = {**JIT_OPTIONS, **options}
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__

    def __getattr__(self, name):
        if name != "dispatcher":
            raise AttributeError(name)
        self.dispatcher = digest_named(self.fn, **self.options)
        return self.dispatcher

    def __call__(self, *args):
        return self.dispatcher(*args)


def cached_jit(fn=None, **options):
    """Decorator: ``fn`` as a :class:`CachedJit` (an entry point called from Python, compiled
    on its first call, cached under the digest name). ``options`` add to or override
    :data:`JIT_OPTIONS` (e.g. ``parallel=True``). Functions that other compiled functions call
    stay plain ``njit`` with ``cache=False``: they are compiled into their callers."""
    if fn is None:
        return lambda f: CachedJit(f, options)
    return CachedJit(fn, options)


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
        self.fn = fn
        self.size_arg = size_arg
        self._sized = (operator.itemgetter(size_arg) if isinstance(size_arg, int) else
                       lambda args, i=size_arg[0], j=size_arg[1]: args[i][j])
        self.parallel_min = int(parallel_min)
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__

    def __getattr__(self, name):
        """``parallel`` and ``serial``, the two numba builds, made when first asked for."""
        if name not in ("parallel", "serial"):
            raise AttributeError(name)
        self.parallel = digest_named(self.fn, parallel=PARALLEL_OPTIONS, **JIT_OPTIONS)
        self.serial = njit(**JIT_OPTIONS)(_renamed(self.fn, "_serial_" + source_digest()))
        return getattr(self, name)

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
