"""`overlap.ahead`: the producer runs ahead in its own thread, in order, bounded, and stops."""

from __future__ import annotations

import threading
import time

import pytest

from trmd_cli.overlap import ahead


def test_order_and_values_are_kept():
    assert list(ahead(iter(range(500)), depth=2)) == list(range(500))
    assert list(ahead([], depth=1)) == []
    assert list(ahead(range(5), depth=0)) == list(range(5))


def test_the_producer_runs_in_another_thread_at_most_depth_ahead():
    produced: list[int] = []
    threads: set[str] = set()

    def items():
        for i in range(20):
            threads.add(threading.current_thread().name)
            produced.append(i)
            yield i

    lead = []
    for i in ahead(items(), depth=2):
        time.sleep(0.01)  # a slow consumer: the producer fills the queue and waits
        lead.append(len(produced) - (i + 1))
    assert threading.current_thread().name not in threads
    # queued (depth) + the one the producer holds while the queue is full
    assert max(lead) <= 3
    assert max(lead) >= 1  # it did run ahead


def test_a_producer_error_is_raised_at_its_item():
    def items():
        yield 0
        yield 1
        raise ValueError("frame 2 is damaged")

    got = []
    with pytest.raises(ValueError, match="frame 2 is damaged"):
        for x in ahead(items()):
            got.append(x)
    assert got == [0, 1]


def test_stopping_early_stops_the_producer_and_closes_it():
    produced: list[int] = []
    closed = threading.Event()

    def items():
        try:
            for i in range(10_000):
                produced.append(i)
                yield i
        finally:
            closed.set()

    before = set(threading.enumerate())  # (another test's abandoned loop may still run)
    for x in ahead(items(), depth=1):
        if x == 3:
            break
    assert closed.is_set()
    assert len(produced) <= 3 + 1 + 2  # nothing was made after the loop ended
    assert not _producers(before)


def test_an_error_in_the_consumer_stops_the_producer():
    produced: list[int] = []

    def items():
        for i in range(10_000):
            produced.append(i)
            yield i

    with pytest.raises(RuntimeError):
        for x in ahead(items()):
            if x == 5:
                raise RuntimeError("disk full")
    n = len(produced)
    time.sleep(0.1)
    assert len(produced) == n <= 5 + 1 + 2


def test_finalised_on_the_producer_thread_it_stops_without_waiting_for_itself():
    """An abandoned loop's generator may be finalised by the garbage collector on the
    producer's own thread: closing it there neither raises ("cannot join current thread",
    before) nor touches the running items; the producer then stops."""
    box: dict = {}
    errors: list[BaseException] = []
    produced: list[int] = []

    def items():
        for i in range(1000):
            if i == 2:
                try:
                    box["loop"].close()  # as the collector would, on this thread
                except BaseException as e:  # noqa: BLE001 - what the test looks for
                    errors.append(e)
            produced.append(i)
            yield i

    before = set(threading.enumerate())
    loop = ahead(items(), depth=1)
    box["loop"] = loop
    assert next(loop) == 0
    deadline = time.monotonic() + 5
    while _producers(before):
        assert time.monotonic() < deadline, "the producer did not stop"
        time.sleep(0.01)
    assert errors == []
    assert len(produced) <= 4  # it stopped at the item after the close


def _producers(before: set) -> list:
    """The producer threads started since ``before`` that still run."""
    return [t for t in set(threading.enumerate()) - before
            if t.name == "trmd-ahead" and t.is_alive()]
