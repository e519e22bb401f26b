"""A heat-map checkpoint through `cnnps predict`, end to end: normals and the heat-map
confidence recomputed independently of the tile loop."""

import json

import numpy as np
import pytest
import torch

from cnnps.models.checkpoint import save_checkpoint
from cnnps.models.heads import heat_maps
from cnnps.models.heatmap import decode_with_spread
from cnnps.models.model_options import build_model
from cnnps.ps.confidence import heatmap_confidence, lit_share
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.rotation import average_rotated_predictions, rotate_z, rotation_angles
from tests.support.cli import run_cli
from tests.support.synthetic import write_capture


@pytest.mark.parametrize("arch, head", [("unet", "heatmap"), ("cnnps", "heatmap-softmax")])
def test_cnnps_predict_runs_a_tiny_heatmap_checkpoint(tmp_path, capsys, arch, head):
    truth = write_capture(tmp_path / "cap", fmt="exr", size=12, m=20, max_tilt_deg=45)
    torch.manual_seed(0)
    net = build_model(arch=arch, head=head, w=16).eval()
    model = save_checkpoint(tmp_path / "heat.pt", net, meta={"note": "random weights"})
    out = tmp_path / "out"
    code, _, err = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--model", str(model), "--rotations", "2",
                            "--device", "cpu", "--precision", "fp32", "--sparse-fill", "off"], capsys)
    assert code == 0, err
    mask = truth["mask"]
    normal, confidence = np.load(out / "normal.npy"), np.load(out / "confidence.npy")
    record = json.loads((out / "prediction.json").read_text())
    assert "heat-map spread" in json.dumps(record)
    # the same normals and confidence from the capture's grey values, without the tile loop
    from cnnps.io.capture import load_capture

    I = load_capture(tmp_path / "cap").pixel_intensities()
    L = np.loadtxt(tmp_path / "cap" / "light_directions.txt")
    angles = rotation_angles(2)
    each, spreads = [], []
    for a in angles:
        maps = torch.from_numpy(observation_maps(I, rotate_z(L, a), w=16))[:, None]
        with torch.no_grad():
            n, s = decode_with_spread(heat_maps(head, net(maps)))  # heatmap-softmax: the softmax of its logits
        each.append(n.numpy())
        spreads.append(s.numpy())
    want = average_rotated_predictions(np.stack(each), angles)
    np.testing.assert_allclose(normal[mask], want, atol=1e-4)
    want_conf = heatmap_confidence(np.mean(spreads, axis=0), lit_share(I, None))
    np.testing.assert_allclose(confidence[mask], want_conf, atol=1e-4)
    assert np.all(confidence[~mask] == 0) and np.all((want_conf > 0) & (want_conf <= 1))



def test_heatmap_decoding_option_changes_the_normals_only_for_parabola(tmp_path):
    import cnnps
    from cnnps.models.heatmap import decode_heatmaps

    rng = np.random.default_rng(3)
    L = rng.normal(size=(20, 3))
    L[:, 2] = np.abs(L[:, 2]) + 1.0
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    images = rng.uniform(0.1, 1.0, size=(20, 4, 5)).astype(np.float32)
    torch.manual_seed(0)
    net = build_model(arch="unet", head="heatmap", w=16).eval()
    model = save_checkpoint(tmp_path / "heat.pt", net, meta={"note": "random weights"})
    common = dict(model=model, rotations=1, device="cpu", precision="fp32", sparse_fill="off")
    default = cnnps.predict(images, L, **common).normals
    window = cnnps.predict(images, L, heatmap_decoding="window", **common).normals
    parabola = cnnps.predict(images, L, heatmap_decoding="parabola", **common).normals
    np.testing.assert_array_equal(window, default)
    # the parabola's normals: the same heat-maps decoded by the other method
    maps = torch.from_numpy(observation_maps(images.reshape(20, -1).T, L, w=16))[:, None]
    with torch.no_grad():
        heat = net(maps)
    want = decode_heatmaps(heat, method="parabola").numpy().reshape(4, 5, 3)
    np.testing.assert_allclose(parabola, want, atol=1e-5)
    assert np.abs(parabola - window).max() > 1e-3
