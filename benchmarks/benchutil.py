"""Timing helpers for the benchmarks: medians over repeats, peak memory of a call."""

from __future__ import annotations

import statistics
import time
import tracemalloc


def median_time(fn, *, repeat: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeat`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def interleaved_medians(fns: dict, *, repeat: int = 5, warmup: int = 1) -> dict:
    """Median wall time (s) of each of ``fns`` (name -> callable), the calls taken in turn,
    one of each per round, for ``repeat`` rounds after ``warmup`` rounds: a figure and its
    baseline see the same state of a shared machine (whose speed drifts within a run by up
    to ~1.5 x), so their ratio holds even when their absolute values move."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    times = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def peak_memory_mb(fn) -> float:
    """Peak Python-heap allocation (numpy arrays included) during ``fn()``, in MiB."""
    tracemalloc.start()
    try:
        fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return peak / 2 ** 20


def row(name: str, value: float, unit: str, note: str = "") -> str:
    return f"  {name:<52} {value:>12.4g} {unit:<8} {note}"


def figure(name: str, value: float, unit: str, *, baseline: float | None = None,
           baseline_name: str = "", ratio: float | None = None, target: str = "",
           met: bool | None = None, note: str = "") -> dict:
    """One measured figure for the results table that ``run.py`` writes.

    ``baseline`` is the same quantity of the baseline measured in the same run (its
    ``baseline_name`` says what it is) and ``ratio`` how the figure compares with it (as
    stated in ``note``); ``target`` the figure the issue asks for and ``met`` whether it is.
    """
    return {"name": name, "value": float(value), "unit": unit,
            "baseline": None if baseline is None else float(baseline),
            "baseline_name": baseline_name, "ratio": None if ratio is None else float(ratio),
            "target": target, "met": met, "note": note}
