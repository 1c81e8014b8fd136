"""Overlapping the stages of a recording: the next frame is read and deblurred while the last
one is written.

Writing a frame (PNG encoding, the video encoder's pipe) and deblurring the next one use
different resources for much of their time — OpenCV's encoders, torch's kernels and file reads
release the GIL — so running the producer one item ahead in a thread of its own hides most of
the writing. There is exactly one producer thread and items keep their order, so the results are
those of the sequential loop, bit for bit; memory holds at most ``depth`` finished items more.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

from .signals import shielded

__all__ = ["ahead"]

T = TypeVar("T")

_END = object()


class _Failed:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def ahead(items: Iterable[T], depth: int = 1) -> Iterator[T]:
    """Yield ``items`` in order, producing up to ``depth`` of them ahead in a background thread.

    An exception raised while producing is raised here, at the item where it happened. When the
    consumer stops early (an error while writing, Ctrl-C, ``close()``), the producer is told to
    stop and is waited for: it finishes the item it is on (one frame) and produces no more, so
    nothing it does outlives the ``with`` blocks around the loop.
    """
    if depth < 1:
        yield from items
        return
    slots: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(obj) -> bool:
        while not stop.is_set():
            try:
                slots.put(obj, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
        except BaseException as e:  # noqa: BLE001 - handed to the consumer, raised there
            put(_Failed(e))
            return
        put(_END)

    worker = threading.Thread(target=produce, name="trmd-ahead", daemon=True)
    worker.start()
    try:
        while True:
            # a Ctrl-C raised inside the queue's lock left it held, and the producer, which
            # must take it to hand over its item, then stopped the consumer's join for ever
            with shielded():
                obj = slots.get()
            if obj is _END:
                return
            if isinstance(obj, _Failed):
                raise obj.exc
            yield obj
    finally:
        stop.set()
        # an abandoned loop's generator can be finalised by the garbage collector on any
        # thread, the producer's own included: that one cannot wait for itself, and stops at
        # its next item as told (its items, still running there, close with it)
        if threading.current_thread() is not worker:
            worker.join()
            close = getattr(items, "close", None)
            if close is not None:
                close()  # a generator's own cleanup (open files) runs here, in the caller's thread
