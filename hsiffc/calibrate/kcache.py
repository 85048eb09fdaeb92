"""Keep numba's on-disk cache honest for kernels that call kernels of other modules.

Numba invalidates a cached kernel only when the source file that defines it changes; a kernel
that calls (and compiles in) kernels of other modules keeps its stale machine code when only
those modules change. :func:`refresh` records a digest of the dependency sources next to the
cache and flushes the cached code of the given kernels whenever the digest differs.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def source_digest(modules) -> str:
    """SHA-256 (hex) of the source files of ``modules``.

    Parameters
    ----------
    modules : iterable of module
        Python modules with source files.

    Returns
    -------
    str
        64 hex digits.
    """
    h = hashlib.sha256()
    for m in modules:
        h.update(Path(inspect.getfile(m)).read_bytes())
    return h.hexdigest()


def refresh(dispatchers, modules) -> int:
    """Flush the on-disk cache of numba ``dispatchers`` compiled against other versions of
    ``modules``; returns how many were flushed. Failures (no cache, read-only cache
    directory) are logged and leave the cache alone, as numba itself would.

    Parameters
    ----------
    dispatchers : iterable
        numba dispatchers compiled with ``cache=True``.
    modules : iterable of module
        The modules whose kernels they compile in.

    Returns
    -------
    int
        Number of dispatchers whose cache was flushed.
    """
    digest = source_digest(modules)
    flushed = 0
    for d in dispatchers:
        cache = getattr(d, "_cache", None)  # numba's per-function cache
        if cache is None or not hasattr(cache, "flush"):
            continue
        try:
            stamp = Path(cache.cache_path) / f"{d.py_func.__module__}.{d.__name__}.deps"
            if stamp.exists() and stamp.read_text() == digest:
                continue
            cache.flush()
            stamp.write_text(digest)
            flushed += 1
        except OSError as exc:
            log.debug("numba cache of %s not refreshed: %s", d.__name__, exc)
    return flushed
