"""The spatial-context first layer (cnnps.models.patch) and the networks built on it."""

import numpy as np
import pytest
import torch

from cnnps.models.map_inputs import patch_maps, turn_patch_grids
from cnnps.models.model_options import build_model
from cnnps.models.network import CNNPS, FastCNNPS, fold_for_inference
from cnnps.models.patch import PatchConv
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.rotation import rotate_z


def _conv_same_3x3(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(C, h, w) * (O, C, 3, 3) -> (O, h, w): zero-padded cross-correlation, by loops."""
    C, h, w = x.shape
    pad = np.zeros((C, h + 2, w + 2))
    pad[:, 1:-1, 1:-1] = x
    out = np.zeros((k.shape[0], h, w))
    for dr in range(3):
        for dc in range(3):
            out += np.einsum("oc,chw->ohw", k[:, :, dr, dc], pad[:, dr:dr + h, dc:dc + w])
    return out


@pytest.mark.parametrize("patch, channels", [(3, 1), (5, 1), (3, 4)])
def test_separable_layer_equals_the_explicit_reference(patch, channels):
    torch.manual_seed(0)
    layer = PatchConv(channels, 6, patch, mid_channels=5)
    with torch.no_grad():
        layer.map_conv.bias.normal_()
        layer.patch_bias.normal_()
    x = torch.rand(2, channels * patch * patch, 7, 7)
    got = layer(x).detach().numpy()
    U = layer.map_conv.weight.detach().double().numpy()
    V = layer.patch_weight.detach().double().numpy()
    ub, vb = layer.map_conv.bias.detach().double().numpy(), layer.patch_bias.detach().double().numpy()
    xs = x.double().numpy()
    for b in range(2):
        want = np.zeros((6, 7, 7)) + vb[:, None, None]
        for i in range(patch):
            for j in range(patch):
                ch = slice((i * patch + j) * channels, (i * patch + j + 1) * channels)  # the documented layout
                y = _conv_same_3x3(xs[b, ch], U) + ub[:, None, None]
                want += np.einsum("om,mhw->ohw", V[:, :, i, j], y)
        np.testing.assert_allclose(got[b], want, rtol=1e-5, atol=1e-5)
    folded = layer.folded()
    assert folded.in_channels == channels * patch * patch and folded.kernel_size == (3, 3)
    np.testing.assert_allclose(folded(x).detach().numpy(), got, rtol=1e-5, atol=1e-5)


def test_patch_one_is_the_plain_network_bit_for_bit():
    torch.manual_seed(5)
    plain = CNNPS()
    torch.manual_seed(5)
    built = build_model(arch="cnnps", head="regression", patch=1)
    assert type(built.conv0) is torch.nn.Conv2d
    assert list(plain.state_dict()) == list(built.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(plain.state_dict().values(), built.state_dict().values()))
    x = torch.rand(4, 1, 32, 32)
    assert torch.equal(plain.eval()(x), built.eval()(x))


@pytest.mark.parametrize("head", ["regression", "heatmap"])
def test_patch_networks_shapes_and_inference_forms(head):
    torch.manual_seed(1)
    net = build_model(head=head, patch=3, w=16).eval()
    x = torch.rand(5, 9, 16, 16)
    with torch.no_grad():
        y = net(x)
        assert y.shape == ((5, 3) if head == "regression" else (5, 16, 16))
        torch.testing.assert_close(fold_for_inference(net)(x), y, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(FastCNNPS(net)(x), y, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="patch must be one of 1, 3, 5, got 2"):
        build_model(patch=2)


@pytest.mark.parametrize("patch", [1, 3])
def test_unet_shapes_and_positive_homogeneity(patch):
    torch.manual_seed(2)
    net = build_model(arch="unet", head="heatmap", patch=patch, w=16).eval()
    x = torch.rand(3, patch * patch, 16, 16)
    with torch.no_grad():
        y = net(x)
        assert y.shape == (3, 16, 16) and y.dtype == torch.float32
        scale = float(y.abs().max())  # float32 sums of mixed signs: compare against the map's size
        torch.testing.assert_close(net(2.5 * x), 2.5 * y, rtol=0, atol=1e-5 * scale)  # no biases, ReLUs
    assert not any("bias" in name for name, _ in net.named_parameters())
    with pytest.raises(ValueError, match="arch 'unet' has the heatmap head only"):
        build_model(arch="unet", head="regression")


def test_patch_grid_turns_with_the_lights_as_the_scene_would():
    # a quarter turn of the scene about z (counter-clockwise seen from the camera) moves
    # the neighbour at offset (dx, dy) (x right, y up) to (-dy, dx); grid row i has dy = c - i
    rng = np.random.default_rng(0)
    b, w, m, n = 3, 8, 30, 2
    c = b // 2
    lights = rng.normal(size=(m, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.5
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    I = rng.random((n, b * b, m)).astype(np.float32)
    angles = np.array([0.0, np.pi / 2, np.pi, 3 * np.pi / 2])
    rotated = np.stack([rotate_z(lights, a) for a in angles])
    got = patch_maps(I, rotated, angles, w)
    assert got.shape == (4, n, b * b, w, w)
    for k, a in enumerate(angles):
        for i in range(b):
            for j in range(b):
                dx, dy = j - c, c - i
                for _ in range(k):
                    dx, dy = -dy, dx
                i2, j2 = c - dy, dx + c
                want = observation_maps(I[:, i * b + j], rotated[k], w=w)
                np.testing.assert_array_equal(got[k, :, i2 * b + j2], want)
    with pytest.raises(ValueError, match="quarter turns only"):
        turn_patch_grids(got.reshape(4, n, b, b, w, w)[:1], np.array([0.3]))
