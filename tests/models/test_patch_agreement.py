"""Training and prediction build the same b x b patches of maps.

Three builders meet on one synthetic capture (a Lambertian sphere, 16 x 16, a lopsided
albedo, 50 distant lights; the values rounded to float16 first, as the observation files
training reads store them, so every builder sees the same numbers):

- training: :class:`cnnps.train.patch_dataset.PatchStream` over the capture's
  observation file (every light, angles of ``rotation_angles(4)``);
- ``cnnps predict``: :func:`cnnps.ps.patches.capture_patches` (the network solver's call);
- ``predict_normals``: :func:`cnnps.models.map_inputs.patch_maps` on each pixel's unturned
  b x b neighbourhood gathered here from the image stack (zero outside the mask).

They must agree bit for bit at K = 1, 2 and 4, at the mask's edge too. The independent
reference is the scene itself turned: the sphere rendered anew under the lights turned
by q quarter turns about z (exact sign swaps), its albedo image turned by ``np.rot90``
(counter-clockwise as displayed: row 0 on top, x right, y up), and the unturned patch of
the pixel's new position built cell by cell from that image. It must equal the
builders' patch of rotation q. Tolerance 1e-6 on maps in [0, 1]: the turned lights are
exact sign swaps there, ``rotate_z``'s cos(pi / 2) = 6e-17 in the builders, and the
render's dot products may sum in another order, changes of order 1e-16 that no float16
value or map cell rounds differently on this scene (measured: equal bit for bit); a
wrong cell, a grid turned the wrong way or a non-zero cell outside the mask moves a map
by 0.1 or more.
"""

import numpy as np
import pytest
import torch

import cnnps
from cnnps.io.observation_store import observation_path, write_observations
from cnnps.models.checkpoint import save_checkpoint
from cnnps.models.inference import predict_normals
from cnnps.models.map_inputs import patch_maps
from cnnps.models.model_options import build_model
from cnnps.ps.obsmap import observation_maps
from cnnps.ps.patches import capture_patches
from cnnps.ps.rotation import rotate_z, rotation_angles
from cnnps.train.patch_dataset import PatchSampling, PatchStream
from tests.support.synthetic import random_lights, shading, sphere_normals

SIZE, M, W = 16, 50, 8  # a power-of-two size: the sphere's grid is exactly symmetric
REF_TOL = 1e-6


def quarter_turn(v: np.ndarray, q: int) -> np.ndarray:
    """(..., 3) vectors turned about z by q quarter turns, (x, y) -> (-y, x) each: exact."""
    out = np.array(v, np.float64)
    for _ in range(q % 4):
        out = np.stack([-out[..., 1], out[..., 0], out[..., 2]], axis=-1)
    return out


def render(q: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(images (M, H, W) float32 of float16 values, mask, lights) of the scene turned by q
    quarter turns: lights turned, the albedo image turned, the sphere (symmetric) as is."""
    normals, mask = sphere_normals(SIZE)
    rr, cc = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    albedo = 0.3 + 0.6 * cc**2 + 0.25 * rr * (1 - cc)  # no symmetry under any turn or mirror
    albedo += 0.05 * np.random.default_rng(7).random(albedo.shape)
    lights = quarter_turn(random_lights(M, seed=3, max_tilt_deg=70.0), q)
    images = np.rot90(albedo, q) * shading(normals, lights) * mask
    return images.astype(np.float16).astype(np.float32), mask, lights


def neighbourhoods(images: np.ndarray, mask: np.ndarray, b: int) -> np.ndarray:
    """(P, b*b, m) every mask pixel's unturned b x b neighbourhood, row by row, zero
    outside the mask and the image: the ``predict_normals`` input of a patch model."""
    h = b // 2
    pad = np.zeros((images.shape[0], SIZE + 2 * h, SIZE + 2 * h), np.float32)
    pad[:, h:h + SIZE, h:h + SIZE] = images * mask
    rows, cols = np.nonzero(mask)
    cells = [pad[:, rows + i, cols + j].T for i in range(b) for j in range(b)]
    return np.stack(cells, axis=1)


def edge_pixels(mask: np.ndarray, b: int) -> np.ndarray:
    """(P,) bool: the mask pixels with a neighbour of their b x b patch outside the mask."""
    h = b // 2
    pad = np.zeros((SIZE + 2 * h, SIZE + 2 * h), bool)
    pad[h:h + SIZE, h:h + SIZE] = mask
    rows, cols = np.nonzero(mask)
    return ~np.all([pad[rows + i, cols + j] for i in range(b) for j in range(b)], axis=0)


def reference(q: int, b: int) -> np.ndarray:
    """(P, b*b, w, w): each pixel's unturned patch in the scene turned by q quarter turns,
    pixels in the order of the unturned mask (pixel (r, c) is (W - 1 - c, r) after a turn)."""
    images, mask, lights = render(q)
    rows, cols = np.nonzero(render(0)[1])
    for _ in range(q):
        rows, cols = SIZE - 1 - cols, rows
    assert mask[rows, cols].all()
    h = b // 2
    out = np.zeros((len(rows), b * b, W, W), np.float32)
    for i in range(b):
        for j in range(b):
            r, c = rows + i - h, cols + j - h
            inside = (r >= 0) & (r < SIZE) & (c >= 0) & (c < SIZE)
            inside[inside] = mask[r[inside], c[inside]]
            out[inside, i * b + j] = observation_maps(images[:, r[inside], c[inside]].T, lights, w=W)
    return out


@pytest.mark.parametrize("b", [3, 5])
def test_training_and_both_prediction_paths_build_the_same_patches(tmp_path, b):
    images, mask, lights = render(0)
    values = images[:, mask].T  # (P, m) the capture's mask pixels, row-major
    P = len(values)
    edge = edge_pixels(mask, b)
    assert 0 < edge.sum() < P

    # cnnps predict (K = 4) and predict_normals' builder, against the independent reference
    angles4 = rotation_angles(4)
    solver = capture_patches(values, mask, lights, 0, P, b=b, w=W, angles=angles4).reshape(4, P, b * b, W, W)
    near = neighbourhoods(images, mask, b)
    direct = patch_maps(near, np.stack([rotate_z(lights, a) for a in angles4]), angles4, W)
    assert np.array_equal(direct, solver)
    for q in range(4):
        want = reference(q, b)
        np.testing.assert_allclose(solver[q], want, rtol=0, atol=REF_TOL)
        # the edge rule: every edge pixel's patch has a cell outside the mask, an all-zero map
        assert (solver[q][edge].reshape(int(edge.sum()), b * b, -1).max(axis=2) == 0).any(axis=1).all()
    # a turn is not a no-op: the quarter turns differ from the unturned patch by far more than the tolerance
    assert min(np.abs(solver[q] - solver[0]).max() for q in (1, 2, 3)) > 0.1

    # K = 1 and K = 2 are the same angles' patches
    for K in (1, 2):
        angles = rotation_angles(K)
        got = capture_patches(values, mask, lights, 0, P, b=b, w=W, angles=angles).reshape(K, P, b * b, W, W)
        assert np.array_equal(got, solver[::4 // K])
        assert np.array_equal(patch_maps(near, np.stack([rotate_z(lights, a) for a in angles]), angles, W), got)

    # training: every sample is the prediction patch of its centre and angle
    normals, _ = sphere_normals(SIZE)
    rows, cols = np.nonzero(mask)
    rec = write_observations(tmp_path, "sphere", values, lights, normals[mask], rows, cols, mask.shape)
    sampling = PatchSampling(b=b, w=W, rotations=4, min_lights=M, max_lights=M, cone_min_deg=180.0,
                             cone_max_deg=180.0)
    stream = PatchStream([(observation_path(tmp_path, "sphere"), rec)], sampling, batch_size=16, seed=1)
    seen = set()
    for epoch in range(2):
        for batch in stream.iter_batches(epoch):
            assert all(m.all() for m in batch.light_mask)
            q = np.rint(batch.theta / (np.pi / 2)).astype(int) % 4
            assert np.array_equal(batch.theta, angles4[q])
            assert np.array_equal(batch.patches.reshape(len(q), b * b, W, W), solver[q, batch.pixel])
            seen |= {(bool(edge[p]), int(k)) for p, k in zip(batch.pixel, q)}
    assert seen == {(e, k) for e in (False, True) for k in range(4)}  # edge and inner pixels at every angle


def test_predict_normals_equals_cnnps_predict_for_a_patch_model(tmp_path):
    """The whole prediction: ``predict_normals`` on gathered neighbourhoods and
    ``cnnps.predict`` (its network solver, capture_patches) give one normal a pixel, to
    float32 rounding of the network's sums in batches of other sizes (1e-6, the bound of
    tests/api/test_predict_tiles.py; a wrong patch moves a random network's normals by 1e-2)."""
    torch.manual_seed(0)
    net = build_model(patch=3, w=W).eval()
    model = save_checkpoint(tmp_path / "patch3.pt", net, meta={"note": "random weights"})
    images, mask, lights = render(0)
    run = cnnps.predict(images, lights, mask, model=model, rotations=4, device="cpu", precision="fp32",
                        sparse_fill="off")
    direct = predict_normals(net, neighbourhoods(images, mask, 3), lights, rotations=4, device="cpu",
                             precision="fp32", progress=False, sparse_fill="off")
    np.testing.assert_allclose(direct, run.normals[mask], rtol=0, atol=1e-6)
    plain = predict_normals(net, neighbourhoods(images, mask, 3), lights, rotations=1, device="cpu",
                            precision="fp32", progress=False, sparse_fill="off")
    assert np.abs(plain - direct).max() > 1e-2  # the rotations change a random network's answer
