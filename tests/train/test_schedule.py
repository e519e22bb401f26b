"""cnnps.train.optimiser.AdamSchedule: one object builds Adam and sets each step's rate."""

from __future__ import annotations

import pytest
import torch

from cnnps.train.optimiser import AdamSchedule, lr_at
from cnnps.train.params import OptimiserParams


def test_the_schedule_builds_the_runs_adam_and_sets_each_steps_rate():
    o = OptimiserParams(lr=2e-3, lr_milestones=(3, 5), lr_gamma=0.5, weight_decay=1e-4, fused_adam=False)
    schedule = AdamSchedule(o)
    opt = schedule.build([torch.nn.Parameter(torch.zeros(2))])
    assert isinstance(opt, torch.optim.Adam)
    group = opt.param_groups[0]
    assert (group["lr"], group["weight_decay"]) == (2e-3, 1e-4)  # the decay the probe once left out
    rates = [schedule.before_step(opt, step) for step in range(7)]
    assert rates == pytest.approx([2e-3, 2e-3, 2e-3, 1e-3, 1e-3, 5e-4, 5e-4])
    assert rates == [lr_at(o, k) for k in range(7)] and opt.param_groups[0]["lr"] == rates[-1]


def test_the_precision_probe_steps_with_the_same_optimiser(monkeypatch):
    from cnnps.train import optimiser, precision
    from cnnps.train.params import Params

    built = []
    real = optimiser.AdamSchedule.build

    def spy(self, parameters):
        opt = real(self, parameters)
        built.append(opt.param_groups[0]["weight_decay"])
        return opt

    monkeypatch.setattr(optimiser.AdamSchedule, "build", spy)
    params = Params(optimiser={"weight_decay": 3e-4, "fused_adam": False})
    net = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(16, 3))
    maps, normals = torch.rand(4, 1, 4, 4), torch.nn.functional.normalize(torch.rand(4, 3), dim=1)
    precision.time_steps(net, params, torch.device("cpu"), "fp32", maps, normals)
    assert built == [3e-4]
