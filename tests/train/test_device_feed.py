"""Batches to the training device (cnnps.train.device_feed) and the loop's time split (step_clock)."""

from __future__ import annotations

import time

import pytest
import torch

from cnnps.train.device_feed import PinnedRing, fed
from cnnps.train.step_clock import StepClock


def _batches(n=5, b=4, w=8):
    g = torch.Generator().manual_seed(0)
    return [(torch.rand(b, 1, w, w, generator=g).half(), torch.rand(b, 3, generator=g)) for _ in range(n)]


def test_cpu_batches_pass_through_untouched():
    batches = _batches()
    out = list(fed(iter(batches), torch.device("cpu")))
    assert len(out) == len(batches)
    for (m, n), (m2, n2) in zip(batches, out):
        assert m2 is m and n2 is n


def test_closing_the_feed_closes_the_source():
    closed = []

    def source():
        try:
            yield from _batches()
        finally:
            closed.append(True)

    clock = StepClock(torch.device("cpu"))
    for i, _ in enumerate(clock.waiting(fed(source(), torch.device("cpu")))):
        if i == 1:
            break
    import gc

    gc.collect()
    assert closed == [True]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_copies_equal_the_batches_and_keep_float16():
    dev = torch.device("cuda")
    batches = _batches(n=7)
    out = [tuple(t.cpu() for t in b) for b in fed(iter(batches), dev, slots=2)]
    for (m, n), (m2, n2) in zip(batches, out):
        assert m2.dtype == torch.float16
        assert torch.equal(m, m2) and torch.equal(n, n2)


def test_ring_refuses_zero_slots():
    with pytest.raises(ValueError, match="slots"):
        PinnedRing(torch.device("cpu"), 0)


def test_clock_splits_the_loop_time():
    clock = StepClock(torch.device("cpu"))

    def slow():
        for b in range(3):
            time.sleep(0.02)
            yield b

    t = time.perf_counter()
    for _ in clock.waiting(slow()):
        with clock.part("validation"):
            time.sleep(0.01)
    loop = time.perf_counter() - t
    s = clock.summary(loop)
    parts = clock.parts  # unrounded: the summary rounds each to the millisecond
    assert parts["data_wait"] >= 0.06 and parts["validation"] >= 0.03 and parts["checkpoints"] == 0
    assert parts["data_wait"] + parts["validation"] <= loop + 1e-9  # disjoint intervals inside the loop's (+ float rounding)
    for k in ("data_wait", "validation", "checkpoints"):
        assert abs(s[k] - parts[k]) <= 0.0005 + 1e-12
    assert 0 < s["overhead_share"] < 1 and 0 < s["data_wait_share"] < 1
    assert s["overhead_share"] == pytest.approx(clock.parts["validation"] / loop, abs=1e-4)
