"""How many worker processes a batch runs, and how many kernel threads each gets.

``--workers N`` is an upper bound, not an order. One process already uses every core: the
compiled kernels run on numba's threads (one per core) while a reader and a writer thread
overlap the I/O. Extra processes pay for themselves only when the batch is large enough:

- a local Dask cluster costs :data:`STARTUP_S` seconds to start (processes, imports, kernels
  loaded from the disk cache), many times the correction of a small input;
- one process corrects about :data:`RATE_MB_S` MB of input a second (the batch benchmark's
  rate on 2 cores, on the benchmarks page).

So more than one process runs only when the input is large enough for two, even if each ran
at that rate, to save more than the start-up: ``total MB >= 2 * STARTUP_S * RATE_MB_S``
(about 1.3 GB); then as many as asked, but never more than files or cores. Each worker's kernels then get
``cores // W`` threads, so that workers x kernel threads <= cores (no oversubscription). A
batch on a Dask scheduler (``--scheduler``) is not planned here: its workers are the
scheduler's.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass

__all__ = ["RATE_MB_S", "STARTUP_S", "WorkerPlan", "available_cores", "plan_workers"]

#: seconds a local cluster costs before its first file (start, imports, kernels from cache)
STARTUP_S = 8.0
#: MB of input one process corrects per second (benchmarks/bench_batch.py, 1 worker)
RATE_MB_S = 80.0


@dataclass(frozen=True)
class WorkerPlan:
    """The processes and kernel threads a batch runs with, and why.

    Attributes
    ----------
    workers : int
        Processes (1: in this process, no cluster).
    threads_per_worker : int
        numba threads of each worker's kernels (workers x threads <= cores).
    requested : int
        What ``--workers`` asked for.
    cores : int
        Cores this process may run on.
    reason : str
        Why (one clause, for the summary).
    """

    workers: int
    threads_per_worker: int
    requested: int
    cores: int
    reason: str

    def describe(self) -> str:
        """One line for the summary, e.g. ``"ran in 1 process, its kernels on 2 threads (2
        cores; --workers 4 asked; ...)"``."""
        threads = f"{self.threads_per_worker} thread{'s' if self.threads_per_worker != 1 else ''}"
        where = ("1 process, its kernels on " if self.workers == 1
                 else f"{self.workers} worker processes, the kernels of each on ")
        text = f"ran in {where}{threads} ({self.cores} cores)"
        if self.requested != self.workers:
            text = text[:-1] + f"; --workers {self.requested} asked; {self.reason})"
        return text

    def to_dict(self) -> dict:
        return asdict(self)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def plan_workers(requested: int, input_bytes, *, cores: int | None = None) -> WorkerPlan:
    """The worker count and kernel threads for a batch (see the module's docstring).

    Parameters
    ----------
    requested : int
        ``--workers`` (>= 1): the most processes to use.
    input_bytes : sequence of int
        Size of each input file, in bytes.
    cores : int, optional
        Cores to plan for (default: :func:`available_cores`).

    Returns
    -------
    WorkerPlan

    Examples
    --------
    >>> plan_workers(4, [1_000_000] * 4, cores=2).workers   # 4 MB: not worth a cluster
    1
    >>> p = plan_workers(4, [500_000_000] * 8, cores=2)     # 4 GB on 2 cores
    >>> p.workers, p.threads_per_worker
    (2, 1)
    """
    cores = available_cores() if cores is None else max(1, int(cores))
    requested = max(1, int(requested))
    sizes = [max(0, int(b)) for b in input_bytes]
    mb = sum(sizes) / 1e6
    limits = [(requested, "")]
    limits.append((cores, f"{cores} cores: more processes than cores would share them"))
    limits.append((max(1, len(sizes)), f"{len(sizes)} file{'s' if len(sizes) != 1 else ''}"))
    bound, why = min(limits, key=lambda x: x[0])
    need = 2 * STARTUP_S * RATE_MB_S  # two processes save their cluster's start from here
    workers = bound if mb >= need else 1
    if workers < bound:
        why = (f"{mb:.0f} MB of input is too little for more than one process: a local "
               f"cluster costs ~{STARTUP_S:.0f} s to start, two pay off from ~{need:.0f} MB")
    return WorkerPlan(workers=workers, threads_per_worker=max(1, cores // workers),
                      requested=requested, cores=cores, reason=why)
