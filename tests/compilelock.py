"""One compile of a numba build per test run, not one per test process.

The test processes of ``pytest -n`` start at once on the biggest test files, and several of
those need the same kernels: with a cold cache each process compiled the same signature at
the same time (numba's disk cache only helps the process that starts *after* the first has
saved it). In a cold run of the suite with ``-n 2`` that was 107 s of the 353 s of CPU the
test processes spent compiling (numba's ``numba:compile`` event, timed per signature and
process); ``tests/reconstruct`` alone, cold, ``-n 2``: 172 s of CPU without the lock, 107 s
with it (/usr/bin/time, user + system, load average about 4.5).

:func:`install` wraps numba's ``Dispatcher.compile`` in the test processes: the outermost
compile of a build cached on disk takes an exclusive file lock named by the function and
the signature, in a folder the test processes of the run share. A process that finds the lock
taken waits, then loads the first one's machine code from the disk cache instead of
compiling it again. A process holds at most one such lock (nested compiles, the functions a
kernel calls, take none), so two processes never wait for each other. Builds that are not
cached on disk (``cache=False``) are compiled as before: there is nothing to share, and so
is everything where ``fcntl`` is missing (Windows).
"""

from __future__ import annotations

import hashlib
import os
import threading

try:
    import fcntl
except ImportError:  # Windows: no lock, each process compiles what it needs
    fcntl = None

__all__ = ["install", "lock_path"]

_depth = threading.local()
_state = {"folder": None}


def lock_path(dispatcher, sig) -> str:
    """The lock file of ``dispatcher``'s build for ``sig`` in the installed folder."""
    from numba.core import sigutils

    args, return_type = sigutils.normalize_signature(sig)
    fn = dispatcher.py_func
    text = f"{fn.__module__}.{fn.__qualname__}|{args}|{return_type}"
    return os.path.join(_state["folder"], hashlib.sha1(text.encode()).hexdigest() + ".lock")


def install(folder: str | None) -> str | None:
    """Serialise the compiles of disk-cached numba builds across the processes that call this
    with the same ``folder`` (which must exist); ``None`` stops it. Returns the folder before."""
    from numba.core import dispatcher as nd

    previous, _state["folder"] = _state["folder"], folder
    original = nd.Dispatcher.compile
    if fcntl is None or getattr(original, "_hsiffc_test_lock", False):
        return previous

    def compile(self, sig):
        level = getattr(_depth, "level", 0)
        cache = getattr(self, "_cache", None)
        if (level or _state["folder"] is None or cache is None
                or type(cache).__name__ == "NullCache"):
            return original(self, sig)
        _depth.level = level + 1
        try:
            with open(lock_path(self, sig), "a") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
                return original(self, sig)
        finally:
            _depth.level = level

    compile._hsiffc_test_lock = True
    compile.__doc__ = original.__doc__
    nd.Dispatcher.compile = compile
    return previous
