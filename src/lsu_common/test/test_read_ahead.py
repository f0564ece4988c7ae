"""read_ahead: order, the producer's error where it occurred, an early stop that ends the producer."""

import threading

import pytest

from lsu_common.read_ahead import read_ahead


def test_items_come_in_order_from_another_thread_with_its_cpu_time():
    threads = set()

    def items():
        for i in range(50):
            threads.add(threading.current_thread().name)
            yield i

    cpu: dict[str, float] = {}
    assert list(read_ahead(items(), 3, "producer", cpu)) == list(range(50))
    assert threads == {"producer"} and cpu["producer_s"] >= 0.0


def test_the_producers_error_comes_out_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise ValueError("bad item 3")

    got = []
    with pytest.raises(ValueError, match="bad item 3"):
        for item in read_ahead(items(), 2, "producer"):
            got.append(item)
    assert got == [1, 2]


def test_leaving_early_stops_the_producer_before_its_next_item():
    made = []

    def items():
        for i in range(1000):
            made.append(i)
            yield i

    for item in read_ahead(items(), 2, "producer"):
        if item == 3:
            break
    # the thread was joined: it made at most the queue's depth and the one it was putting beyond what was taken
    assert len(made) <= 4 + 2 + 1 and made == list(range(len(made)))
    assert not any(t.name == "producer" and t.is_alive() for t in threading.enumerate())
