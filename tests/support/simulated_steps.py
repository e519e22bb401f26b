"""A simulated bf16-capable CPU for ``train.precision: auto``'s probe.

:class:`SimulatedSteps` makes the probe (:mod:`cnnps.train.precision`) see a machine with
bf16 kernels whose fp32 and bf16 training steps take ``1 / rates[precision]`` seconds,
whatever this machine is: the probe's steps still run for real (their losses are real,
bf16 on torch's reference kernels where the CPU has no bf16 units), only its clocks are
simulated. Change ``rates`` between two calls and the two precisions' speeds cross, as load
or another machine would make them. The run's own steps are not touched (the training
loop imported ``train_step`` before the patch)."""

from __future__ import annotations

import torch

from cnnps.train import optimiser
from cnnps.train import precision as tp


class SimulatedSteps:
    """``rates``: {precision: steps/s}; ``timed``: the precision of every probe step taken,
    in order (empty: no probe ran); ``cpu_share``: the share of their CPUs' time the probe's
    threads get (1: a quiet machine)."""

    def __init__(self, rates: dict, cpu_share: float = 1.0):
        self.rates, self.cpu_share = dict(rates), cpu_share
        self.wall = self.cpu = 0.0
        self.timed: list[str] = []

    def install(self, monkeypatch) -> "SimulatedSteps":
        real = optimiser.train_step

        def step(model, opt, maps, normals, device, precision, channels_last=True):
            loss = real(model, opt, maps, normals, device, precision, channels_last)
            dt = 1.0 / self.rates[precision]
            self.wall += dt
            self.cpu += dt * torch.get_num_threads() * self.cpu_share
            self.timed.append(precision)
            return loss

        monkeypatch.setattr(optimiser, "train_step", step)
        monkeypatch.setattr(tp, "wall_clock", lambda: self.wall)
        monkeypatch.setattr(tp, "cpu_clock", lambda: self.cpu)
        monkeypatch.setattr("cnnps.models.precision_probe.bf16_available", lambda device: True)
        return self
