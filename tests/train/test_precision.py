"""``train.precision: auto``: the pick rule, a probe that leaves the run untouched, and the
choice and segments a run records."""

from __future__ import annotations

import pytest
import torch

from cnnps.models.network import CNNPS
from cnnps.stages.train import Params
from cnnps.train import precision as tp


def _fake_steps(monkeypatch, rates: dict, losses: dict, available: bool = True) -> list:
    calls = []

    def fake(model, params, device, precision, maps, normals):
        calls.append(precision)
        return rates[precision], losses[precision]

    monkeypatch.setattr(tp, "time_steps", fake)
    monkeypatch.setattr("cnnps.models.precision_probe.bf16_available", lambda device: available)
    return calls


@pytest.mark.parametrize("rates, losses, pick, said", [
    ({"fp32": 6.0, "bf16": 8.7}, {"fp32": 0.50, "bf16": 0.51}, "bf16", "bf16 1.45x fp32: bf16"),  # AVX-512 BF16
    ({"fp32": 6.0, "bf16": 7.2}, {"fp32": 0.50, "bf16": 0.50}, "fp32", "under the 1.25x"),  # faster, not enough
    ({"fp32": 6.0, "bf16": 3.0}, {"fp32": 0.50, "bf16": 0.50}, "fp32", "bf16 0.50x fp32"),  # AVX-512 without BF16
    ({"fp32": 6.0, "bf16": 20.0}, {"fp32": 0.50, "bf16": 0.60}, "fp32", "first loss 20.0% off"),  # a broken kernel
])
def test_bf16_is_picked_only_when_clearly_faster_and_its_loss_agrees(monkeypatch, rates, losses, pick, said):
    calls = _fake_steps(monkeypatch, rates, losses)
    choice = tp.choose_train_precision(CNNPS(w=8), Params(), torch.device("cpu"), 16)
    assert choice.precision == pick and calls == ["fp32", "bf16"]
    assert said in choice.reason and "\n" not in choice.reason
    assert choice.rates == {"fp32": rates["fp32"], "bf16": rates["bf16"]}


def test_without_bf16_kernels_nothing_is_timed(monkeypatch):
    calls = _fake_steps(monkeypatch, {}, {}, available=False)
    choice = tp.choose_train_precision(CNNPS(w=8), Params(), torch.device("cpu"), 16)
    assert choice.precision == "fp32" and calls == [] and "bf16 skipped (no bf16 kernels" in choice.reason


def test_the_probe_steps_a_copy_and_leaves_the_model_and_the_rng_as_they_were(monkeypatch):
    """Both precisions really step (bf16 on torch's reference kernels where the CPU has no
    bf16 units): the run's weights and the global RNG are those before the probe, and bf16's
    first loss is within the rule's tolerance of fp32's on the same weights, batch and masks."""
    monkeypatch.setattr("cnnps.models.precision_probe.bf16_available", lambda device: True)
    torch.manual_seed(3)
    model = CNNPS(w=8).to(memory_format=torch.channels_last)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    rng = torch.random.get_rng_state()
    choice = tp.choose_train_precision(model, Params(data={"batch_size": 16}), torch.device("cpu"), 16)
    assert torch.equal(torch.random.get_rng_state(), rng)
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert choice.rates["fp32"] > 0 and choice.rates["bf16"] > 0
    gap = abs(choice.losses["bf16"] - choice.losses["fp32"]) / choice.losses["fp32"]
    assert gap < tp.LOSS_RTOL  # bf16 keeps 8 significant bits: the loss moves by a fraction of a percent
    assert choice.losses["fp32"] == pytest.approx(tp.time_steps(model, Params(), torch.device("cpu"), "fp32",
                                                                *_probe_batch(16))[1], rel=1e-6)


def _probe_batch(n: int):
    from cnnps.models.precision_probe import probe_maps

    maps, normals = probe_maps(n, w=8)
    return torch.from_numpy(maps).unsqueeze(1), torch.from_numpy(normals)
