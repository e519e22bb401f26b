"""Averages of a run's weights: the mean over its checkpoints (stochastic weight
averaging, :class:`WeightAverage`) and an exponential moving average over its steps
(:class:`WeightEMA`).

With ``train.optimiser.average_from: N`` (N >= 1) the train stage keeps the running mean of
the network's weights at every checkpoint from step N on (each ``checkpoint_every`` steps
and the last step), and ``model.pt`` is that mean instead of the last step's weights
(Izmailov et al., "Averaging Weights Leads to Wider Optima and Better Generalization",
UAI 2018). The network has no batch-norm, so the mean needs no statistics pass.

The mean travels in every checkpoint, so a killed run resumes to the same mean; the steps
it averages are the checkpoints' steps, so ``checkpoint_every`` chooses them. Why and
when: docs/models.md (a short fine-tune's checkpoints are noisy on real objects, their
mean is not).

Example::

    avg = WeightAverage(from_step=200)
    for step in (100, 200, 300):
        if avg.wants(step):
            avg.add(step, model.state_dict())      # steps 200 and 300
    model.load_state_dict(avg.mean())             # (w200 + w300) / 2

With ``train.optimiser.ema_decay: d`` (0 < d < 1) the stage keeps, after every optimiser
step, e <- d e + (1 - d) w (e the first step's weights at the start; float32, on the
weights' device), and ``model.pt`` is e; it travels in the checkpoints like the mean. A
decay d averages over about 1 / (1 - d) steps (0.999: the last thousand or so).
"""

from __future__ import annotations

import torch


class WeightAverage:
    """Running mean of state dicts added at steps >= ``from_step`` (0: never)."""

    def __init__(self, from_step: int = 0):
        self.from_step = int(from_step)
        self.n = 0
        self.last_step: int | None = None
        self._mean: dict[str, torch.Tensor] | None = None

    def wants(self, step: int) -> bool:
        """Whether the weights of ``step`` belong in the mean (once a step)."""
        return self.from_step > 0 and step >= self.from_step and step != self.last_step

    def add(self, step: int, state: dict[str, torch.Tensor]) -> None:
        """Fold ``state`` (the model's state dict at ``step``) into the mean, in float32."""
        self.n += 1
        self.last_step = int(step)
        if self._mean is None:
            self._mean = {k: v.detach().to("cpu", torch.float32, copy=True) for k, v in state.items()}
            return
        for k, v in state.items():
            m = self._mean[k]
            m += (v.detach().to("cpu", torch.float32) - m) / self.n

    def mean(self, like: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """The mean state dict; with ``like`` (a state dict) in its dtypes. Raises when empty."""
        if self._mean is None:
            raise ValueError("no weights were averaged")
        if like is None:
            return {k: v.clone() for k, v in self._mean.items()}
        return {k: v.to(like[k].dtype) for k, v in self._mean.items()}

    def state_dict(self) -> dict:
        """What a checkpoint keeps: ``from_step``, ``n``, ``last_step`` and the mean."""
        return {"from_step": self.from_step, "n": self.n, "last_step": self.last_step, "mean": self._mean}

    def load_state_dict(self, state: dict | None) -> None:
        """Take a checkpoint's average back (None: a checkpoint without one, an empty mean)."""
        if not state:
            self.n, self.last_step, self._mean = 0, None, None
            return
        self.n, self.last_step, self._mean = int(state["n"]), state["last_step"], state["mean"]


class WeightEMA:
    """Exponential moving average of a model's weights, updated once a step (``decay`` 0: off)."""

    def __init__(self, decay: float = 0.0):
        self.decay = float(decay)
        self.n = 0  # steps folded in
        self._ema: dict[str, torch.Tensor] | None = None

    def update(self, state: dict[str, torch.Tensor]) -> None:
        """Fold the weights after one more step into the average (floating tensors; others copied)."""
        if not self.decay:
            return
        self.n += 1
        if self._ema is None:
            self._ema = {k: v.detach().to(torch.float32, copy=True) for k, v in state.items()}
            return
        with torch.no_grad():
            for k, v in state.items():
                e = self._ema[k]
                if torch.is_floating_point(v):
                    e.mul_(self.decay).add_(v.detach().to(torch.float32), alpha=1.0 - self.decay)
                else:
                    e.copy_(v)

    def mean(self, like: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """The average as a state dict (on the CPU; with ``like``, in its dtypes). Raises when empty."""
        if self._ema is None:
            raise ValueError("no weights were averaged")
        return {k: v.detach().to("cpu", like[k].dtype if like is not None else v.dtype, copy=True)
                for k, v in self._ema.items()}

    def state_dict(self) -> dict:
        """What a checkpoint keeps: ``decay``, ``n`` and the average (on the CPU)."""
        return {"decay": self.decay, "n": self.n,
                "ema": None if self._ema is None else {k: v.detach().cpu() for k, v in self._ema.items()}}

    def load_state_dict(self, state: dict | None, device=None) -> None:
        """Take a checkpoint's average back onto ``device`` (None: a checkpoint without one)."""
        if not state or state.get("ema") is None:
            self.n, self._ema = 0, None
            return
        self.n = int(state["n"])
        self._ema = {k: v.to(device or "cpu", torch.float32) for k, v in state["ema"].items()}
