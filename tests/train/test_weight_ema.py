"""train.optimiser.ema_decay: model.pt is the exponential moving average of the weights over
the steps, checked against the average recomputed from every step's checkpoint, and a
killed run resumes to the same average."""

from __future__ import annotations

import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.models.checkpoint import load_checkpoint
from cnnps.stages import train
from cnnps.train.resume import checkpoint_path, read_training_state

BASE = dict(pixelwise={"share": 1.0, "w": 16}, cpu={"threads": 1}, data={"batch_size": 16}, progress=False,
            log_every=1, precision="fp32", max_steps=5, checkpoint_every=1, keep_checkpoints=10, val_every=0,
            val_max_rows=100)


def test_ema_is_the_moving_average_of_every_steps_weights_and_resumes_to_it(tmp_path):
    d = 0.6
    p = train.Params(**BASE, optimiser={"lr": 1e-3, "ema_decay": d})
    a, b = tmp_path / "a", tmp_path / "b"
    ma = train.run(p, a)
    steps = [read_training_state(checkpoint_path(a / "train/checkpoints", s))["model"] for s in range(1, 6)]
    expected = {k: v.double() for k, v in steps[0].items()}
    for state in steps[1:]:  # independent of WeightEMA: the recurrence in float64
        expected = {k: d * expected[k] + (1 - d) * state[k].double() for k in expected}
    shipped = load_checkpoint(a / "train/model.pt")[0].state_dict()
    for k, v in shipped.items():
        torch.testing.assert_close(v.double(), expected[k], rtol=0, atol=1e-6)
    assert any(not torch.allclose(shipped[k], steps[-1][k]) for k in shipped)  # not the last step's weights
    assert ma["average"]["ema_decay"] == d and ma["average"]["steps"] == 5
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=3)
    train.run(p, b)
    resumed = load_checkpoint(b / "train/model.pt")[0].state_dict()
    for k in shipped:
        torch.testing.assert_close(resumed[k], shipped[k], rtol=0, atol=0)


def test_ema_settings():
    assert "optimiser_ema_decay" not in train.Params(**BASE).flat()  # off: the key a run had before
    assert train.Params(**BASE, optimiser={"ema_decay": 0.99}).flat()["optimiser_ema_decay"] == 0.99
    with pytest.raises(ConfigError, match="ema_decay"):
        train.Params(**BASE, optimiser={"ema_decay": 1.0})
    with pytest.raises(ConfigError, match="set one of them"):
        train.Params(**BASE, optimiser={"ema_decay": 0.9, "average_from": 2})
