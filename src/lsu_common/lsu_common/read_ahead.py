"""An iterator's items made ahead by a thread of their own (no rclpy).

Used where producing an item costs CPU that can run beside the consumer's: a bag read (and
decompressed) while the previous messages are extracted, a simulated pair rendered while the
previous one waits for its readers. Items come out in order; an exception of the producer comes
out of the consumer's iteration where it occurred; leaving the iteration early stops the producer
before its next item.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from typing import TypeVar

T = TypeVar("T")

__all__ = ["read_ahead"]

_DONE = object()


def read_ahead(items: Iterator[T], depth: int, name: str, cpu: dict[str, float] | None = None) -> Iterator[T]:
    """``items`` produced by a daemon thread named ``name``, at most ``depth`` ahead of the consumer.

    ``cpu["producer_s"]`` (with ``cpu``) is the producing thread's CPU time so far. When the consumer
    stops early the producer ends after the item it is making (a generator waiting inside ``items``
    finishes that wait first); the thread is joined for at most 5 s.
    """
    box: queue.Queue[object] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item: object) -> bool:
        """Queue ``item`` unless the consumer has left; False then."""
        while not stop.is_set():
            try:
                box.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        t0 = time.thread_time()
        try:
            for item in items:
                queued = put(item)
                if cpu is not None:
                    cpu["producer_s"] = time.thread_time() - t0
                if not queued:
                    return
            if cpu is not None:
                cpu["producer_s"] = time.thread_time() - t0
            put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which raises it
            put(exc)

    producer = threading.Thread(target=produce, name=name, daemon=True)
    producer.start()
    try:
        while True:
            item = box.get()
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item  # type: ignore[misc]
    finally:
        stop.set()
        producer.join(timeout=5.0)
