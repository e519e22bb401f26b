"""made_ahead: the per-pixel batches of each step, in order, made in a background thread."""

from __future__ import annotations

import threading

import pytest
import torch

from cnnps.train.maps_ahead import made_ahead


def _make(log):
    def make(step):
        log.append((step, threading.get_ident(), torch.get_num_threads()))
        g = torch.Generator().manual_seed(step)
        return torch.rand(4, 3, generator=g), torch.full((2,), float(step))

    return make


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_the_batches_of_each_step_in_order_whatever_the_depth(depth):
    ref = [_make([])(s) for s in range(5, 12)]
    got = list(made_ahead(_make([]), range(5, 12), torch.device("cpu"), depth=depth))
    assert len(got) == len(ref)
    for (a, b), (c, d) in zip(got, ref):
        assert torch.equal(a, c) and torch.equal(b, d)


def test_made_in_another_thread_with_its_own_thread_count_and_the_callers_kept():
    outer = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        log: list = []
        it = made_ahead(_make(log), range(3), torch.device("cpu"), depth=1, cpu_threads=1)
        next(it)
        assert torch.get_num_threads() == 2  # the caller's team is its own
        rest = list(it)
        assert len(rest) == 2
        assert {t for _, t, _ in log} == {log[0][1]} and log[0][1] != threading.get_ident()
        assert {n for _, _, n in log} == {1}
        assert torch.get_num_threads() == 2
        seen = []  # and threads started later get the caller's count again
        t = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
        t.start()
        t.join()
        assert seen == [2]
    finally:
        torch.set_num_threads(outer)


def test_an_error_reaches_the_consumer_at_its_step():
    def make(step):
        if step == 2:
            raise ValueError("bad step 2")
        return (torch.zeros(1),)

    it = made_ahead(make, range(5), torch.device("cpu"), depth=2)
    assert len([next(it), next(it)]) == 2
    with pytest.raises(ValueError, match="bad step 2"):
        next(it)


def test_closing_early_stops_the_thread():
    before = set(threading.enumerate())
    it = made_ahead(_make([]), iter(range(10**9)), torch.device("cpu"), depth=1)
    next(it)
    assert set(threading.enumerate()) - before  # the maker's thread runs
    it.close()
    assert not [t for t in set(threading.enumerate()) - before if t.is_alive()]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_cuda_the_batches_wait_for_their_stream():
    dev = torch.device("cuda")

    def make(step):
        g = torch.Generator(device=dev).manual_seed(step)
        return (torch.rand(1 << 16, generator=g, device=dev).mul_(2).add_(1),)

    ref = [make(s)[0] for s in range(4)]
    got = [b[0] for b in made_ahead(make, range(4), dev, depth=2)]
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b)
