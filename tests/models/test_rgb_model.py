"""The colour variant of CNN-PS (4 input channels: grey, R, G, B): the network, its
checkpoints, widening a grey model, and inference building grey and colour maps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.models.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from cnnps.models.inference import MapPredictor, predict_normals, rotated_normals
from cnnps.models.network import (
    CNNPS,
    RGB_CHANNELS,
    count_parameters,
    fast_cpu_model,
    fold_for_inference,
    widen_input,
    widen_state,
)
from cnnps.models.shipped import weights_path
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.rotation import rotate_z, rotation_angles
from cnnps.synth.pixelwise import observation_maps_rgb_torch


def _grey_maps(n: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 1, w, w, generator=g) * (torch.rand(n, 1, w, w, generator=g) < 0.15)
    return x / x.amax(dim=(2, 3), keepdim=True).clamp_min(1e-6)


def _with_colour(grey: torch.Tensor, seed: int = 1) -> torch.Tensor:
    """(n, 4, w, w): the grey maps, then three other maps (any content)."""
    g = torch.Generator().manual_seed(seed)
    return torch.cat([grey, torch.rand(grey.shape[0], 3, *grey.shape[2:], generator=g)], 1)


@pytest.fixture(scope="module")
def shipped():
    model, _config, _meta = load_checkpoint(weights_path())
    return model


def test_the_first_convolution_takes_the_channels():
    torch.manual_seed(0)
    grey, rgb = CNNPS(w=16), CNNPS(w=16, in_channels=RGB_CHANNELS)
    assert (grey.in_channels, rgb.in_channels) == (1, 4) and rgb.conv0.weight.shape == (16, 4, 3, 3)
    assert count_parameters(rgb) - count_parameters(grey) == 3 * 16 * 9  # three more input planes of conv0
    with torch.no_grad():
        out = rgb.eval()(_with_colour(_grey_maps(5, 16)))
    assert out.shape == (5, 3) and torch.allclose(out.norm(dim=1), torch.ones(5), atol=1e-6)
    with pytest.raises(ValueError, match="in_channels"):
        CNNPS(in_channels=0)


def test_checkpoints_keep_the_channels_and_old_files_load_as_grey(tmp_path, shipped):
    torch.manual_seed(1)
    model = CNNPS(w=16, in_channels=4).eval()
    path = save_checkpoint(tmp_path / "rgb.pt", model, {"note": "x"})
    loaded, config, _ = load_checkpoint(path)
    assert config["in_channels"] == 4 and loaded.in_channels == 4
    x = _with_colour(_grey_maps(6, 16))
    with torch.no_grad():
        assert torch.equal(loaded(x), model(x))
    # a file written before colour models has no in_channels: it loads as a grey network
    payload = read_checkpoint(weights_path())
    payload["config"].pop("in_channels", None)
    torch.save(payload, tmp_path / "old.pt")
    old, config, _ = load_checkpoint(tmp_path / "old.pt")
    assert "in_channels" not in config and old.in_channels == 1 and old.conv0.weight.shape == (16, 1, 3, 3)
    assert shipped.in_channels == 1 and shipped.conv0.weight.shape == (16, 1, 3, 3)
    with pytest.raises(ValueError, match="disagrees"):
        save_checkpoint(tmp_path / "bad.pt", model, {"in_channels": 1})


def test_widening_keeps_the_grey_outputs_exactly(shipped):
    """conv0's colour filters at 0: on maps whose channel 0 is the grey map the widened
    network gives the grey network's normals, whatever channels 1-3 hold. Through the
    inference copies (what cnnps score runs) bit for bit."""
    rng_state = torch.get_rng_state()
    wide = widen_input(shipped)
    assert torch.equal(torch.get_rng_state(), rng_state)  # built without drawing
    assert wide.in_channels == 4 and torch.equal(wide.conv0.weight[:, :1], shipped.conv0.weight)
    assert not wide.conv0.weight[:, 1:].any()
    for k, v in shipped.state_dict().items():
        if k != "conv0.weight":
            assert torch.equal(wide.state_dict()[k], v), k
    grey = _grey_maps(300, 32)
    x = _with_colour(grey)
    with torch.no_grad():
        torch.testing.assert_close(wide(x), shipped(grey), rtol=0, atol=1e-6)
        cl = torch.channels_last
        for make in (fold_for_inference, fast_cpu_model):
            a, b = make(shipped)(grey.contiguous(memory_format=cl)), make(wide)(x.contiguous(memory_format=cl))
            assert torch.equal(a, b), make.__name__
    a = MapPredictor(shipped, device="cpu")(grey[:, 0].numpy())
    b = MapPredictor(wide, device="cpu")(x.numpy())
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="1-channel"):
        widen_state(wide.state_dict())


def test_inference_copies_of_a_colour_model_match_it():
    """Folded and fused copies of a colour model whose colour filters are not 0."""
    torch.manual_seed(2)
    model = CNNPS(w=16, in_channels=4).eval()
    x = _with_colour(_grey_maps(64, 16)).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        ref = model(x)
        for make in (fold_for_inference, fast_cpu_model):
            net = make(model)
            assert net.in_channels == 4 and not net.grey_only
            torch.testing.assert_close(net(x), ref, rtol=1e-5, atol=1e-5)
    pred = MapPredictor(model, device="cpu", batch_size=16)
    torch.testing.assert_close(torch.from_numpy(pred(x.numpy())), ref, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match=r"\(B, 4, 16, 16\)"):
        pred(x[:, 0].numpy())


def test_a_colour_batch_takes_the_eager_layers_and_trains():
    """The fused CPU training layers are for one channel: a (B, 4, w, w) batch runs the
    eager ones, with the counter masks, and gets gradients on every conv0 plane."""
    torch.manual_seed(3)
    model = CNNPS(w=16, in_channels=4).train().to(memory_format=torch.channels_last)
    model.set_mask_key((0, 0, 1))
    x = _with_colour(_grey_maps(32, 16)).contiguous(memory_format=torch.channels_last)
    assert not model._fused_training(x)
    grey = CNNPS(w=16).train()
    grey.set_mask_key((0, 0, 1))
    assert grey._fused_training(x[:, :1].contiguous(memory_format=torch.channels_last))  # the same pass, grey
    loss = model(x).sum()
    loss.backward()
    assert model.conv0.weight.grad[:, 1:].abs().sum() > 0


class _Recorder:
    """A 4-channel map predictor that keeps its maps and answers +z."""

    w, in_channels = 32, 4

    def __init__(self):
        self.maps = []

    def __call__(self, maps, progress=None):
        self.maps.append(np.array(maps))
        return np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (len(maps), 1))


def _scene(P=20, m=40, seed=0):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.3
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    colour = (rng.uniform(0, 1, (P, m, 3)) * rng.uniform(0.2, 1, (P, 1, 3))).astype(np.float32)
    return colour, L, rng.random((P, m)) < 0.8


@pytest.mark.parametrize("K", [1, 4])
def test_rotated_normals_build_grey_and_colour_maps_per_rotation(K):
    """Per rotation, channel 0 is observation_maps of the grey values and channels 1-3 the
    training rule's colour maps (observation_maps_rgb_torch) of the colour values, with the
    same missing observations."""
    colour, L, present = _scene()
    grey = colour.mean(axis=2, dtype=np.float32) * np.float32(1.01)  # any grey: taken as given
    rec = _Recorder()
    rotated_normals(rec, grey, L, K, light_mask=present, colour=colour, pixel_chunk=40)
    maps = np.concatenate([m.reshape(K, -1, 4, 32, 32) for m in rec.maps], axis=1)  # (K, P, 4, w, w)
    assert sum(len(m) for m in rec.maps) == K * 20 and max(len(m) for m in rec.maps) <= 40 // 4
    for k, a in enumerate(rotation_angles(K)):
        Lk = rotate_z(L, a)
        np.testing.assert_array_equal(maps[k, :, 0], observation_maps(grey, Lk, 32, light_mask=present))
        ref = observation_maps_rgb_torch(torch.from_numpy(colour), torch.from_numpy(Lk), 32,
                                         light_mask=torch.from_numpy(present)).numpy()
        np.testing.assert_allclose(maps[k, :, 1:], ref, rtol=1e-6, atol=1e-7)
    # (P, m, 3) values alone: the grey map is their mean's; grey values alone: R = G = B
    rec3, rec1 = _Recorder(), _Recorder()
    rotated_normals(rec3, colour, L, 1, light_mask=present)
    np.testing.assert_array_equal(rec3.maps[0][:, 0], observation_maps(colour.mean(axis=2), L, 32, light_mask=present))
    rotated_normals(rec1, grey, L, 1)
    for c in range(1, 4):
        np.testing.assert_allclose(rec1.maps[0][:, c], rec1.maps[0][:, 0], rtol=1e-6, atol=1e-7)


def test_a_colour_model_refuses_what_it_cannot_be_fed():
    colour, L, _ = _scene(P=6, m=12)
    rec = _Recorder()
    views = np.tile([[0.0, 0.0, 1.0]], (6, 1))
    with pytest.raises(ConfigError, match="orthographic"):
        rotated_normals(rec, colour, L, 1, views=views)
    with pytest.raises(ConfigError, match="point lights"):
        rotated_normals(rec, colour, np.broadcast_to(L, (6, 12, 3)), 1)
    torch.manual_seed(4)
    model = CNNPS(w=32, in_channels=4)
    with pytest.raises(ConfigError, match="--sparse-fill off"):  # 12 images: the fill would apply
        predict_normals(model, colour, L, rotations=1, device="cpu", progress=False)
    out = predict_normals(model, colour, L, rotations=1, device="cpu", progress=False, sparse_fill="off")
    assert out.shape == (6, 3)
    with pytest.raises(ValueError, match=r"\(P, m\)"):
        predict_normals(CNNPS(w=32), colour, L, rotations=1, device="cpu", progress=False, sparse_fill="off")


def test_prediction_refuses_a_colour_model_in_one_line(tmp_path):
    """``cnnps predict`` reads grey values (its pixel stack): a colour checkpoint is one
    ConfigError naming the file and where to score it."""
    from cnnps.models.network_solver import load_predictor

    torch.manual_seed(6)
    path = save_checkpoint(tmp_path / "rgb.pt", CNNPS(w=16, in_channels=4))
    with pytest.raises(ConfigError, match="rgb.pt: an RGB model .*cnnps score"):
        load_predictor(path, "cpu", "fp32", None)
