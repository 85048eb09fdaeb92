"""--workers is an upper bound: never more processes than files or cores, none of a cluster's
start-up on a small input, and workers x kernel threads <= cores; the summary says what ran."""

from __future__ import annotations

import itertools

import pytest

import hsiffc.batch.workers as planning
from hsiffc.batch.workers import plan_workers


def test_a_small_input_runs_in_one_process_and_says_why():
    plan = plan_workers(4, [2_000_000, 1_200_000, 700_000, 150_000], cores=2)  # the samples
    assert (plan.workers, plan.threads_per_worker) == (1, 2)
    text = plan.describe()
    assert text.startswith("ran in 1 process, its kernels on 2 threads (2 cores; --workers 4 "
                           "asked; 4 MB of input is too little for more than one process")
    two = plan_workers(2, [10 ** 10] * 2, cores=2).describe()
    assert two == "ran in 2 worker processes, the kernels of each on 1 thread (2 cores)"


def test_never_more_workers_than_files_or_cores_nor_threads_than_cores():
    big = 10 ** 10
    for requested, files, cores in itertools.product((1, 2, 3, 8), (1, 2, 5), (1, 2, 4, 16)):
        plan = plan_workers(requested, [big] * files, cores=cores)
        assert plan.workers == min(requested, files, cores)
        assert plan.workers * plan.threads_per_worker <= cores
        assert plan.threads_per_worker == max(1, cores // plan.workers)


def test_workers_grow_with_the_input_size():
    per_two = planning.STARTUP_S * planning.RATE_MB_S * 2 * 1e6  # bytes for two to pay off
    assert plan_workers(4, [per_two * 0.9 / 4] * 4, cores=8).workers == 1
    assert plan_workers(4, [per_two * 1.1 / 4] * 4, cores=8).workers == 4
    assert plan_workers(4, [per_two * 1.1 / 4] * 4, cores=3).workers == 3


def test_batch_summary_names_what_ran(demo_result, sample_cubes, tmp_path):
    from hsiffc.batch import correct_batch

    cal = demo_result.calibration.save(tmp_path / "cal.npz")
    summary = correct_batch([sample_cubes / "test_2200K.tif"], tmp_path / "out", cal, workers=4)
    assert summary.exit_status == 0
    assert summary.execution["workers"] == 1 and summary.execution["requested"] == 4
    assert summary.execution["text"] in summary.to_text()
    assert summary.to_dict()["execution"]["threads_per_worker"] == planning.available_cores()


@pytest.mark.parametrize("bad", [0, -1])
def test_plan_needs_at_least_one_worker_asked(bad):
    assert plan_workers(bad, [10], cores=2).workers == 1  # correct_batch refuses < 1 first
