"""Read-ahead of input frames (io/prefetch.py): order, errors, early stop."""
from __future__ import annotations

import threading
import time

import pytest

from splat_slam_ros.io.prefetch import prefetch


def test_prefetch_keeps_order_and_reads_ahead_in_another_thread():
    where = []

    def gen():
        for i in range(20):
            where.append(threading.current_thread().name)
            yield i
    assert list(prefetch(gen(), 3)) == list(range(20))
    assert set(where) == {"prefetch"}
    assert list(prefetch(range(5), 0)) == [0, 1, 2, 3, 4]


def test_prefetch_raises_the_producer_error_at_its_place():
    class Bad(ValueError):
        pass

    def gen():
        yield 1
        yield 2
        raise Bad("frame 3 is broken")
    got = []
    with pytest.raises(Bad, match="frame 3"):
        for x in prefetch(gen(), 2):
            got.append(x)
    assert got == [1, 2]


def test_prefetch_stops_reading_when_the_consumer_stops():
    produced = []

    def gen():
        for i in range(1000):
            produced.append(i)
            yield i
    it = prefetch(gen(), 2)
    assert [next(it) for _ in range(3)] == [0, 1, 2]
    it.close()
    time.sleep(0.3)
    n = len(produced)
    time.sleep(0.3)
    assert len(produced) == n <= 3 + 2 + 1          # at most depth ahead (+ the one in hand)
    assert not any(t.name == "prefetch" and t.is_alive() for t in threading.enumerate())
