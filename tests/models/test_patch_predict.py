"""A patch model (spatial context, b = 3) through `cnnps predict` and `cnnps.predict`, end
to end: normals and confidence against a direct computation on the whole capture, the
same normals from tiles of any size (each tile read with its halo), and the refusals.

Tolerances: the direct computation runs the trained network as built (``net(x)`` in
torch), the solver runs it folded (:class:`cnnps.models.network.FastCNNPS`, float32 sums
in another order) in batches of another size, so the outputs differ by float32 rounding:
measured at most 1.4e-6 on a normal component; 1e-5 bounds that with room for other
kernels (an error in the patches, the halo or the rotation convention moves normals of a
random network by 1e-2 or more). Tiles compose the network's batches differently: 1e-6
(the bound of tests/api/test_predict_tiles.py).
"""

import json

import numpy as np
import pytest
import torch

import cnnps
from cnnps.infra.errors import ConfigError
from cnnps.models.checkpoint import save_checkpoint
from cnnps.models.heads import decode_output
from cnnps.models.model_options import build_model
from cnnps.ps.confidence import lit_share, network_confidence
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.patches import capture_patches
from cnnps.ps.rotation import average_rotated_predictions, normalize, rotate_z, rotation_angles
from tests.support.cli import run_cli
from tests.support.synthetic import random_lights, shading, sphere_normals, write_capture

W = 8  # observation map width of the tiny networks
TOL = 1e-5
TILE_TOL = 1e-6


@pytest.fixture(scope="module")
def patch_model(tmp_path_factory):
    torch.manual_seed(0)
    net = build_model(patch=3, w=W).eval()
    path = save_checkpoint(tmp_path_factory.mktemp("patch") / "patch3.pt", net, meta={"note": "random weights"})
    return net, path


def direct_normals(net, values, mask, lights, rotations):
    """(P, 3) normals and (P,) rotation spread (deg) of every mask pixel, the whole capture
    at once: capture_patches -> network -> decode -> each answer turned back -> mean."""
    angles = rotation_angles(rotations)
    P = int(mask.sum())
    x = capture_patches(values, mask, lights, 0, P, b=3, w=W, angles=angles)  # (K, P, 3, 3, 1, w, w)
    with torch.no_grad():
        each = np.stack([decode_output(net, net(torch.from_numpy(x[k].reshape(P, 9, W, W)))).numpy()
                         for k in range(len(angles))])
    mean = average_rotated_predictions(each, angles)
    back = [normalize(rotate_z(e.astype(np.float64), -a)) for e, a in zip(each, angles)]
    spread = np.mean([np.degrees(np.arccos(np.clip((b * mean).sum(1), -1, 1))) for b in back], axis=0)
    return mean, spread


def test_cnnps_predict_runs_a_tiny_patch_checkpoint(tmp_path, capsys, patch_model):
    net, model = patch_model
    truth = write_capture(tmp_path / "cap", fmt="exr", size=12, m=20, max_tilt_deg=45)
    out = tmp_path / "out"
    code, _, err = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--model", str(model),
                            "--rotations", "3", "--device", "cpu", "--precision", "fp32", "--sparse-fill", "off"],
                           capsys)
    assert code == 0, err
    mask = truth["mask"]
    normal, confidence = np.load(out / "normal.npy"), np.load(out / "confidence.npy")
    record = json.loads((out / "prediction.json").read_text())
    assert record["rotations"] == 3 and "spread of the K rotated answers" in record["confidence"]["measure"]
    from cnnps.io.capture import load_capture

    I = load_capture(tmp_path / "cap").pixel_intensities()
    L = np.loadtxt(tmp_path / "cap" / "light_directions.txt")
    want, spread = direct_normals(net, I, mask, L, 3)  # K = 3: 120 deg turns, bilinear cells
    np.testing.assert_allclose(normal[mask], want, atol=TOL)
    np.testing.assert_allclose(confidence[mask], network_confidence(spread, lit_share(I, None)), atol=TOL)
    assert np.all(normal[~mask] == 0) and np.all(confidence[~mask] == 0)
    # the neighbours matter: the centre pixel's map in all nine cells gives other normals
    angles = rotation_angles(3)
    with torch.no_grad():
        alone = np.stack([decode_output(net, net(torch.from_numpy(
            np.repeat(observation_maps(I, rotate_z(L, a), w=W)[:, None], 9, axis=1)))).numpy() for a in angles])
    assert np.abs(average_rotated_predictions(alone, angles) - want).max() > 1e-2


def test_tiles_of_any_size_give_the_same_normals(patch_model):
    """Tiles of 7 and 23 mask pixels (a tile ends mid-row, its patches reach rows of
    the tiles before and after) equal the whole capture in one tile, with the sparse
    fill on (each halo pixel filled as its own tile fills it)."""
    net, model = patch_model
    normals, mask = sphere_normals(14)
    lights = random_lights(16, 3, 50.0)
    images = shading(normals, lights).astype(np.float32)
    runs = {t: cnnps.predict(images, lights, mask, model=model, rotations=4, device="cpu", precision="fp32",
                             sparse_fill="on", tile_pixels=t)
            for t in (7, 23, int(mask.sum()))}
    whole = runs[int(mask.sum())]
    assert whole.record["sparse_fill"]["filled_pixels"] == int(mask.sum())  # Lambertian: every pixel filled
    for t in (7, 23):
        np.testing.assert_allclose(runs[t].normals[mask], whole.normals[mask], atol=TILE_TOL)
        np.testing.assert_allclose(runs[t].confidence[mask], whole.confidence[mask], atol=TILE_TOL)
    # and the whole run is the direct computation on the filled values
    from cnnps.ps.sparse_fill import lambertian_fill

    f = lambertian_fill(images[:, mask].T, lights, w=W)
    want, _ = direct_normals(net, f.intensities, mask, f.lights, 4)  # every pixel filled: no light masked
    np.testing.assert_allclose(whole.normals[mask], want, atol=TOL)


def test_a_pinhole_camera_is_refused_in_one_line(tmp_path, capsys, patch_model):
    _, model = patch_model
    write_capture(tmp_path / "cap", fmt="exr", size=8, m=12)
    (tmp_path / "cap" / "intrinsics.txt").write_text("20 0 4\n0 20 4\n0 0 1\n")
    code, _, err = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "out"), "--model", str(model),
                            "--device", "cpu", "--precision", "fp32"], capsys)
    errors = [line for line in err.splitlines() if "error" in line]  # the rest: the progress bars
    assert code == 2 and len(errors) == 1, err
    assert str(model) in errors[0] and "a patch model (patch=3)" in errors[0] and "--camera-model" in errors[0]
    assert not (tmp_path / "out").exists()


def test_near_point_lights_are_refused(patch_model):
    _, model = patch_model
    normals, mask = sphere_normals(8)
    lights = random_lights(12, 0, 40.0)
    images = shading(normals, lights).astype(np.float32)
    K = np.array([[20.0, 0, 4], [0, 20.0, 4], [0, 0, 1]])
    with pytest.raises(ConfigError, match="--light-model") as info:
        cnnps.predict(images, None, mask, light_positions=lights * 10.0 - [0, 0, 10.0], intrinsics=K, model=model,
                      rotations=1, device="cpu", precision="fp32", distance=10.0)
    assert str(model) in str(info.value) and "\n" not in str(info.value)
