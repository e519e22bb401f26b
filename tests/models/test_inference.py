from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from cnnps.infra.errors import CnnpsError
from cnnps.models.inference import MapPredictor, predict_normals, resolve_device
from cnnps.models.network import CNNPS
from cnnps.ps.metrics import angular_error_deg


class CellLambertian(nn.Module):
    """A 'network' that reads a normal off an observation map analytically.

    Each non-empty cell is taken as a light at the cell centre (lz from the unit
    sphere) and the Lambertian least-squares normal is solved per map. With lights at
    cell centres and no shadows this is exact, and rotating the lights by multiples of
    90 degrees maps cell centres onto cell centres, so it is exactly rotation-equivariant.
    """

    def __init__(self, w: int):
        super().__init__()
        self.w = w
        c = (np.arange(w) + 0.5) * 2.0 / w - 1.0
        ly, lx = np.meshgrid(c, c, indexing="ij")  # row = y cell, col = x cell
        lz = np.sqrt(np.clip(1.0 - lx**2 - ly**2, 0.0, None))
        self.register_buffer("grid", torch.tensor(np.stack([lx, ly, lz], -1).reshape(-1, 3)))

    def forward(self, x):
        v = x.reshape(x.shape[0], -1).double()
        used = (v > 0).double()
        a = torch.einsum("bc,ci,cj->bij", used, self.grid, self.grid)
        b = v @ self.grid
        n = torch.linalg.solve(a + 1e-12 * torch.eye(3, dtype=a.dtype), b.unsqueeze(-1)).squeeze(-1)
        return torch.nn.functional.normalize(n, dim=1).float()


def _cell_centre_lights(w: int, m: int, rng) -> np.ndarray:
    """m distinct cell-centre light directions within ~45 degrees of the view axis."""
    c = (np.arange(w) + 0.5) * 2.0 / w - 1.0
    ly, lx = np.meshgrid(c, c, indexing="ij")
    ok = lx**2 + ly**2 < 0.5
    pick = rng.choice(np.flatnonzero(ok.ravel()), size=m, replace=False)
    lx, ly = lx.ravel()[pick], ly.ravel()[pick]
    return np.stack([lx, ly, np.sqrt(1 - lx**2 - ly**2)], 1)


def _normals(p: int, rng, max_tilt_deg: float = 35.0) -> np.ndarray:
    tilt = np.deg2rad(rng.uniform(0, max_tilt_deg, p))
    az = rng.uniform(0, 2 * np.pi, p)
    return np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)


@pytest.fixture(scope="module")
def lambertian_scene():
    rng = np.random.default_rng(0)
    lights = _cell_centre_lights(32, 60, rng)
    normals = _normals(300, rng)
    albedo = rng.uniform(0.3, 1.0, (300, 1))
    intensities = albedo * (normals @ lights.T)
    assert intensities.min() > 0  # no shadows: the toy solver is exact
    return intensities.astype(np.float32), lights, normals


def test_toy_model_exact_and_equivariant(lambertian_scene):
    intensities, lights, normals = lambertian_scene
    toy = CellLambertian(32)
    n1 = predict_normals(toy, intensities, lights, rotations=1, device="cpu", progress=False)
    assert n1.dtype == np.float32 and n1.shape == (300, 3)
    assert angular_error_deg(n1, normals).max() < 1e-3
    # 90-degree steps map cell centres onto cell centres: K = 4 must agree exactly. A
    # wrong rotation sign (lights by +theta, answer back by +theta) would be off by
    # up to 2 * tilt = 70 degrees here.
    n4 = predict_normals(toy, intensities, lights, rotations=4, device="cpu", progress=False)
    assert angular_error_deg(n4, n1).max() < 1e-3


def test_k1_and_k10_agree_for_equivariant_model():
    # Off-grid lights: rotations by 36 degrees move lights inside their cells, so the
    # toy model is equivariant only up to the cell quantisation (measured: mean
    # 0.08 deg, max 0.18 deg at w = 64 with 200 lights; error to the truth 0.04 deg).
    rng = np.random.default_rng(1)
    m = 200
    tilt = np.arccos(rng.uniform(np.cos(np.deg2rad(45)), 1.0, m))
    az = rng.uniform(0, 2 * np.pi, m)
    lights = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)
    normals = _normals(400, rng, max_tilt_deg=40)
    intensities = np.maximum(normals @ lights.T, 0).astype(np.float32)
    toy = CellLambertian(64)
    n1 = predict_normals(toy, intensities, lights, rotations=1, device="cpu", progress=False)
    n10 = predict_normals(toy, intensities, lights, rotations=10, device="cpu", progress=False)
    diff = angular_error_deg(n10, n1)
    assert diff.mean() < 0.15 and diff.max() < 0.5
    assert angular_error_deg(n10, normals).mean() < 0.1


def test_streaming_and_batching_do_not_change_results(lambertian_scene):
    intensities, lights, _ = lambertian_scene
    torch.manual_seed(0)
    model = CNNPS().eval()
    ref = predict_normals(model, intensities[:96], lights, rotations=2, device="cpu", progress=False)
    out = predict_normals(model, intensities[:96], lights, rotations=2, device="cpu", progress=False,
                          batch_size=7, pixel_chunk=40)
    # oneDNN picks kernels by batch size (and thread count, SIMD path), so the two differ
    # by float32 rounding, ~1e-6 per prediction. K = 2 then averages the prediction
    # under the lights and, rotated back, the one under the lights turned by 180 deg;
    # an untrained net is far from equivariant, so for some pixels the two nearly cancel
    # and renormalising their mean m scales the rounding by 1/|m| (measured: 6e-5 with
    # 2 threads at |m| = 0.006, where a flat atol 1e-4 had little room). Bound the
    # rounding, not its amplified size: |out - ref| * |m| <= 2e-5 (measured 1.9e-6).
    # A chunking or batching bug moves normals by ~0.1-1 at |m| ~ 0.5.
    from cnnps.ps.rotation import rotate_z

    p0 = predict_normals(model, intensities[:96], lights, rotations=1, device="cpu", progress=False)
    p1 = rotate_z(predict_normals(model, intensities[:96], rotate_z(lights, np.pi), rotations=1, device="cpu",
                                  progress=False), -np.pi)
    m = np.linalg.norm((p0 + p1) / 2, axis=1)
    assert (np.abs(out - ref).max(axis=1) * m).max() <= 2e-5
    np.testing.assert_allclose(np.linalg.norm(ref, axis=1), 1.0, atol=1e-5)
    # the fast path (folded network) equals the plain eager network
    from cnnps.ps.obsmap import observation_maps

    with torch.no_grad():
        eager = model(torch.from_numpy(observation_maps(intensities[:96], lights)).unsqueeze(1)).numpy()
    one = predict_normals(model, intensities[:96], lights, rotations=1, device="cpu", progress=False)
    assert np.abs(one - eager).max() < 1e-4


def test_bf16_agrees_with_fp32(lambertian_scene):
    intensities, lights, _ = lambertian_scene
    torch.manual_seed(0)
    model = CNNPS().eval()
    a = predict_normals(model, intensities, lights, rotations=1, device="cpu", precision="fp32", progress=False)
    b = predict_normals(model, intensities, lights, rotations=1, device="cpu", precision="bf16", progress=False)
    err = angular_error_deg(a, b)
    # bf16 has an 8-bit mantissa: random he-initialised weights (a pessimistic proxy)
    # measured mean ~0.15 deg, max < 1 deg; it must differ (else bf16 did not run).
    assert 0 < err.mean() < 0.5 and err.max() < 3.0


def test_progress_bar_over_all_maps(lambertian_scene, capsys):
    intensities, lights, _ = lambertian_scene
    toy = CellLambertian(32)
    predict_normals(toy, intensities[:50], lights, rotations=3, device="cpu", progress=True, batch_size=16)
    err = capsys.readouterr().err
    assert "cnn-ps" in err and "/150" in err  # one bar over K * P maps
    predict_normals(toy, intensities[:50], lights, rotations=3, device="cpu", progress=False)
    assert capsys.readouterr().err == ""


def test_cuda_without_cuda_is_a_clear_error():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    with pytest.raises(CnnpsError, match="cuda.*(no CUDA|CUDA support)"):
        resolve_device("cuda")
    with pytest.raises(CnnpsError, match="cuda"):
        predict_normals(CellLambertian(32), np.ones((2, 3), np.float32), np.eye(3), device="cuda")
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("CPU") == torch.device("cpu")


def test_map_predictor_leaves_model_and_rng_alone():
    # the train stage validates with it between training steps: the model keeps its mode
    # and weights, and the global RNG (the next steps' dropout masks) is not drawn from
    torch.manual_seed(0)
    model = CNNPS(w=16).train()
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    state = torch.get_rng_state()
    maps = np.random.default_rng(0).random((5, 16, 16)).astype(np.float16)  # float16, as in the shards
    out = MapPredictor(model, device="cpu")(maps)
    assert torch.equal(torch.get_rng_state(), state) and model.training
    assert all(torch.equal(v, weights[k]) for k, v in model.state_dict().items())
    with torch.no_grad():
        eager = model.eval()(torch.from_numpy(maps.astype(np.float32)).unsqueeze(1)).numpy()
    assert np.abs(out - eager).max() < 1e-4  # eval mode (no dropout); rounding apart (measured 6e-7)


@pytest.mark.parametrize("bad", [dict(device="tpu"), dict(precision="fp8"), dict(batch_size=0)])
def test_bad_options(bad):
    with pytest.raises(CnnpsError):
        MapPredictor(CellLambertian(32), **{"device": "cpu", **bad})


def test_shape_errors():
    toy = CellLambertian(32)
    with pytest.raises(ValueError, match="lights"):
        predict_normals(toy, np.ones((4, 5), np.float32), np.ones((4, 3)), progress=False)
    with pytest.raises(ValueError, match="rotations"):
        predict_normals(toy, np.ones((4, 3), np.float32), np.eye(3), rotations=0, progress=False)


class _RecordingPredictor:
    """A MapPredictor stand-in that returns a fixed function of each map and keeps the maps."""

    w = 32

    def __init__(self):
        self.maps = []

    def __call__(self, maps, progress=None):
        self.maps.append(np.array(maps))
        flat = maps.reshape(len(maps), -1).astype(np.float64)
        v = np.stack([flat[:, :300].sum(1), flat[:, 300:700].sum(1), 1.0 + flat[:, 700:].sum(1)], 1)
        return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


@pytest.mark.parametrize("read_ahead", [0, 1])
def test_rotated_normals_builds_the_same_maps_in_one_pass(read_ahead):
    """All K rotations of a chunk in one pass (observation_maps_multi), built a chunk ahead:
    the maps, and so the normals, equal K separate observation_maps calls."""
    from cnnps.models.inference import rotated_normals
    from cnnps.ps.obsmap import observation_maps
    from cnnps.ps.rotation import average_rotated_predictions, rotate_z, rotation_angles

    rng = np.random.default_rng(3)
    lights = _cell_centre_lights(32, 40, np.random.default_rng(4)) @ np.diag([1, -1, 1])  # any directions
    I = rng.random((250, 40)).astype(np.float32)
    mask = rng.random((250, 40)) > 0.2
    pred = _RecordingPredictor()
    got = rotated_normals(pred, I, lights, 5, light_mask=mask, pixel_chunk=200, read_ahead=read_ahead)
    angles = rotation_angles(5)
    ref_maps = [observation_maps(I, rotate_z(lights, a), light_mask=mask) for a in angles]
    ref = average_rotated_predictions(np.stack([_RecordingPredictor()(m) for m in ref_maps]), angles)
    np.testing.assert_array_equal(got, ref.astype(np.float32))
    chunks = [m.reshape(5, -1, 32, 32) for m in pred.maps]  # 40 pixels a chunk: 200 maps // 5 rotations
    assert [c.shape[1] for c in chunks] == [40] * 6 + [10]
    for k in range(5):
        np.testing.assert_array_equal(np.concatenate([c[k] for c in chunks]), ref_maps[k])


class _CellCounter(nn.Module):
    """Records how many cells of each map are non-empty; answers +z."""

    def __init__(self, w: int = 32):
        super().__init__()
        self.w = w
        self.cells: list[int] = []

    def forward(self, x):
        self.cells += (x.reshape(x.shape[0], -1) > 0).sum(1).tolist()
        return torch.tensor([[0.0, 0.0, 1.0]]).repeat(x.shape[0], 1)


def test_sparse_fill_below_fifty_images_only(lambertian_scene):
    from cnnps.ps.sparse_fill import FILL_BELOW, VIRTUAL_LIGHTS

    intensities, lights, normals = lambertian_scene  # 60 lights, no shadows
    counts = {}
    for m, mode in ((8, "auto"), (8, "off"), (FILL_BELOW, "auto"), (FILL_BELOW, "on")):
        net = _CellCounter()
        predict_normals(net, intensities[:, :m], lights[:m], rotations=1, device="cpu", progress=False,
                        sparse_fill=mode)
        counts[m, mode] = np.array(net.cells)
    assert (counts[8, "off"] == 8).all() and (counts[FILL_BELOW, "auto"] == FILL_BELOW).all()
    assert (counts[8, "auto"] == 8 + VIRTUAL_LIGHTS).all()  # exact Lambertian values: every pixel filled
    assert (counts[FILL_BELOW, "on"] > FILL_BELOW).all()
    # the virtual values are the Lambertian fit's: an exact reader of maps stays exact
    toy = CellLambertian(32)
    n = predict_normals(toy, intensities[:, :8], lights[:8], rotations=1, device="cpu", progress=False)
    assert angular_error_deg(n, normals).max() < 1e-2
    with pytest.raises(ValueError, match="sparse fill"):
        predict_normals(toy, intensities[:, :8], lights[:8], device="cpu", progress=False, sparse_fill="yes")
