"""Read ahead in a background thread, keeping the order: ``prefetched(fn, items, depth)``.

The training loader decodes Parquet row groups (pyarrow's C++ code, which releases the
GIL) while the main thread runs the shuffle buffer and the training step; results come
back in exactly the order of ``items``, so the batches (and resuming mid-epoch) are the
same as without the thread. ``depth`` results at most wait in the queue (memory: depth
row groups). An exception in ``fn`` is raised in the consumer at the item that failed.
Closing the generator early (``break``, garbage collection) stops the thread.
"""

from __future__ import annotations

import queue
import threading
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_DONE = object()


def prefetched(fn: Callable[[T], R], items: Iterable[T], depth: int = 2) -> Iterator[R]:
    """``fn(item)`` for every item, in order, computed up to ``depth`` items ahead in one
    background thread (``depth`` 0: in the caller's thread, no thread at all)."""
    if depth <= 0:
        for item in items:
            yield fn(item)
        return
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(value) -> bool:
        while not stop.is_set():
            try:
                q.put(value, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for item in items:
                if stop.is_set() or not put((True, fn(item))):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            put((False, exc))
            return
        put((True, _DONE))

    thread = threading.Thread(target=work, name="cnnps-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            ok, value = q.get()
            if not ok:
                raise value
            if value is _DONE:
                return
            yield value
    finally:
        stop.set()
        thread.join(timeout=5)
