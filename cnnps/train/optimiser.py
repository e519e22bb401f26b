"""Training a CNN-PS: the model, its Adam optimiser and learning-rate schedule as one object
(:class:`AdamSchedule`, which the loop asks once a step), one step.

``params`` here is the train section's typed tree (:class:`cnnps.train.params.Params`,
its ``optimiser`` and ``cpu`` sections included).

None of the speed settings changes the model or the loss: ``channels_last`` (NHWC
activations), ``optimiser.fused_adam`` (torch's fused kernel: the same algorithm,
one pass per tensor), ``precision: bf16`` (autocast) and ``compile`` (torch.compile)
change the float rounding (and, for channels_last or compile, which elements a dropout
mask draws); what each gains: docs/performance.md#training-settings. Used by
:mod:`cnnps.train.loop` and benchmarks/train/step_variants.py.
"""

from __future__ import annotations

from contextlib import nullcontext

import torch
from torch import nn

from cnnps.infra.errors import ConfigError
from cnnps.models.heads import training_loss
from cnnps.models.model_options import build_model
from cnnps.models.train_layers import COUNTER_MASK_BITS
from cnnps.train.params import OptimiserParams, Params


def lr_at(optimiser: OptimiserParams, step: int) -> float:
    """The learning rate of optimiser step ``step + 1`` (``step`` steps done): ``lr``
    times ``lr_gamma`` for every milestone already reached, of ``optimiser`` (the
    ``train.optimiser`` section). A step schedule does not depend on ``max_steps``, so
    raising ``max_steps`` still continues a finished run.

    >>> lr_at(OptimiserParams(lr=1e-3, lr_gamma=0.5, lr_milestones=(10,)), 10)
    0.0005
    """
    return optimiser.lr * optimiser.lr_gamma ** sum(step >= m for m in optimiser.lr_milestones)


def set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    for group in opt.param_groups:
        group["lr"] = lr


class AdamSchedule:
    """Adam and its learning-rate schedule from one ``train.optimiser`` section (nerfstudio's
    optimiser-and-scheduler config): :meth:`build` makes the optimiser, the training run's
    and the precision probe's alike (``lr``, ``weight_decay``, ``fused_adam``), and
    :meth:`before_step` sets the learning rate of the next step (:func:`lr_at`), which the
    loop calls once before every step. Setting the same rate again changes nothing, so a
    resumed or uninterrupted run takes the same steps::

        schedule = AdamSchedule(params.optimiser)
        opt = schedule.build(model.parameters())
        for step in range(steps):          # steps done
            schedule.before_step(opt, step)
            ...                            # forward, backward, opt.step()
    """

    def __init__(self, optimiser: OptimiserParams):
        self.params = optimiser

    def build(self, parameters) -> torch.optim.Adam:
        o = self.params
        return torch.optim.Adam(parameters, lr=o.lr, weight_decay=o.weight_decay, fused=True if o.fused_adam else None)

    def lr_at(self, step: int) -> float:
        """The learning rate of the step after ``step`` steps (:func:`lr_at`)."""
        return lr_at(self.params, step)

    def before_step(self, opt: torch.optim.Optimizer, step: int) -> float:
        """Set ``opt``'s learning rate for the step after ``step`` steps; returns it."""
        lr = self.lr_at(step)
        set_lr(opt, lr)
        return lr


def autocast(device: torch.device, precision: str):
    """bf16 autocast on ``device`` for ``precision == "bf16"``, nothing for "fp32" (a run's
    ``auto`` is resolved before a step: :mod:`cnnps.train.precision`)."""
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    if precision != "fp32":
        raise ValueError(f"a step runs in fp32 or bf16, not {precision!r}")
    return nullcontext()


def make_model(w: int, params: Params, device: torch.device,
               in_channels: int = 1) -> tuple[nn.Module, torch.optim.Adam]:
    """A fresh network of the options ``params.model`` (``arch``, ``head``, ``patch``:
    :func:`cnnps.models.model_options.build_model`; the defaults are the paper's CNN-PS)
    taking (B, ``in_channels`` patch^2, w, w) maps, weights drawn after
    ``torch.manual_seed(params.seed)``, on ``device``, channels_last if asked, and its
    Adam optimiser (:meth:`AdamSchedule.build`)."""
    torch.manual_seed(params.seed)
    try:
        model = build_model(**params.model.options(), w=w, in_channels=in_channels, dropout=params.dropout)
    except ValueError as exc:  # e.g. a U-Net's w must be a multiple of 4
        raise ConfigError(f"train.model: {exc}") from None
    model = model.to(device)
    model.fused_cpu_layers = params.cpu.layers == "fused"
    model.mask_bits = COUNTER_MASK_BITS.get(params.cpu.dropout_masks, 32)
    if params.channels_last:
        model = model.to(memory_format=torch.channels_last)
    return model, AdamSchedule(params.optimiser).build(model.parameters())


def compile_model(model, params: Params):
    """``torch.compile(model)`` when ``params.compile``, else ``model``.

    Compilation happens lazily on the first call; :mod:`cnnps.train.loop` falls back
    to the eager model (with a warning) when that first compiled step fails.
    """
    if not params.compile:
        return model
    return torch.compile(model)


def train_step(model, opt, maps: torch.Tensor, normals: torch.Tensor, device: torch.device, precision: str,
               channels_last: bool) -> torch.Tensor:
    """One Adam step on a batch (maps (B,C,w,w), C the model's input channels times its
    patch's b^2, unit normals (B,3)); the loss of the model's head
    (:func:`cnnps.models.heads.training_loss`: the MSE of the normals for ``regression``,
    the heat-map loss for ``heatmap``), detached (a tensor on ``device``: reading it out is
    left to the caller, it waits for the step)."""
    maps = maps.to(device, non_blocking=True).float()  # float16 maps are converted on the device
    normals = normals.to(device, non_blocking=True)
    if channels_last:
        maps = maps.contiguous(memory_format=torch.channels_last)
    with autocast(device, precision):
        pred = model(maps)
    loss = training_loss(model, pred, normals)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss.detach()
