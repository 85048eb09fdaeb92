"""Read-ahead of hsiffc correct (hsiffc.batch.task.Prefetch): order, errors, early close."""

from __future__ import annotations

import time

import pytest

from hsiffc.batch.task import Prefetch


def test_items_arrive_in_order_and_decoding_runs_ahead():
    seen = []

    def source():
        for i in range(6):
            seen.append(i)
            yield i

    frames = Prefetch(source(), depth=2)
    it = iter(frames)
    assert next(it) == 0
    time.sleep(0.2)  # the thread reads ahead while the caller works, at most depth + 1 items
    assert 2 <= len(seen) <= 4
    assert list(it) == [1, 2, 3, 4, 5]
    frames.close()


def test_an_error_in_the_source_reaches_the_caller_at_its_item():
    def source():
        yield "a"
        raise OSError("truncated file")

    frames = Prefetch(source())
    got = []
    with pytest.raises(OSError, match="truncated"):
        for item in frames:
            got.append(item)
    assert got == ["a"]
    frames.close()


def test_close_stops_the_thread_before_the_source_is_exhausted():
    produced = []

    def source():
        for i in range(1000):
            produced.append(i)
            yield i

    frames = Prefetch(source(), depth=1)
    assert next(iter(frames)) == 0
    frames.close()
    n = len(produced)
    time.sleep(0.1)
    assert len(produced) == n < 1000
