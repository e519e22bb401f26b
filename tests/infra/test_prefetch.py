"""``prefetched``: order kept, errors raised where they happened, thread stopped on close."""

from __future__ import annotations

import threading
import time

import pytest

from cnnps.infra.prefetch import prefetched


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_results_come_in_order(depth):
    def slow_square(x):
        time.sleep(0.001 * (x % 3))  # finishing times vary; the order must not
        return x * x

    assert list(prefetched(slow_square, range(40), depth)) == [x * x for x in range(40)]


def test_work_runs_ahead_in_another_thread():
    seen = []

    def record(x):
        seen.append((x, threading.current_thread().name))
        return x

    it = prefetched(record, range(10), depth=3)
    assert next(it) == 0
    deadline = time.monotonic() + 5
    while len(seen) < 4 and time.monotonic() < deadline:  # items 1..3 are computed before they are asked for
        time.sleep(0.01)
    assert len(seen) >= 4 and {name for _, name in seen} == {"cnnps-prefetch"}
    it.close()


def test_an_error_is_raised_at_its_item():
    def fail_on_five(x):
        if x == 5:
            raise ValueError("bad row group 5")
        return x

    got = []
    with pytest.raises(ValueError, match="bad row group 5"):
        for x in prefetched(fail_on_five, range(10), depth=2):
            got.append(x)
    assert got == [0, 1, 2, 3, 4]


def test_closing_early_stops_the_thread():
    before = {t.ident for t in threading.enumerate()}
    it = prefetched(lambda x: x, iter(range(10**9)), depth=2)
    assert next(it) == 0
    it.close()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(
        t.name == "cnnps-prefetch" and t.ident not in before for t in threading.enumerate()
    ):
        time.sleep(0.01)
    assert not any(t.name == "cnnps-prefetch" and t.ident not in before and t.is_alive() for t in threading.enumerate())
