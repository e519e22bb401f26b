"""The fused CPU training layers (cnnps.models.train_layers) against torch's layers and a
float64 reference with the same dropout masks."""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from cnnps.models import train_layers
from cnnps.models.network import CNNPS, counter_dropout

KEY = (3, 0, 11)


def _batch(n: int, w: int = 32, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 1, w, w, generator=g) * (torch.rand(n, 1, w, w, generator=g) < 0.3)
    normals = F.normalize(torch.randn(n, 3, generator=g), dim=1)
    return x.contiguous(memory_format=torch.channels_last), normals


def _grads(model, x, normals):
    model.zero_grad(set_to_none=True)
    out = model(x)
    F.mse_loss(out, normals).backward()
    return out.detach().double(), {k: p.grad.detach().double().clone() for k, p in model.named_parameters()}


def _model(w: int = 32, seed: int = 0) -> CNNPS:
    torch.manual_seed(seed)
    model = CNNPS(w=w).to(memory_format=torch.channels_last).train()
    with torch.no_grad():  # non-zero biases, so their gradients and the ReLU boundaries are exercised
        for name, p in model.named_parameters():
            if name.endswith("bias"):
                p.copy_(0.05 * torch.randn(p.shape))
    model.set_mask_key(KEY)
    return model


@pytest.mark.parametrize("w,bits", [(16, 32), (32, 32), (32, 16)])
def test_fused_gradients_match_a_float64_reference(w, bits):
    """Same masks, same loss: every parameter's gradient within float32 rounding of the
    float64 reference (torch's layers), as torch's own float32 layers are; with 32- and
    16-bit counter masks."""
    model = _model(w)
    model.mask_bits = bits
    x, normals = _batch(24, w)
    assert model._fused_training(x)
    out, grads = _grads(model, x, normals)
    model.fused_cpu_layers = False
    assert not model._fused_training(x)
    out_ref32, grads_ref32 = _grads(model, x, normals)
    ref = copy.deepcopy(model).double()
    ref.set_mask_key(KEY)
    out64, grads64 = _grads(ref, x.double(), normals.double())
    # measured: outputs 3e-7, gradients <= 6e-6 relative (torch's float32 layers alike)
    assert (out - out64).abs().max() < 1e-5
    for name, g64 in grads64.items():
        err = ((grads[name] - g64).norm() / g64.norm()).item()
        err32 = ((grads_ref32[name] - g64).norm() / g64.norm()).item()
        assert err < 1e-4, (name, err, err32)
    # and the masks are the ones torch's layers drew: another key gives other gradients
    model.fused_cpu_layers = True
    model.set_mask_key((3, 0, 12))
    _, other = _grads(model, x, normals)
    assert ((other["conv0.weight"] - grads["conv0.weight"]).norm() / grads["conv0.weight"].norm()) > 1e-2


def test_fused_layers_only_where_they_apply():
    model = _model(16)
    x, _ = _batch(4, 16)
    assert model._fused_training(x)
    assert not model._fused_training(x.double())
    model.set_mask_key(None)  # torch's masks
    assert not model._fused_training(x)
    model.set_mask_key(KEY)
    model.eval()
    assert not model._fused_training(x)
    model.train()
    with torch.autocast("cpu", dtype=torch.bfloat16):  # bf16 steps run the fused layers in bf16
        assert model._fused_training(x)
    with torch.autocast("cpu", dtype=torch.float16):
        assert not model._fused_training(x)


@pytest.mark.parametrize("w", [16, 32])
def test_fused_bf16_gradients_are_as_close_to_float64_as_torchs_bf16_autocast(w):
    """A bf16 step (bf16 autocast) runs the fused layers in bf16. bf16 keeps 8 significant
    bits, so its gradients are off the float64 reference by several percent, however the
    layers are written: measured against torch's own layers under bf16 autocast with the
    same masks, the fused ones are about as close (mean over the parameters 0.7-1.5x
    autocast's error, 2.2x at worst for one parameter), and every gradient points the
    float64 way (a wrong mask or a dropped scale gives errors near 1)."""
    model = _model(w)
    x, normals = _batch(24, w)
    ref = copy.deepcopy(model).double()
    ref.set_mask_key(KEY)
    _, grads64 = _grads(ref, x.double(), normals.double())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert model._fused_training(x)
        out, fused = _grads(model, x, normals)
        model.fused_cpu_layers = False
        _, autocast = _grads(model, x, normals)
    assert out.dtype == torch.float64 and torch.allclose(out.norm(dim=1), torch.ones(24, dtype=torch.float64))
    err = {k: ((fused[k] - g).norm() / g.norm()).item() for k, g in grads64.items()}
    err_autocast = {k: ((autocast[k] - g).norm() / g.norm()).item() for k, g in grads64.items()}
    assert max(err.values()) < 0.3, err
    assert sum(err.values()) < 2.5 * sum(err_autocast.values()), (err, err_autocast)
    assert all(p.grad.dtype == torch.float32 for p in model.parameters())  # Adam steps the float32 weights


@pytest.mark.parametrize("bits", [32, 16])
def test_keep_mask_is_counter_dropouts_mask(bits):
    x = torch.ones(8, 16, 8, 8).contiguous(memory_format=torch.channels_last)
    dropped = counter_dropout(x, 0.2, KEY + (1,), bits=bits)
    keep, scale = train_layers.keep_mask((8, 8, 8, 16), 0.2, KEY + (1,), bits=bits)
    assert keep.dtype == torch.float32 and set(keep.unique().tolist()) == {0.0, 1.0}
    assert torch.equal(keep.permute(0, 3, 1, 2) * scale, dropped)


@pytest.mark.parametrize("pointwise", [True, False])
def test_layers_against_torch(monkeypatch, pointwise):
    """Each fused piece against the torch expression it replaces (oneDNN's fused kernel
    and the plain fallback)."""
    if not pointwise:
        monkeypatch.setattr(train_layers, "mkldnn_pointwise_available", lambda: False)
    torch.manual_seed(1)
    cl = torch.channels_last
    x = torch.rand(6, 1, 16, 16)
    w0, b0 = torch.randn(16, 1, 3, 3), torch.randn(16)
    ref = F.relu(F.conv2d(x, w0, b0, padding=1))
    out = train_layers.first_conv_relu(x.contiguous(memory_format=cl), w0, b0)
    assert out.is_contiguous(memory_format=cl) and torch.allclose(out, ref, atol=1e-5)

    r = torch.randn(6, 32, 16, 16).contiguous(memory_format=cl).requires_grad_()
    w, b = torch.randn(16, 32, 3, 3).requires_grad_(), torch.randn(16).requires_grad_()
    keep, scale = train_layers.keep_mask((6, 16, 16, 16), 0.2, KEY)
    y = train_layers.ConvReluDrop.apply(r, w, b, keep, scale)
    y_ref = F.relu(F.conv2d(r, w, b, padding=1) * keep.permute(0, 3, 1, 2) * scale)
    g = torch.randn_like(y_ref)
    assert torch.allclose(y, y_ref, atol=1e-4)
    d = torch.autograd.grad(y, (r, w, b), g)
    d_ref = torch.autograd.grad(y_ref, (r, w, b), g)
    for a, c in zip(d, d_ref):
        assert torch.allclose(a, c, rtol=1e-4, atol=1e-3)

    t = torch.randn(6, 48, 16, 16).contiguous(memory_format=cl).requires_grad_()
    wt, bt = torch.randn(48, 48, 1, 1).requires_grad_(), torch.randn(48).requires_grad_()
    keep, scale = train_layers.keep_mask((6, 16, 16, 48), 0.2, KEY)
    y = train_layers.TransitionDropPoolRelu.apply(t, wt, bt, keep, scale)
    y_ref = F.relu(F.avg_pool2d(F.conv2d(t, wt, bt) * keep.permute(0, 3, 1, 2) * scale, 2))
    g = torch.randn_like(y_ref)
    assert torch.allclose(y, y_ref, atol=1e-4)
    for a, c in zip(torch.autograd.grad(y, (t, wt, bt), g), torch.autograd.grad(y_ref, (t, wt, bt), g)):
        assert torch.allclose(a, c, rtol=1e-4, atol=1e-3)

    z = torch.randn(6, 80, 8, 8).contiguous(memory_format=cl)
    wf, bf = torch.randn(80, 80, 1, 1), torch.randn(80)
    assert torch.allclose(train_layers.mix_channels_flat(z, wf, bf), F.conv2d(z, wf, bf).flatten(1), atol=1e-4)


def test_training_steps_agree_with_torchs_layers():
    """Five Adam steps with the fused layers and with torch's: the same weights up to
    float rounding (the masks and the data are the same)."""
    from cnnps.stages.train import Params
    from cnnps.train.optimiser import make_model, train_step

    x, normals = _batch(32, 16, seed=4)
    runs = {}
    for layers in ("fused", "reference"):
        model, opt = make_model(16, Params(cpu={"layers": layers}), torch.device("cpu"))
        start = {k: v.detach().clone() for k, v in model.state_dict().items()}
        model.train()
        for step in range(5):
            model.set_mask_key((0, 0, step))
            s = 16 * (step % 2)
            train_step(model, opt, x[s:s + 16], normals[s:s + 16], torch.device("cpu"), "fp32", True)
        runs[layers] = {k: v.detach().clone() for k, v in model.state_dict().items()}
    for name, ref in runs["reference"].items():
        # Adam divides by the gradient's running size, so a weight whose gradient is ~0 may
        # take a step of either sign on a rounding difference: compare the updates as a whole
        update = ref - start[name]
        rel = ((runs["fused"][name] - ref).norm() / update.norm()).item()
        assert rel < 1e-3, (name, rel)  # measured <= 4e-5 (fc1), 2e-6 elsewhere
