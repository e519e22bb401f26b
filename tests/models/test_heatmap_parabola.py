"""The log-parabola heat-map decoding (cnnps.models.heatmap, method="parabola"): exact
targets against the normals they were made from, and the fall-backs to the window's
centre of mass against a loop reference."""

import numpy as np
import pytest
import torch

from cnnps.models.heatmap import decode_heatmaps, decode_with_spread, heatmap_targets


def _cap_normals(n: int, max_deg: float, seed: int) -> torch.Tensor:
    """``n`` unit normals uniform over the cap within ``max_deg`` of +z."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.cos(np.deg2rad(max_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    r = np.sqrt(1 - z * z)
    return torch.tensor(np.stack([r * np.cos(phi), r * np.sin(phi), z], 1), dtype=torch.float32)


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    cos = np.clip(np.sum(a.double().numpy() * b.double().numpy(), axis=1), -1, 1)
    return np.rad2deg(np.arccos(cos))


def _window_uv(heat: np.ndarray) -> tuple[float, float]:
    """The 5 x 5 window's centre of mass (u, v) in cells, written from the definition."""
    h, w = heat.shape
    r0, c0 = np.unravel_index(np.argmax(heat), heat.shape)
    su = sv = total = 0.0
    for r in range(r0 - 2, r0 + 3):
        for c in range(c0 - 2, c0 + 3):
            if 0 <= r < h and 0 <= c < w and heat[r, c] > 0:
                total += heat[r, c]
                su += heat[r, c] * (c + 0.5)
                sv += heat[r, c] * (r + 0.5)
    return (su / total, sv / total) if total > 0 else (c0 + 0.5, r0 + 0.5)


@pytest.mark.parametrize("w, max_deg", [(32, 75.0), (16, 60.0)])
def test_exact_targets_decode_to_their_normals(w, max_deg):
    # within these caps the peak lies within one cell of an inner cell's centre (the clamp)
    normals = _cap_normals(4000, max_deg, seed=w)
    targets = heatmap_targets(normals, w)
    err = _angle_deg(decode_heatmaps(targets, method="parabola"), normals)
    assert err.max() < 0.05, err.max()  # float32 maps and logs: measured max 0.03 deg
    window = _angle_deg(decode_heatmaps(targets), normals)
    assert window.mean() > 0.3  # the centre of mass's bias the parabola removes (measured 0.9-1.4 deg)


def test_an_axis_with_a_non_positive_neighbour_takes_the_window_centre_of_mass():
    w = 16
    normal = torch.tensor([[0.2, -0.3, np.sqrt(1 - 0.13)]], dtype=torch.float32)
    heat = heatmap_targets(normal, w)[0].numpy()
    r0, c0 = np.unravel_index(np.argmax(heat), heat.shape)
    heat[r0, c0 + 1] = 0.0  # the u-axis stencil fails; column c0 (the v-axis stencil) is untouched
    got = decode_heatmaps(torch.from_numpy(heat)[None], method="parabola")[0].double().numpy()
    u_mass, _ = _window_uv(heat)
    v_true = w * (float(normal[0, 1]) + 1) / 2
    nx, ny = 2 * u_mass / w - 1, 2 * v_true / w - 1
    want = np.array([nx, ny, np.sqrt(1 - nx * nx - ny * ny)])
    np.testing.assert_allclose(got, want / np.linalg.norm(want), atol=2e-5)


def test_flat_and_empty_maps_decode_as_the_window_does():
    flat = torch.full((1, 8, 8), 0.5)  # log-curvature 0 on both axes
    empty = -torch.rand(1, 8, 8)  # nothing positive
    for maps in (flat, empty):
        torch.testing.assert_close(decode_heatmaps(maps, method="parabola"), decode_heatmaps(maps), rtol=0, atol=0)
    # a sharp, symmetric peak: concave, offset 0 on both axes -> the maximum's cell centre
    peak = torch.zeros(1, 8, 8)
    peak[0, 3, 5], peak[0, 3, 4], peak[0, 3, 6], peak[0, 2, 5], peak[0, 4, 5] = 1.0, 0.5, 0.5, 0.5, 0.5
    nx, ny = 2 * 5.5 / 8 - 1, 2 * 3.5 / 8 - 1
    want = torch.tensor([[nx, ny, np.sqrt(1 - nx * nx - ny * ny)]], dtype=torch.float32)
    torch.testing.assert_close(decode_heatmaps(peak, method="parabola"), want, rtol=0, atol=1e-6)


def test_spread_keeps_its_meaning_and_unknown_methods_are_refused():
    maps = torch.rand(5, 16, 16)
    normals, spread = decode_with_spread(maps, method="parabola")
    torch.testing.assert_close(normals, decode_heatmaps(maps, method="parabola"), rtol=0, atol=0)
    assert torch.all((spread > 0) & (spread < 90))
    with pytest.raises(ValueError, match="heat-map decoding must be one of window, parabola, got 'mean'"):
        decode_heatmaps(maps, method="mean")
