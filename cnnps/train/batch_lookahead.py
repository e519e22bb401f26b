"""An iterator that can read its next item early: the training loop reads its next batch
while the step's helper processes finish their rows (:mod:`cnnps.train.step_processes`).

The items and their order are those of the wrapped iterator; only *when* each is read
changes. Example::

    it = Lookahead(iter([1, 2, 3]))
    next(it)   # 1
    it.pull()  # reads 2 now
    next(it)   # 2, already read
    list(it)   # [3]
"""

from __future__ import annotations

from collections.abc import Iterator

_EMPTY = object()


class Lookahead:
    """``items``, with :meth:`pull` to read the next one ahead of :func:`next`. Closing it
    closes ``items`` (when it has ``close``)."""

    def __init__(self, items: Iterator):
        self._items = items
        self._next = _EMPTY
        self._done = False

    def pull(self) -> None:
        """Read the next item now (once: a second pull before :func:`next` does nothing)."""
        if self._next is _EMPTY and not self._done:
            try:
                self._next = next(self._items)
            except StopIteration:
                self._done = True

    def __iter__(self) -> Lookahead:
        return self

    def __next__(self):
        self.pull()
        if self._next is _EMPTY:
            raise StopIteration
        item, self._next = self._next, _EMPTY
        return item

    def close(self) -> None:
        self._next, self._done = _EMPTY, True
        close = getattr(self._items, "close", None)
        if close is not None:
            close()
