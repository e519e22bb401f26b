"""Observation maps: invariances, the cell rule and a brute-force reference."""

import numpy as np
import pytest

from cnnps.obsmap import light_cells, observation_maps
from cnnps.rotation import rotate_z

W = 32


def _centre_lights(m, seed=0, w=W):
    """m unit lights at the centres of distinct cells (far from cell boundaries)."""
    rng = np.random.default_rng(seed)
    centres = (np.arange(w) + 0.5) / w * 2 - 1
    cx, cy = np.meshgrid(centres, centres)
    ok = cx**2 + cy**2 < 0.95
    idx = rng.choice(np.flatnonzero(ok), m, replace=False)
    lx, ly = cx.ravel()[idx], cy.ravel()[idx]
    return np.stack([lx, ly, np.sqrt(1 - lx**2 - ly**2)], axis=1)


def _brute_force(I, L, w, light_mask=None):
    """Per-pixel Python reference of the documented rule."""
    P, m = I.shape
    out = np.zeros((P, w, w))
    for p in range(P):
        acc, cnt = {}, {}
        for j in range(m):
            if light_mask is not None and not light_mask[p, j]:
                continue
            col = min(int(w * (L[j, 0] + 1) / 2), w - 1)
            row = min(int(w * (L[j, 1] + 1) / 2), w - 1)
            acc[row, col] = acc.get((row, col), 0.0) + max(I[p, j], 0.0)
            cnt[row, col] = cnt.get((row, col), 0) + 1
        for k in acc:
            out[p][k] = acc[k] / cnt[k]
        if out[p].max() > 0:
            out[p] /= out[p].max()
    return out


def _rand_lights(m, seed):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2])
    return L / np.linalg.norm(L, axis=1, keepdims=True)


def test_matches_brute_force_with_collisions_and_negatives():
    rng = np.random.default_rng(1)
    L = _rand_lights(300, 2)  # 300 lights in 32x32 cells: many collisions
    I = rng.uniform(-0.05, 1.0, (5, 300))
    maps = observation_maps(I, L, W)
    assert maps.shape == (5, W, W) and maps.dtype == np.float32
    np.testing.assert_allclose(maps, _brute_force(I, L, W), rtol=1e-5, atol=1e-6)
    row, col = light_cells(L, W)
    assert len(set(zip(row, col))) < 300  # collisions really happened


def test_collision_rule_is_the_mean():
    L = np.array([[0.01, 0.01, 1.0], [0.012, 0.013, 1.0], [-0.5, 0.5, 0.7]])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    row, col = light_cells(L, W)
    assert (row[0], col[0]) == (row[1], col[1]) == (16, 16)
    maps = observation_maps(np.array([[0.2, 0.6, 0.8]]), L, W)[0]
    assert maps[16, 16] == pytest.approx(0.4 / 0.8)
    assert maps[row[2], col[2]] == pytest.approx(1.0)
    assert np.count_nonzero(maps) == 2


def test_cell_indices_follow_the_frame():
    L = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    row, col = light_cells(L, W)
    assert col.tolist() == [0, W - 1, 16, 16, 16]
    assert row.tolist() == [16, 16, 0, W - 1, 16]  # row 0 holds ly = -1


def test_order_of_images_does_not_matter():
    rng = np.random.default_rng(3)
    L = _rand_lights(200, 4)
    I = rng.uniform(0, 1, (50, 200))
    perm = rng.permutation(200)
    a = observation_maps(I, L, W)
    b = observation_maps(I[:, perm], L[perm], W)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)


def test_each_map_peaks_at_one_and_dark_pixels_stay_zero():
    rng = np.random.default_rng(5)
    L = _rand_lights(96, 6)
    I = rng.uniform(0, 3, (20, 96))
    I[3] = 0.0
    I[4] = -1.0  # all below black
    maps = observation_maps(I, L, W)
    peaks = maps.reshape(20, -1).max(axis=1)
    assert np.all(peaks[[3, 4]] == 0)
    np.testing.assert_allclose(np.delete(peaks, [3, 4]), 1.0, rtol=1e-6)
    assert maps.min() >= 0


@pytest.mark.parametrize("k", [1, 2, 3])
def test_rotating_lights_by_quarter_turns_rotates_the_map(k):
    """Lights turned by k * 90 deg counter-clockwise (x toward y) about z.

    Rows grow with +y, so seen as an array (row 0 first) the map turns clockwise:
    np.rot90(map, -k).
    """
    rng = np.random.default_rng(7)
    L = _centre_lights(60, seed=8)
    I = rng.uniform(0.1, 1, (10, 60))
    base = observation_maps(I, L, W)
    turned = observation_maps(I, rotate_z(L, k * np.pi / 2), W)
    np.testing.assert_array_equal(turned, np.rot90(base, -k, axes=(1, 2)))
    if k != 2:  # and the other direction is wrong (the test can fail)
        assert not np.array_equal(turned, np.rot90(base, k, axes=(1, 2)))


def test_light_mask_equals_building_from_the_subset():
    rng = np.random.default_rng(9)
    L = _rand_lights(120, 10)
    I = rng.uniform(0, 1, (6, 120))
    lm = rng.uniform(size=(6, 120)) < 0.4
    maps = observation_maps(I, L, W, light_mask=lm)
    for p in range(6):
        ref = observation_maps(I[p : p + 1, lm[p]], L[lm[p]], W)[0]
        np.testing.assert_allclose(maps[p], ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(maps, _brute_force(I, L, W, lm), rtol=1e-5, atol=1e-6)
    full = observation_maps(I, L, W, light_mask=np.ones_like(lm))
    np.testing.assert_array_equal(full, observation_maps(I, L, W))


def test_bad_shapes():
    with pytest.raises(ValueError):
        observation_maps(np.ones((2, 5)), np.ones((4, 3)))
    with pytest.raises(ValueError):
        observation_maps(np.ones((2, 5)), _rand_lights(5, 0), light_mask=np.ones((2, 4), bool))
