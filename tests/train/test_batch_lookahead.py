from __future__ import annotations

from cnnps.train.batch_lookahead import Lookahead


def _counted(items, reads):
    for item in items:
        reads.append(item)
        yield item


def test_lookahead_reads_early_and_yields_the_same_items_in_order():
    reads = []
    it = Lookahead(_counted([1, 2, 3], reads))
    assert next(it) == 1 and reads == [1]
    it.pull()
    assert reads == [1, 2]  # read now, before next() asks
    it.pull()
    assert reads == [1, 2]  # once
    assert next(it) == 2 and reads == [1, 2]
    assert list(it) == [3]
    it.pull()  # past the end: nothing, and no error
    assert list(it) == []


def test_lookahead_of_an_empty_iterator_and_close():
    assert list(Lookahead(iter([]))) == []
    closed = []

    def gen():
        try:
            yield from range(10)
        finally:
            closed.append(True)

    it = Lookahead(gen())
    assert next(it) == 0
    it.pull()
    it.close()  # a batch read ahead is dropped; the source is closed
    assert closed == [True] and list(it) == []
