"""``train.precision: auto``: the pick rule, a probe that leaves the run untouched, and the
choice a run records, and the cache that makes it once per machine."""

from __future__ import annotations

import pytest
import torch

from cnnps.models.network import CNNPS
from cnnps.train.params import Params
from cnnps.train import precision as tp


def _fake_steps(monkeypatch, rates: dict, losses: dict, available: bool = True) -> list:
    calls = []

    def fake(model, params, device, precision, maps, normals):
        calls.append(precision)
        return rates[precision], losses[precision], 1.0

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


# -- once per machine: resolve() and its cache ---------------------------------------------


@pytest.fixture
def simulated(monkeypatch, tmp_path):
    """A bf16-capable CPU whose bf16 steps run 1.5x fp32's; the cache in ``tmp_path``."""
    from tests.support.simulated_steps import SimulatedSteps

    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path))
    return SimulatedSteps({"fp32": 4.0, "bf16": 6.0}).install(monkeypatch)


def test_a_named_precision_is_taken_as_it_is(simulated):
    for name in ("fp32", "bf16"):
        choice = tp.resolve(CNNPS(w=8), Params(precision=name), torch.device("cpu"), 16)
        assert (choice.precision, choice.source, choice.reason) == (name, "params", f"train.precision: {name}")
    assert simulated.timed == []


def test_auto_probes_once_per_machine_and_step_then_takes_the_cached_answer(simulated, tmp_path, monkeypatch):
    model, cpu = CNNPS(w=8), torch.device("cpu")
    first = tp.resolve(model, Params(), cpu, 16)
    assert first.precision == "bf16" and first.source == "probe" and first.rates == {"fp32": 4.0, "bf16": 6.0}
    assert first.cpu_share == 1.0 and not first.under_load and len(simulated.timed) == 8
    simulated.rates = {"fp32": 6.0, "bf16": 4.0}  # the speeds cross: the answer for this machine stays
    again = tp.resolve(model, Params(), cpu, 16)
    assert again.precision == "bf16" and again.source == "cache" and len(simulated.timed) == 8
    assert again.record() == first.record() and again.age_seconds is not None
    other = tp.resolve(model, Params(), cpu, 32)  # another batch is another step: probed
    assert other.precision == "fp32" and other.source == "probe" and other.key != first.key
    assert "32 rows" in other.key and "| cpu |" in other.key and "CNNPS w8 c1" in other.key
    monkeypatch.setattr(tp, "now", lambda: first.probed_at + tp.CACHE_MAX_AGE_S + 1)  # 30 days on
    old = tp.resolve(model, Params(), cpu, 16)
    assert old.source == "probe" and old.precision == "fp32" and "too old" in old.reason
    (tmp_path / tp.CACHE_FILE).write_text("{not json")  # a damaged cache: probed, and written anew
    assert tp.resolve(model, Params(), cpu, 16).source == "probe"
    assert tp.resolve(model, Params(), cpu, 16).source == "cache"


def test_a_probe_under_load_says_so_and_its_answer_is_kept(simulated):
    """Threads that got a third of their CPUs' time: the reason says so, and the answer is
    cached all the same, so that the next run of these params steps alike."""
    simulated.cpu_share = 1 / 3
    choice = tp.resolve(CNNPS(w=8), Params(), torch.device("cpu"), 16)
    assert choice.under_load and choice.cpu_share == pytest.approx(1 / 3, abs=1e-3)
    assert "under load (its threads got 33% of their CPUs' time)" in choice.reason
    assert tp.resolve(CNNPS(w=8), Params(), torch.device("cpu"), 16).source == "cache"


def test_the_probe_steps_a_patch_heatmap_model_on_its_input_and_keys_its_cache_apart(monkeypatch):
    """A U-Net (no dropout) of patch 3: the probe's first loss is the heat-map loss of the
    model on the probe's maps in its 9 input channels; its cache key names head and patch,
    the paper's network's key is unchanged."""
    from cnnps.models.heads import head_loss
    from cnnps.models.model_options import build_model
    from cnnps.models.precision_probe import probe_maps

    monkeypatch.setattr("cnnps.models.precision_probe.bf16_available", lambda device: True)
    torch.manual_seed(2)
    net = build_model(arch="unet", head="heatmap", patch=3, w=8)
    choice = tp.choose_train_precision(net, Params(), torch.device("cpu"), 4)
    maps, normals = probe_maps(4, w=8, channels=9)
    with torch.no_grad():
        want = float(head_loss("heatmap", net(torch.from_numpy(maps)), torch.from_numpy(normals)))
    assert choice.losses["fp32"] == pytest.approx(want, rel=1e-5)
    key = tp.cache_key(net, Params(), torch.device("cpu"), 4)
    assert "HeatmapUNet w8 c1 heatmap b3 |" in key
    assert "CNNPS w8 c1 |" in tp.cache_key(CNNPS(w=8), Params(), torch.device("cpu"), 4)
