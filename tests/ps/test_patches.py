"""Patches of observation maps: cell offsets, rotation with the image, the edge rule,
interpolation, and the prediction tiles."""

import numpy as np
import pytest

from cnnps.ps.obsmap import observation_maps
from cnnps.ps.patches import (
    capture_patches,
    gather_taps,
    mask_row_starts,
    neighbour_taps,
    patch_maps,
    patch_offsets,
    patch_read_range,
    reach,
)
from cnnps.ps.rotation import rotate_z, rotation_angles
from cnnps.synth.training_samples import build_rows
from tests.support.renders import random_lights, sphere_normals

W = 16


def _lambertian(normals: np.ndarray, mask: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """(m, H, W) float32 shading max(n.l, 0) inside the mask, 0 outside."""
    return (np.clip(np.einsum("hwc,mc->mhw", normals, lights), 0, None) * mask).astype(np.float32)


def _scene(size=13, m=40, seed=0):
    rng = np.random.default_rng(seed)
    mask, normals = sphere_normals(size, radius=0.42, center=(0.06, -0.03))  # off centre: no symmetry
    lights = random_lights(rng, m)
    return mask, normals, lights, _lambertian(normals, mask, lights)


def test_offsets_at_zero_and_ninety_degrees():
    off0 = patch_offsets(3, [0.0])[0]
    assert off0.tolist() == [[i - 1, j - 1] for i in range(3) for j in range(3)]
    off90 = patch_offsets(3, [np.pi / 2])[0]
    # cell [i, j] of the image turned counter-clockwise is the stored pixel (r + j - 1, c - i + 1)
    assert off90.tolist() == [[j - 1, 1 - i] for i in range(3) for j in range(3)]
    assert reach(1) == 0 and reach(3) == 3 and reach(5) == 4 and reach(5, "nearest") == 3


def test_b1_patch_is_the_extract_stages_map_bit_for_bit():
    rng = np.random.default_rng(3)
    P, m = 50, 70
    I = rng.random((P, m)).astype(np.float32) * (rng.random((P, m)) > 0.3)
    L = random_lights(rng, m)
    light_mask = rng.random((P, m)) < 0.6
    normals = rng.normal(size=(P, 3))
    angles = rotation_angles(10)
    maps16, rot_n = build_rows(I, normals, L, light_mask, angles, W)  # the extract stage's rows
    for r, theta in enumerate(angles):
        th = np.full(P, theta)
        got = patch_maps(I[:, None, :], L, th, W, light_mask=light_mask)
        assert got.shape == (P, 1, 1, 1, W, W)
        assert np.array_equal(got[:, 0, 0, 0], observation_maps(I, rotate_z(L, theta), W, light_mask=light_mask))
        assert np.array_equal(got[:, 0, 0, 0].astype(np.float16).view(np.uint16), maps16[r].view(np.uint16))
    # capture_patches at b = 1: every mask pixel's own map
    mask, _, lights, images = _scene()
    values = images[:, mask].T
    got = capture_patches(values, mask, lights, 0, len(values), b=1, w=W, angles=angles[:3])
    for k, theta in enumerate(angles[:3]):
        assert np.array_equal(got[k, :, 0, 0, 0], observation_maps(values, rotate_z(lights, theta), W))


def test_ninety_degree_rotation_of_the_image_gives_the_rotated_images_patches():
    mask, normals, lights, images = _scene()
    theta = np.pi / 2
    # the capture turned counter-clockwise by 90 degrees: image, mask, normals and lights
    rot_mask = np.rot90(mask)
    rot_lights = rotate_z(lights, theta)
    rot_images = np.rot90(images, axes=(1, 2))
    rot_normals = rotate_z(np.rot90(normals), theta)
    # independent check of the frame: the turned image is the render of the turned scene
    np.testing.assert_allclose(rot_images, _lambertian(rot_normals, rot_mask, rot_lights), atol=1e-6)
    H, Wd = mask.shape
    for b in (3, 5):
        for interp in ("bilinear", "nearest"):
            vals, rot_vals = images[:, mask].T, rot_images[:, rot_mask].T
            got = capture_patches(vals, mask, lights, 0, len(vals), b=b, w=W, angles=[theta], interpolation=interp)[0]
            want = capture_patches(rot_vals, rot_mask, rot_lights, 0, len(rot_vals), b=b, w=W, angles=[0.0],
                                   interpolation=interp)[0]
            # stored pixel (r, c) is pixel (W - 1 - c, r) of the turned image
            rr, cc = np.nonzero(mask)
            rot_index = np.full(rot_mask.shape, -1)
            rot_index[rot_mask] = np.arange(rot_mask.sum())
            where = rot_index[Wd - 1 - cc, rr]
            assert (where >= 0).all()
            assert np.array_equal(got, want[where]), (b, interp)
            assert np.any(got[:, 0, 0] != got[:, b // 2, b // 2])  # not trivially equal cells


def test_edge_rule_zero_maps_outside_the_mask():
    mask, _, lights, images = _scene()
    values = images[:, mask].T
    rr, cc = np.nonzero(mask)
    got = capture_patches(values, mask, lights, 0, 1, b=3, w=W, angles=[0.0])[0, 0]  # the first (top) pixel
    r, c = rr[0], cc[0]
    for i in range(3):
        for j in range(3):
            y, x = r + i - 1, c + j - 1
            inside = 0 <= y < mask.shape[0] and 0 <= x < mask.shape[1] and mask[y, x]
            if inside:
                want = observation_maps(images[:, y, x][None], lights, W)[0]
                assert np.array_equal(got[i, j, 0], want)
            else:
                assert not got[i, j, 0].any()
    assert not got[0].any() and got[1, 1].any()  # the row above the top pixel is outside


def test_bilinear_cells_reproduce_a_linear_field_and_renormalise_at_the_edge():
    H, Wd, m = 9, 9, 3
    yy, xx = np.mgrid[0:H, 0:Wd].astype(np.float64)
    coef = np.array([[1.0, 0.5, 0.25], [2.0, -0.1, 0.3], [5.0, 0.2, -0.2]])  # value_j = a + b r + c col
    field = coef[:, 0, None, None] + coef[:, 1, None, None] * yy + coef[:, 2, None, None] * xx
    mask = np.ones((H, Wd), bool)
    index = np.arange(H * Wd).reshape(H, Wd)
    values = field.reshape(m, -1).T
    theta = np.radians(30.0)
    off = patch_offsets(3, [theta])
    taps, weights = neighbour_taps(index, np.array([4]), np.array([4]), off, "bilinear")
    obs, _ = gather_taps(values, taps, weights)
    pos_r, pos_c = 4 + off[0, :, 0], 4 + off[0, :, 1]
    want = coef[:, 0] + coef[:, 1] * pos_r[:, None] + coef[:, 2] * pos_c[:, None]
    np.testing.assert_allclose(obs[0], want, rtol=1e-6)  # float32 weights: 6e-8 relative each
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-6)
    # nearest: the rounded pixel, exactly
    taps_n, w_n = neighbour_taps(index, np.array([4]), np.array([4]), off, "nearest")
    obs_n, _ = gather_taps(values, taps_n, w_n)
    want_n = values[index[np.rint(pos_r).astype(int), np.rint(pos_c).astype(int)]]
    assert np.array_equal(obs_n[0], want_n.astype(np.float32))
    # at the edge: pixels outside the mask drop out, the rest renormalised
    mask[:, 5:] = False
    index_e = np.where(mask, index, -1)
    taps_e, w_e = neighbour_taps(index_e, np.array([4]), np.array([4]), patch_offsets(3, [np.radians(20.0)]))
    right = taps_e[0, 5]  # cell [1, 2]: between columns 4 and 5 -> only column 4 counts
    assert (index_e.ravel()[right[right >= 0]] % Wd == 4).all()
    np.testing.assert_allclose(w_e[0, 5].sum(), 1.0, rtol=1e-6)
    taps_0, w_0 = neighbour_taps(index_e, np.array([4]), np.array([4]), patch_offsets(3, [0.0]))
    assert (taps_0[0, 5] == -1).all() and not w_0[0, 5].any()  # column 5 is outside: no tap
    obs_0, _ = gather_taps(values, taps_0, w_0)
    assert not obs_0[0, 5].any() and np.array_equal(obs_0[0, 4], values[index[4, 4]].astype(np.float32))


def test_prediction_tile_reads_only_its_range_and_missing_observations():
    mask, _, lights, images = _scene(size=31, m=12)
    values = images[:, mask].T
    P = len(values)
    rng = np.random.default_rng(5)
    missing = rng.random(values.shape) < 0.1
    full = capture_patches(values, mask, lights, 0, P, b=5, w=W, angles=[0.0, 1.0], missing=missing)
    start, stop = P // 2, P // 2 + 9
    starts = mask_row_starts(mask)
    first, last = patch_read_range(mask, start, stop, b=5, row_starts=starts)
    assert 0 < first <= start and stop <= last < P
    assert (first, last) == patch_read_range(mask, start, stop, b=5)
    tile = capture_patches(values[first:last], mask, lights, start, stop, b=5, w=W, angles=[0.0, 1.0],
                           first=first, missing=missing[first:last], row_starts=starts)
    assert np.array_equal(tile, full[:, start:stop])
    # the pixels read: every tap of the tile's patches, any angle, lies in [first, last)
    index = np.full(mask.shape, -1)
    index[mask] = np.arange(P)
    rr, cc = np.nonzero(mask)
    for theta in np.linspace(0, 2 * np.pi, 13):
        taps, _ = neighbour_taps(index, rr[start:stop], cc[start:stop], patch_offsets(5, np.full(stop - start, theta)))
        used = taps[taps >= 0]
        assert first <= used.min() and used.max() < last
    with pytest.raises(ValueError, match="patch_read_range"):
        capture_patches(values[start:stop], mask, lights, start, stop, b=5, first=start)
    # at theta 0 a cell's missing observations are left out of its map
    p = start
    r, c = np.nonzero(mask)
    i, j = 1, 3  # offset (-1, +1)
    q = np.flatnonzero((r == r[p] - 1) & (c == c[p] + 1))[0]
    want = observation_maps(values[q][None], lights, W, light_mask=~missing[q][None])[0]
    assert np.array_equal(full[0, p, i, j, 0], want)
