"""Where the tasks run: in this process, on a local Dask cluster or on a Dask scheduler.

An executor calls :func:`~hsiffc.batch.task.correct_file` once per job and reports each result
(and, in this process, each frame) to an optional observer with ``frame(nbytes)`` and
``file(result, counted_frames)`` methods (the CLI's progress bar).
"""

from __future__ import annotations

import logging
import os
import socket
import time
from urllib.parse import urlparse

from .memory import reuse_freed_memory
from .plan import BatchError
from .commits import DeferredCommits
from .task import correct_file, empty_result, settle

__all__ = ["check_scheduler", "local_cluster", "run_dask", "run_jobs", "run_local"]

#: seconds a scheduler address has to accept a connection before the batch gives up
CONNECT_TIMEOUT_S = 3.0


def run_jobs(jobs, settings, *, workers: int = 1, scheduler: str | None = None,
             observer=None, threads: int | None = None) -> dict:
    """Run every job; returns ``{job index: result dict}``. ``threads``: numba threads of
    each local worker's kernels (:func:`hsiffc.batch.workers.plan_workers`; None: numba's
    default, every core)."""
    if scheduler or workers > 1:
        return run_dask(jobs, settings, workers=workers, scheduler=scheduler, observer=observer,
                        threads=threads)
    return run_local(jobs, settings, observer=observer)


def run_local(jobs, settings, *, observer=None) -> dict:
    """One job after the other in this process. Each output's fsync and rename run on a
    committer thread while the next file is corrected
    (:class:`~hsiffc.batch.commits.DeferredCommits`); a file's result is reported once its
    output is in place."""
    results = {}
    on_frame = observer.frame if observer is not None else None
    last = None

    def report(i):
        settle(results[i], commits)
        if observer is not None:
            observer.file(results[i], counted_frames=True)

    with DeferredCommits() as commits:
        for i, job in enumerate(jobs):
            results[i] = correct_file(job, settings, on_frame=on_frame, commits=commits)
            if last is not None:
                report(last)
            last = i
        if last is not None:
            report(last)
    return results


def check_scheduler(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Fail fast, with one line, when a Dask scheduler address cannot be reached.

    Raises
    ------
    BatchError
        A TCP address (``tcp://``/``tls://`` or ``HOST:PORT``) that is malformed or where
        nothing accepts a connection within ``timeout_s`` seconds. Other transports are not
        checked.
    """
    url = urlparse(address if "://" in address else f"tcp://{address}")
    if url.scheme not in ("tcp", "tls"):
        return  # in-process or other transports: left to distributed
    try:
        port = url.port
    except ValueError:
        port = None
    if not url.hostname or port is None:
        raise BatchError(f"--scheduler {address!r} is not a scheduler address; give "
                         "tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786)")
    try:
        with socket.create_connection((url.hostname, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise BatchError(f"--scheduler {address}: cannot connect ({exc.strerror or exc}); start "
                         "the scheduler (dask scheduler) or check the address and firewall, or "
                         "run without --scheduler") from None


def local_cluster(workers: int):
    """A local cluster of single-threaded worker processes.

    Its workers start without distributed's default ``MALLOC_TRIM_THRESHOLD_``: setting it
    turns off glibc's adaptive mmap threshold, so every large numpy temporary is mapped and
    page-faulted afresh (twice the time per frame here); memory stays bounded without it.
    """
    import dask
    from distributed import LocalCluster

    key = "distributed.nanny.pre-spawn-environ"
    environ = {k: v for k, v in (dask.config.get(key, default=None) or {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({key: environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None, silence_logs=logging.ERROR)


def correct_file_in_worker(job, settings, threads: int | None = None):
    """:func:`correct_file` in a Dask worker process, whose allocator is set up first
    (:func:`hsiffc.batch.memory.reuse_freed_memory`, once per process: a process-wide setting made
    only where hsiffc owns the process, the CLI and its workers, never in a caller's), and
    whose kernels run on ``threads`` numba threads (so that workers x threads <= cores)."""
    reuse_freed_memory()
    if threads is not None:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    return correct_file(job, settings)


def run_dask(jobs, settings, *, workers: int, scheduler: str | None, observer=None,
             threads: int | None = None) -> dict:
    """One Dask task per job on a local cluster (``workers``, their kernels on ``threads``
    threads each) or on ``scheduler``."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise BatchError("--workers above 1 and --scheduler run on Dask, which is not "
                         "installed: install it with pip install 'hsiffc[dask]', or run "
                         "with --workers 1") from None

    cluster = None
    if scheduler:
        client = Client(scheduler, timeout="30s")
    else:
        cluster = local_cluster(workers)
        client = Client(cluster)
    results = {}
    try:
        futures = {client.submit(correct_file_in_worker, job, settings,
                                 None if scheduler else threads, pure=False,
                                 key=f"hsiffc-correct-{i}-{os.getpid()}-{time.time_ns()}"): i
                   for i, job in enumerate(jobs)}
        for fut in as_completed(list(futures)):
            i = futures[fut]
            try:
                res = fut.result()
            except Exception as exc:  # e.g. KilledWorker: the worker died on this file
                res = empty_result(jobs[i], reason=f"the worker failed on this file "
                                   f"({type(exc).__name__}: {exc}); run again to retry it")
            results[i] = res
            if observer is not None:
                observer.file(res, counted_frames=False)
    finally:
        client.close()
        if cluster is not None:
            close_quietly(cluster)
    return results


def close_quietly(cluster) -> None:
    """Close a local cluster hsiffc started, without the nanny's "Worker process still alive
    after 4.0 seconds, killing" warning: every result is in by then, and a worker slow to exit
    on a busy machine is stopped as intended, nothing the user has to act on."""
    nanny = logging.getLogger("distributed.nanny")
    level = nanny.level
    nanny.setLevel(logging.ERROR)
    try:
        cluster.close()
    finally:
        nanny.setLevel(level)
