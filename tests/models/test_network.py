from __future__ import annotations

import numpy as np
import pytest
import torch

from cnnps.models.network import (
    ARCH_VERSION,
    CNNPS,
    FoldedCNNPS,
    count_parameters,
    fold_for_inference,
)


def _expected_params(w: int) -> int:
    conv = lambda cin, cout, k: cin * cout * k * k + cout  # noqa: E731
    convs = (
        conv(1, 16, 3) + conv(16, 16, 3) + conv(32, 16, 3)  # stem + dense block 1
        + conv(48, 48, 1)  # transition
        + conv(48, 16, 3) + conv(64, 16, 3)  # dense block 2
        + conv(80, 80, 1)
    )
    return convs + (80 * (w // 2) ** 2 * 128 + 128) + (128 * 3 + 3)


def _maps(n: int, w: int = 32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 1, w, w, generator=g) * (torch.rand(n, 1, w, w, generator=g) < 0.1)
    return x / x.amax(dim=(2, 3), keepdim=True).clamp_min(1e-6)


def test_parameter_count_matches_paper():
    model = CNNPS()
    n = count_parameters(model)
    assert n == _expected_params(32) == 2_654_051  # the paper's "about 2.65 M"
    assert model.fc1.in_features == 80 * 16 * 16 == 20480


# The state-dict layout (w = 32) each ARCH_VERSION stands for. Checkpoints are refused
# by version, so renaming or reshaping a layer without bumping ARCH_VERSION (old files
# would then load into the wrong layers, or fail obscurely) fails here.
LAYOUTS = {
    1: [("conv0.weight", (16, 1, 3, 3)), ("conv0.bias", (16,)),
        ("block1_conv1.weight", (16, 16, 3, 3)), ("block1_conv1.bias", (16,)),
        ("block1_conv2.weight", (16, 32, 3, 3)), ("block1_conv2.bias", (16,)),
        ("trans_conv.weight", (48, 48, 1, 1)), ("trans_conv.bias", (48,)),
        ("block2_conv1.weight", (16, 48, 3, 3)), ("block2_conv1.bias", (16,)),
        ("block2_conv2.weight", (16, 64, 3, 3)), ("block2_conv2.bias", (16,)),
        ("final_conv.weight", (80, 80, 1, 1)), ("final_conv.bias", (80,)),
        ("fc1.weight", (128, 20480)), ("fc1.bias", (128,)),
        ("fc2.weight", (3, 128)), ("fc2.bias", (3,))],
}


def test_arch_version_pins_the_layout():
    layout = [(k, tuple(v.shape)) for k, v in CNNPS(w=32).state_dict().items()]
    assert layout == LAYOUTS.get(ARCH_VERSION), "layout changed: bump ARCH_VERSION and add it to LAYOUTS"


@pytest.mark.parametrize("w", [8, 16, 32, 48])
def test_shapes_and_unit_norm(w):
    torch.manual_seed(w)
    model = CNNPS(w=w).eval()
    assert count_parameters(model) == _expected_params(w)
    with torch.no_grad():
        out = model(_maps(7, w))
    assert out.shape == (7, 3) and out.dtype == torch.float32
    assert torch.allclose(out.norm(dim=1), torch.ones(7), atol=1e-6)


@pytest.mark.parametrize("w", [0, 7, 33])
def test_bad_width(w):
    with pytest.raises(ValueError, match="even"):
        CNNPS(w=w)


def test_dropout_only_in_training():
    torch.manual_seed(0)
    model = CNNPS()
    x = _maps(16)
    model.train()
    with torch.no_grad():
        a, b = model(x), model(x)
    assert (a - b).abs().max() > 1e-4  # dropout active
    model.eval()
    with torch.no_grad():
        c, d = model(x), model(x)
    assert torch.equal(c, d)


def test_folded_model_matches_original():
    torch.manual_seed(1)
    model = CNNPS().eval()
    # give the biases non-zero values so the bias folding is exercised too
    with torch.no_grad():
        for mod in model.modules():
            if isinstance(mod, (torch.nn.Conv2d, torch.nn.Linear)):
                mod.bias.normal_(0.0, 0.05)
    folded = fold_for_inference(model)
    assert isinstance(folded, FoldedCNNPS) and not folded.training
    x = _maps(64, seed=3)
    with torch.no_grad():
        ref, out = model(x), folded(x)
        pre_ref = model.fc1(model.features(x).flatten(1))
    # compare before the final normalisation too (the folded fc1 absorbs final_conv)
    with torch.no_grad():
        h = folded.conv0(x).relu()
        h = torch.cat([h, folded.block1_conv1(h).relu()], 1)
        h = torch.cat([h, folded.block1_conv2(h).relu()], 1)
        h = folded.trans_conv(torch.nn.functional.avg_pool2d(h, 2)).relu()
        h = torch.cat([h, folded.block2_conv1(h).relu()], 1)
        h = torch.cat([h, folded.block2_conv2(h).relu()], 1)
        pre_out = folded.fc1(h.flatten(1))
    scale = pre_ref.abs().max()
    assert (pre_ref - pre_out).abs().max() < 1e-5 * scale
    assert (ref - out).abs().max() < 1e-5
    # the original is untouched
    assert model.final_conv.weight.shape == (80, 80, 1, 1)


def test_inference_copies_draw_nothing_from_the_global_rng():
    # the train stage validates with these copies between training steps: drawing from
    # the global RNG there would shift the dropout masks of every later step
    import cnnps.models.network as network

    model = CNNPS(w=16)
    state = torch.get_rng_state()
    fold_for_inference(model)
    network.fast_cpu_model(model)
    assert torch.equal(torch.get_rng_state(), state)


def test_fold_rejects_other_modules():
    with pytest.raises(TypeError):
        fold_for_inference(torch.nn.Linear(2, 3))


@pytest.mark.parametrize("use_mkldnn", [True, False])
@pytest.mark.parametrize("w", [16, 32])
def test_fast_cpu_model_matches_original(monkeypatch, use_mkldnn, w):
    import cnnps.models.network as network

    if not use_mkldnn:
        monkeypatch.setattr(network, "mkldnn_pointwise_available", lambda: False)
    elif not network.mkldnn_pointwise_available():
        pytest.skip("torch without oneDNN pointwise kernels")
    torch.manual_seed(2)
    model = CNNPS(w=w).eval()
    with torch.no_grad():
        for mod in model.modules():
            if isinstance(mod, (torch.nn.Conv2d, torch.nn.Linear)):
                mod.bias.normal_(0.0, 0.05)
    fast = network.fast_cpu_model(model)
    x = _maps(40, w, seed=4)
    with torch.inference_mode():
        ref = model(x)
        out_nchw = fast(x)
        out_cl = fast(x.contiguous(memory_format=torch.channels_last))
    assert out_nchw.shape == (40, 3)
    # measured max 1e-6 (float32 rounding of a different summation order)
    assert (ref - out_nchw).abs().max() < 1e-5
    assert (ref - out_cl).abs().max() < 1e-5
    # it is a copy: changing the model afterwards does not change it
    with torch.no_grad():
        model.fc2.bias.add_(1.0)
        assert (fast(x) - out_nchw).abs().max() < 1e-6


@pytest.mark.parametrize("bits,rate", [(32, 0.2), (16, 13107 / 65536)])
def test_counter_dropout_masks_follow_their_key_and_rate(bits, rate):
    """Dropout from the counter-based stream: the drop rate and scale of nn.Dropout (the
    rate p rounded to 2^-bits: 0.2 is 13107 / 65536 with 16 bits), the same mask for the
    same key (what makes a resumed run exact), another for another key, and laid out in
    the tensor's memory order (channels_last)."""
    from cnnps.models.network import counter_dropout

    x = torch.ones(64, 16, 32, 32).contiguous(memory_format=torch.channels_last)
    y = counter_dropout(x, 0.2, (0, 0, 7, 1), bits=bits)
    kept = y != 0
    n = kept.numel()
    assert abs(1 - kept.float().mean().item() - 0.2) < 7 * (0.2 * 0.8 / n) ** 0.5  # seeded: no flake
    assert torch.all(y[kept] == torch.tensor(1 / (1 - rate), dtype=torch.float32))  # scale 1 / (1 - rate)
    assert abs(rate - 0.2) <= 2.0 ** -(bits + 1)
    assert y.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(y, counter_dropout(x, 0.2, (0, 0, 7, 1), bits=bits))
    assert not torch.equal(kept, counter_dropout(x, 0.2, (0, 0, 8, 1), bits=bits) != 0)
    assert not torch.equal(kept, counter_dropout(x, 0.2, (0, 0, 7, 2), bits=bits) != 0)
    # the bits are laid out in memory order: a contiguous (NCHW) copy of the input draws the
    # same bits in its own order, so as many elements are kept, at other places
    plain = counter_dropout(x.contiguous(), 0.2, (0, 0, 7, 1), bits=bits)
    assert plain.is_contiguous() and (plain != 0).float().mean().item() == kept.float().mean().item()


def test_16_bit_counter_masks_are_the_32_bit_streams_halves():
    """Both widths read the same SFC64 stream: the 16-bit masks of n elements are drawn
    from the first n / 4 64-bit outputs, a prefix of what 32 bits read (independently
    computed here with NumPy), and they differ from the 32-bit masks."""
    import numpy as np

    from cnnps.models.train_layers import counter_keep

    key, n = (2, 0, 5, 3), 16 * 40  # one block of 16 rows, 40 elements a row
    keep16, scale16 = counter_keep((16, 40), 0.2, key, bits=16)
    keep32, _ = counter_keep((16, 40), 0.2, key, bits=32)
    raw = np.random.SFC64(list(key) + [0]).random_raw(n // 2)
    expect16 = raw[:n // 4].view(np.int16) >= -(2**15) + 13107
    expect32 = raw.view(np.int32) >= -(2**31) + round(0.2 * 2**32)
    assert np.array_equal(keep16.numpy(), expect16) and np.array_equal(keep32.numpy(), expect32)
    assert not torch.equal(keep16, keep32)
    assert scale16 == 65536 / (65536 - 13107)
    with pytest.raises(ValueError, match="bits"):
        counter_keep((16, 40), 0.2, key, bits=8)


def test_counter_masks_apply_only_while_training_on_a_cpu_with_a_key():
    from cnnps.models.network import CNNPS

    torch.manual_seed(0)
    model = CNNPS(w=8)
    x = torch.rand(4, 1, 8, 8)
    model.train()
    model.set_mask_key((1, 0, 5))
    a, b = model(x), model(x)
    assert torch.equal(a, b)  # the same key: the same masks, whatever torch's generator does
    model.set_mask_key((1, 0, 6))
    assert not torch.equal(a, model(x))
    model.eval()
    e = model(x)
    model.set_mask_key(None)
    assert torch.equal(e, model(x))  # no dropout at all in eval mode


def test_bf16_fast_model_stays_within_the_probe_tolerance():
    """The bf16 CPU path (FastCNNPS with bf16 weights, no autocast) against the fp32 one on
    the probe's maps with the shipped weights: bf16 keeps 8 significant bits, so each
    layer's output is off by ~0.4 % at most and the normal by a fraction of a degree; the
    probe accepts it when its mean error is within TOLERANCE_DEG of fp32's. Runs on
    oneDNN's bf16 kernels where the CPU has them, on torch's reference kernels elsewhere."""
    from cnnps.models import network
    from cnnps.models import precision_probe as pp
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor
    from cnnps.models.shipped import shipped_model_path
    from cnnps.ps.metrics import angular_error_deg

    model = load_checkpoint(shipped_model_path(), "cpu")[0]
    maps, truth = pp.probe_maps(96)
    fp32 = MapPredictor(model, device="cpu", precision="fp32")(maps)
    bf16_predictor = MapPredictor(model, device="cpu", precision="bf16")
    assert isinstance(bf16_predictor.net, network.FastCNNPS) and not bf16_predictor.autocast
    assert bf16_predictor.net.fc1_z0.dtype == torch.bfloat16 and bf16_predictor.net.fc2_wt.dtype == torch.float32
    bf16 = bf16_predictor(maps)
    assert bf16.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(bf16, axis=1), 1.0, atol=1e-5)
    deviation = angular_error_deg(bf16, fp32)
    assert 0 < deviation.mean() < 0.2 and deviation.max() < 1.0  # measured 0.06 / 0.18 on 128 maps
    change = angular_error_deg(bf16, truth).mean() - angular_error_deg(fp32, truth).mean()
    assert abs(change) < pp.TOLERANCE_DEG


def test_fast_model_refuses_other_dtypes():
    from cnnps.models import network

    with pytest.raises(ValueError, match="float32 or bfloat16"):
        network.FastCNNPS(CNNPS(w=16), dtype=torch.float16)
