"""Kernel threads sized to the work, and no oversubscription with --workers: each worker's
kernels run on cores // workers numba threads."""

from __future__ import annotations

import os

import numba
import pytest

import hsiffc.kernels.launch as launch
from hsiffc.batch import executors


@pytest.fixture
def fake_threads(monkeypatch):
    """numba's per-thread count as a plain value (a 16-core machine), and a Kernel whose
    builds report which ran and on how many threads."""
    state = {"n": 16}
    monkeypatch.setattr(launch, "get_num_threads", lambda: state["n"])
    monkeypatch.setattr(launch, "set_num_threads", lambda n: state.update(n=n))
    k = launch.Kernel.__new__(launch.Kernel)
    k.parallel_min = 65536
    k._sized = lambda args: args[0]
    k.parallel = lambda *a: ("parallel", state["n"])
    k.serial = lambda *a: ("serial", 1)
    return k, state


class _Sized:
    def __init__(self, size):
        self.size = size


def test_small_frames_run_serially_and_threads_grow_with_the_work(fake_threads):
    k, state = fake_threads
    assert k(_Sized(64 * 64)) == ("serial", 1)  # a thumbnail: one thread
    assert k(_Sized(65535)) == ("serial", 1)
    assert k(_Sized(256 * 256)) == ("parallel", 2)  # parallel_min: two threads
    assert k(_Sized(512 * 512)) == ("parallel", 8)  # one per parallel_min // 2 elements
    assert k(_Sized(2048 * 1088)) == ("parallel", 16)  # a camera frame: every thread
    assert state["n"] == 16  # the caller's count is restored after a smaller call
    state["n"] = 3  # e.g. a worker's cores // workers: never more than that
    assert k(_Sized(2048 * 1088)) == ("parallel", 3)
    state["n"] = 1
    assert k(_Sized(2048 * 1088)) == ("serial", 1)  # one thread: the serial build


def test_the_test_processes_run_the_serial_builds_on_one_thread():
    """conftest sets NUMBA_NUM_THREADS before numba is imported (unless the environment set
    it): it took, and a camera frame then runs a kernel's serial build."""
    want = int(os.environ["NUMBA_NUM_THREADS"])
    assert numba.config.NUMBA_NUM_THREADS == want == numba.get_num_threads()
    if want == 1:
        from hsiffc.kernels.leakage import response_kernel
        assert response_kernel.threads(2048 * 1088) == 1


def test_a_worker_runs_its_kernels_on_its_share_of_the_cores(monkeypatch):
    seen = []
    monkeypatch.setattr(executors, "reuse_freed_memory", lambda: None)
    monkeypatch.setattr(executors, "correct_file",
                        lambda job, settings: seen.append(numba.get_num_threads()) or {})
    before = numba.get_num_threads()
    try:
        executors.correct_file_in_worker(None, None, threads=1)
        assert seen == [1]
    finally:
        numba.set_num_threads(before)


def test_a_batch_on_workers_gives_each_cores_over_workers_threads(monkeypatch, demo_result,
                                                                 sample_cubes, tmp_path):
    import hsiffc.batch as batch
    from hsiffc.batch.task import empty_result

    got = {}

    def run_jobs(jobs, settings, *, workers, scheduler, observer, threads):
        got.update(workers=workers, threads=threads)
        return {i: empty_result(j, reason="not run (test)") for i, j in enumerate(jobs)}

    monkeypatch.setattr(batch, "run_jobs", run_jobs)
    monkeypatch.setattr(batch, "_sizes", lambda jobs: [10 ** 10] * len(jobs))  # 10 GB each
    monkeypatch.setattr(batch.workers, "available_cores", lambda: 8)
    cal = demo_result.calibration.save(tmp_path / "cal.npz")
    files = [sample_cubes / "test_2200K.tif", sample_cubes / "training_2900K.tif"]
    batch.correct_batch(files, tmp_path / "out", cal, workers=4)
    assert got == {"workers": 2, "threads": 4}  # two files: two workers of 8 // 2 threads


@pytest.mark.parametrize("given", [None, "ACTIVE"])
def test_openmp_threads_wait_passively_unless_the_environment_says(given):
    # a spinning OpenMP thread takes a shared core from the serial code between kernels:
    # hsiffc asks for passive waiting before numba starts its threads, and keeps a policy the
    # environment sets
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given:
        env["OMP_WAIT_POLICY"] = given
    run = subprocess.run([sys.executable, "-c", "import os, hsiffc.kernels; "
                          "print(os.environ['OMP_WAIT_POLICY'])"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split()[-1] == (given or "PASSIVE")
