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


def test_train_model_builds_the_network_and_a_step_minimises_its_heads_loss():
    """A regression step's loss is the MSE of the normals (the paper's network, its weights
    those of build_model's defaults); a heat-map step's is the heat-map loss, on (B, b^2, w, w)."""
    from cnnps.models.heads import head_loss
    from cnnps.models.model_options import build_model, model_options
    from cnnps.train.optimiser import train_step

    cpu = torch.device("cpu")
    model, _ = make_model(8, Params(seed=4), cpu)
    torch.manual_seed(4)
    plain = build_model(w=8)
    assert model_options(model) == {"arch": "cnnps", "head": "regression", "patch": 1}
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), plain.state_dict().values()))
    p = Params(seed=4, dropout=0.0, model={"arch": "unet", "head": "heatmap", "patch": 3})
    net, opt = make_model(8, p, cpu)
    assert model_options(net) == {"arch": "unet", "head": "heatmap", "patch": 3}
    maps, normals = torch.rand(6, 9, 8, 8), torch.nn.functional.normalize(torch.rand(6, 3) + 0.1, dim=1)
    with torch.no_grad():
        want = float(head_loss("heatmap", net(maps), normals))
    got = float(train_step(net, opt, maps, normals, cpu, "fp32", channels_last=False))
    assert got == pytest.approx(want, rel=1e-6) and got > 0
    from cnnps.infra.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^train\.model: .*multiple of 4"):
        make_model(10, p, cpu)
