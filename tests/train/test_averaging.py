"""WeightAverage: the running mean of state dicts against torch.stack(...).mean."""

from __future__ import annotations

import pytest
import torch

from cnnps.train.averaging import WeightAverage


def _states(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [{"w": torch.randn(3, 4, generator=g), "b": torch.randn(4, generator=g).half()} for _ in range(n)]


def test_the_mean_is_the_mean_of_the_added_states_from_the_first_step_on():
    states = _states(5)
    avg = WeightAverage(from_step=3)
    for step, s in enumerate(states, start=1):
        if avg.wants(step):
            avg.add(step, s)
    assert avg.n == 3 and avg.last_step == 5
    mean = avg.mean(like=states[0])
    torch.testing.assert_close(mean["w"], torch.stack([s["w"] for s in states[2:]]).mean(0), rtol=1e-6, atol=1e-6)
    assert mean["b"].dtype == torch.float16
    torch.testing.assert_close(mean["b"].float(), torch.stack([s["b"].float() for s in states[2:]]).mean(0),
                               rtol=1e-3, atol=1e-3)


def test_a_step_is_added_once_and_zero_is_off():
    avg = WeightAverage(from_step=1)
    avg.add(4, _states(1)[0])
    assert not avg.wants(4) and avg.wants(5) and not avg.wants(0)
    off = WeightAverage(0)
    assert not any(off.wants(s) for s in range(10))
    with pytest.raises(ValueError, match="no weights"):
        off.mean()


def test_the_state_round_trips_and_the_resumed_mean_equals_the_straight_one():
    states = _states(4, seed=1)
    straight = WeightAverage(1)
    for i, s in enumerate(states, 1):
        straight.add(i, s)
    first = WeightAverage(1)
    for i, s in enumerate(states[:2], 1):
        first.add(i, s)
    resumed = WeightAverage(1)
    resumed.load_state_dict(first.state_dict())
    for i, s in enumerate(states[2:], 3):
        resumed.add(i, s)
    for k in ("w", "b"):
        torch.testing.assert_close(resumed.mean()[k], straight.mean()[k], rtol=0, atol=0)
    resumed.load_state_dict(None)
    assert resumed.n == 0 and resumed.wants(1)
