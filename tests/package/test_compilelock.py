"""The test processes' compile lock (tests/compilelock.py): a compile of a disk-cached build
waits while another process compiles the same signature, then loads it."""

from __future__ import annotations

import threading
import uuid

import compilelock
import pytest


@pytest.mark.skipif(compilelock.fcntl is None, reason="no fcntl (Windows): no compile lock")
def test_a_compile_waits_for_the_lock_of_its_signature(tmp_path, monkeypatch):
    from numba import types

    name = f"lockprobe_{uuid.uuid4().hex}"
    (tmp_path / f"{name}.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef add_one(x):\n    return x + 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    probe = __import__(name)
    locks = tmp_path / "locks"
    locks.mkdir()
    previous = compilelock.install(str(locks))
    try:
        done = []
        with open(compilelock.lock_path(probe.add_one, (types.int64,)), "a") as held:
            # another process compiling this signature
            compilelock.fcntl.flock(held, compilelock.fcntl.LOCK_EX)
            worker = threading.Thread(target=lambda: done.append(probe.add_one(1)))
            worker.start()
            worker.join(0.5)
            assert worker.is_alive() and not done
        worker.join(60)
        assert done == [2]
        assert probe.add_one(41) == 42  # compiled once: the next call needs no lock
    finally:
        compilelock.install(previous)


def test_the_test_processes_of_a_parallel_run_share_the_lock(request):
    folder = getattr(request.config, "workerinput", {}).get("hsiffc_compile_locks")
    if folder is None or compilelock.fcntl is None:
        pytest.skip("not a test process of pytest -n, or no fcntl")
    from numba.core.dispatcher import Dispatcher

    assert getattr(Dispatcher.compile, "_hsiffc_test_lock", False)
    assert compilelock.install(folder) == folder  # the run's folder was installed
