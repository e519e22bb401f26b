"""The model and Adam of a training run (cnnps.train.optimiser) from the train stage's params."""

from __future__ import annotations

import pytest
import torch

from cnnps.train.params import Params
from cnnps.train.optimiser import lr_at, make_model


def test_the_train_stages_masks_set_the_models_mask_bits():
    assert Params().cpu.dropout_masks == "counter16"
    for masks, bits in (("counter16", 16), ("counter", 32), ("torch", 32)):
        model, _ = make_model(8, Params(cpu={"dropout_masks": masks}), torch.device("cpu"))
        assert model.mask_bits == bits


def test_the_optimiser_section_sets_adam_and_the_layers_section_the_cpu_pass():
    p = Params(optimiser={"lr": 3e-4, "weight_decay": 1e-5, "fused_adam": False}, cpu={"layers": "reference"})
    model, opt = make_model(8, p, torch.device("cpu"))
    group = opt.param_groups[0]
    assert (group["lr"], group["weight_decay"], group["fused"]) == (3e-4, 1e-5, None)
    assert model.fused_cpu_layers is False
    assert lr_at(Params(optimiser={"lr": 1e-3, "lr_milestones": [5], "lr_gamma": 0.5}).optimiser, 5) == \
        pytest.approx(5e-4)
