"""Heat-map and patch models through the inference consumers: rotated_normals,
predict_normals, the precision probe."""

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.models.inference import MapPredictor, predict_normals, rotated_normals
from cnnps.models.map_inputs import patch_maps
from cnnps.models.model_options import build_model
from cnnps.models.patch import PatchConv
from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.rotation import average_rotated_predictions, rotate_z, rotation_angles


def _scene(P=30, m=40, seed=0):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.3
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    return rng.random((P, m)).astype(np.float32), L


@pytest.mark.parametrize("arch", ["cnnps", "unet"])
def test_rotations_decode_each_heatmap_then_average(arch):
    torch.manual_seed(0)
    pred = MapPredictor(build_model(arch=arch, head="heatmap", w=16), device="cpu")
    I, L = _scene()
    K = 4
    spread = np.empty(len(I), np.float32)
    got = rotated_normals(pred, I, L, K, spread=spread, pixel_chunk=40)  # several chunks
    angles = rotation_angles(K)
    each, each_spread = [], []
    for a in angles:
        s = np.empty(len(I), np.float32)
        each.append(pred(observation_maps(I, rotate_z(L, a), w=16), spread=s))
        each_spread.append(s)
    np.testing.assert_allclose(got, average_rotated_predictions(np.stack(each), angles), atol=1e-6)
    np.testing.assert_allclose(spread, np.mean(each_spread, axis=0), rtol=1e-6)
    again = rotated_normals(pred, I, L, K)  # the same normals without the spread
    np.testing.assert_array_equal(again, got)


def test_patch_model_rotations_turn_the_grid_and_average():
    torch.manual_seed(1)
    model = build_model(head="heatmap", patch=3, w=16)
    pred = MapPredictor(model, device="cpu")
    I, L = _scene(P=12 * 9)
    I = I.reshape(12, 9, -1)
    angles = rotation_angles(4)
    got = predict_normals(model, I, L, rotations=4, device="cpu", progress=False, sparse_fill="off")
    maps = patch_maps(I, np.stack([rotate_z(L, a) for a in angles]), angles, 16)
    each = np.stack([pred(maps[k]) for k in range(4)])
    np.testing.assert_allclose(got, average_rotated_predictions(each, angles), atol=1e-6)
    with pytest.raises(ConfigError, match=r"a patch model \(patch=3\) takes 1, 2 or 4 rotations"):
        rotated_normals(pred, I, L, 10)
    with pytest.raises(ValueError, match=r"takes \(P, 9, m\) intensities"):
        rotated_normals(pred, I[:, 0], L, 1)
    filled = predict_normals(model, I[:, :, :20], L[:20], rotations=1, device="cpu", progress=False, sparse_fill="on")
    assert filled.shape == (12, 3) and np.allclose(np.linalg.norm(filled, axis=1), 1, atol=1e-5)


def test_the_precision_probe_runs_heatmap_and_patch_models(monkeypatch, tmp_path):
    import cnnps.models.precision_probe as pp

    monkeypatch.setattr(pp, "PROBE_MAPS", 32)
    monkeypatch.setattr(pp, "TIMED_CALLS", 1)
    monkeypatch.setattr(pp, "thread_candidates", lambda: [torch.get_num_threads()])
    torch.manual_seed(2)
    for model in (build_model(head="heatmap", patch=3, w=16), build_model(arch="unet", head="heatmap", w=16)):
        choice = pp.probe(model, torch.device("cpu"), batch_size=32)
        assert choice.precision in ("fp32", "bf16") and "fp32" in choice.reason
        assert np.isfinite(choice.error_change_deg.get("bf16", 0.0))


@pytest.mark.parametrize("b", [3, 5])
def test_a_unet_predicts_through_its_folded_patch_layer(b):
    torch.manual_seed(b)
    model = build_model(arch="unet", head="heatmap", patch=b, w=16)
    model.train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    maps = np.random.default_rng(b).random((40, b * b, 16, 16)).astype(np.float32)
    folded = MapPredictor(model, device="cpu")
    plain = MapPredictor(model, device="cpu", fold=False)
    assert not any(isinstance(m, PatchConv) for m in folded.net.modules())
    assert any(isinstance(m, PatchConv) for m in plain.net.modules())
    s_folded, s_plain = np.empty(40, np.float32), np.empty(40, np.float32)
    n_folded, n_plain = folded(maps, spread=s_folded), plain(maps, spread=s_plain)
    # one float32 convolution against two: float rounding only, far below a decoded cell
    assert angular_error_deg(n_folded, n_plain).max() < 1e-3
    np.testing.assert_allclose(s_folded, s_plain, atol=1e-3)
    assert model.training and all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # untouched
    with torch.no_grad():  # the heat-maps themselves, against the training network's
        x = torch.from_numpy(maps)
        np.testing.assert_allclose(folded.net(x).numpy(), model.eval()(x).numpy(), rtol=1e-4, atol=1e-5)
