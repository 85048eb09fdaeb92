"""Deferred commits: an output's fsync and rename on a background thread (see
:func:`hsiffc.files.atomic.atomic_path`, ``defer=``), so that a batch's next file overlaps the disk."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

__all__ = ["DeferredCommits"]


class DeferredCommits:
    """Runs the commits of :func:`hsiffc.files.atomic.atomic_path` (``defer=``) on one background
    thread, in order.

    The commit waits for the disk (fsync of a finished file, its rename, fsync of the folder);
    a batch hands it over and starts its next file, so the disk and the next file's work
    overlap. The file is in place, durable, only once :meth:`wait` for it returns. Use as a
    context manager (leaving it waits for every commit).
    """

    def __init__(self):
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="hsiffc-commit")
        self._futures: dict[str, object] = {}

    def submit(self, path, fn, *args) -> None:
        """Queue ``fn(*args)``, the commit of ``path``."""
        self._futures[os.fspath(path)] = self._pool.submit(fn, *args)

    def pending(self, path) -> bool:
        """Whether a commit of ``path`` was queued and not yet waited for."""
        return os.fspath(path) in self._futures

    def wait(self, path) -> None:
        """Wait for the commit of ``path``; raises its error (the file was then not put in
        place and its temporary file was removed)."""
        self._futures.pop(os.fspath(path)).result()

    def close(self) -> None:
        """Wait for every commit (errors of commits nobody waited for are dropped)."""
        self._pool.shutdown(wait=True)
        self._futures.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
