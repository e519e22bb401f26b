"""Observation maps: invariances, the cell rule and a brute-force reference."""

import numpy as np
import pytest

from cnnps.ps.obsmap import light_cells, observation_maps
from cnnps.ps.rotation import rotate_z

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


# -- exact arithmetic, the shared multi-configuration path, edge cases -----------------

from cnnps.ps import obsmap as obsmap_module  # noqa: E402
from cnnps.ps.obsmap import observation_maps_multi  # noqa: E402


def _brute_force_f32(I, L, w, light_mask=None):
    """Per-pixel float32 reference of the documented arithmetic: sums in image order,
    then / count, then / the map's largest cell, all in float32 (exactly reproducible)."""
    P, m = I.shape
    row, col = light_cells(L, w)
    out = np.zeros((P, w, w), np.float32)
    for p in range(P):
        acc, cnt = {}, {}
        for j in range(m):
            if light_mask is not None and not light_mask[p, j]:
                continue
            k = (row[j], col[j])
            v = max(np.float32(I[p, j]), np.float32(0.0))
            acc[k] = np.float32(acc.get(k, np.float32(0.0)) + v)
            cnt[k] = cnt.get(k, 0) + 1
        for k in acc:
            out[p][k] = np.float32(acc[k] / np.float32(cnt[k]))
        peak = out[p].max()
        if peak > 0:
            out[p] = out[p] / peak
    return out


def _reduceat_previous(I, L, w, light_mask=None):
    """The previous implementation (grouped reduceat over the light axis), kept as a
    reference: it sums a cell's lights in numpy's (pairwise) order instead of image order."""
    P, m = I.shape
    row, col = light_cells(L, w)
    cell = row * w + col
    values = np.maximum(I.astype(np.float32, copy=False), 0.0)
    if light_mask is not None:
        values = np.where(light_mask, values, 0.0)
    order = np.argsort(cell, kind="stable")
    sc = cell[order]
    starts = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]])
    sums = np.add.reduceat(values[:, order], starts, axis=1)
    if light_mask is None:
        counts = np.diff(np.r_[starts, m]).astype(np.float32)[None, :]
    else:
        counts = np.add.reduceat(light_mask[:, order].astype(np.float32), starts, axis=1)
    compact = sums / np.maximum(counts, 1.0)
    peak = compact.max(axis=1, keepdims=True)
    np.divide(compact, peak, out=compact, where=peak > 0)
    compact[(peak <= 0)[:, 0]] = 0.0
    maps = np.zeros((P, w * w), np.float32)
    maps[:, sc[starts]] = compact
    return maps.reshape(P, w, w)


def _hard_case(P, m, w, seed):
    """Random lights and intensities with a light mask, cells shared by many lights
    (w small), negative values, all-dark and fully masked-out pixels."""
    rng = np.random.default_rng(seed)
    L = _rand_lights(m, seed + 1)
    I = rng.uniform(-0.1, 1.0, (P, m)).astype(np.float32)
    I *= rng.uniform(0.0, 3.0, (P, 1)).astype(np.float32)  # per-pixel albedo spread
    I[rng.uniform(size=(P, m)) < 0.2] = 0.0  # shadows
    mask = rng.uniform(size=(P, m)) < rng.uniform(0.05, 1.0, (P, 1))
    I[1] = -0.5  # dark under every light
    mask[2] = False  # no light at all
    I[3] = 0.0
    return I, L, mask


@pytest.mark.parametrize("w, m", [(32, 300), (8, 200), (4, 1200)])
def test_exactly_the_float32_brute_force(w, m):
    I, L, mask = _hard_case(23, m, w, seed=w + m)
    row, col = light_cells(L, w)
    biggest = np.bincount(row * w + col).max()
    assert biggest >= {32: 3, 8: 8, 4: 100}[w]  # cells shared by many lights really happen
    ref = _brute_force_f32(I, L, w, mask)
    for dt in (np.float32, np.float16, np.float64):
        got = observation_maps(I, L, w, light_mask=mask, dtype=dt)
        assert got.dtype == dt and got.shape == (23, w, w)
        np.testing.assert_array_equal(got, ref.astype(dt))
    np.testing.assert_array_equal(observation_maps(I, L, w), _brute_force_f32(I, L, w))
    assert not observation_maps(I, L, w, light_mask=mask)[[1, 2, 3]].any()  # dark pixels stay 0
    # and close to the float64 reference of the rule
    got = observation_maps(I, L, w, light_mask=mask)
    np.testing.assert_allclose(got, _brute_force(I, L, w, mask), rtol=2e-6, atol=1e-7)


def test_more_than_255_lights_in_one_cell():
    I, L, mask = _hard_case(4, 3000, 4, seed=11)
    row, col = light_cells(L, 4)
    assert np.bincount(row * 4 + col).max() > 255  # counts no longer fit in uint8
    np.testing.assert_array_equal(observation_maps(I, L, 4, light_mask=mask), _brute_force_f32(I, L, 4, mask))


@pytest.mark.parametrize("m", [96, 1300])
def test_within_one_float16_step_of_the_previous_implementation(m):
    """float16 maps (what training stores) equal the previous reduceat implementation up to
    one float16 step: both round float32 sums, in different orders, and only cells of three
    or more lights can differ, by a few float32 ulps, before the float16 rounding."""
    I, L, mask = _hard_case(400, m, 32, seed=m)
    for lm in (mask, None):
        old = _reduceat_previous(I, L, 32, lm)
        new32 = observation_maps(I, L, 32, light_mask=lm)
        np.testing.assert_allclose(new32, old, rtol=1e-6, atol=0)
        a = observation_maps(I, L, 32, light_mask=lm, dtype=np.float16).view(np.int16).astype(np.int32)
        b = old.astype(np.float16).view(np.int16).astype(np.int32)
        assert np.abs(a - b).max() <= 1
        assert np.mean(a != b) < 1e-3


def test_multi_equals_one_configuration_at_a_time():
    rng = np.random.default_rng(12)
    m = 2500  # few pixels per internal block: several blocks, the last one shorter
    L = _rand_lights(m, 13)
    I = rng.uniform(-0.05, 1, (130, m)).astype(np.float32)
    mask = rng.uniform(size=(130, m)) < 0.3
    angles = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    Ls = np.stack([rotate_z(L, a) for a in angles])
    for lm in (mask, None):
        for dt in (np.float16, np.float32):
            multi = observation_maps_multi(I, Ls, W, light_mask=lm, dtype=dt)
            assert multi.shape == (7, 130, W, W) and multi.dtype == dt
            for r in range(7):
                np.testing.assert_array_equal(multi[r], observation_maps(I, Ls[r], W, light_mask=lm, dtype=dt))
    # one pixel per row of the blocks, compared with the reference
    np.testing.assert_array_equal(
        observation_maps_multi(I[:3], Ls[2:4], W, light_mask=mask[:3])[1], _brute_force_f32(I[:3], Ls[3], W, mask[:3])
    )


def test_without_opencv_gives_the_same_maps(monkeypatch):
    I, L, mask = _hard_case(40, 300, 32, seed=3)
    fast16 = observation_maps(I, L, W, light_mask=mask, dtype=np.float16)
    fast32 = observation_maps(I, L, W, light_mask=mask)
    monkeypatch.setattr(obsmap_module, "_cv2", None)
    np.testing.assert_array_equal(observation_maps(I, L, W, light_mask=mask, dtype=np.float16), fast16)
    np.testing.assert_array_equal(observation_maps(I, L, W, light_mask=mask), fast32)


def test_inputs_of_any_layout_and_dtype():
    I, L, mask = _hard_case(30, 150, 32, seed=4)
    ref = observation_maps(I, L, W, light_mask=mask)
    If = np.asfortranarray(I.astype(np.float64))
    np.testing.assert_array_equal(observation_maps(If, L, W, light_mask=np.asfortranarray(mask)), ref)
    wide = np.zeros((30, 300), np.float32)
    wide[:, ::2] = I  # a strided view
    np.testing.assert_array_equal(observation_maps(wide[:, ::2], L, W, light_mask=mask), ref)
    np.testing.assert_array_equal(observation_maps(I, L, W, light_mask=mask.astype(np.uint8)), ref)


def test_masked_out_non_finite_values_are_ignored():
    I, L, mask = _hard_case(10, 100, 32, seed=5)
    ref = observation_maps(I, L, W, light_mask=mask)
    J = I.copy()
    J[~mask] = np.nan
    J[~mask & (np.arange(100) % 2 == 0)] = np.inf
    np.testing.assert_array_equal(observation_maps(J, L, W, light_mask=mask), ref)


def test_empty_inputs():
    L = _rand_lights(5, 0)
    assert observation_maps(np.zeros((0, 5)), L, W).shape == (0, W, W)
    z = observation_maps(np.ones((3, 0)), np.zeros((0, 3)), W)
    assert z.shape == (3, W, W) and not z.any()
    assert observation_maps_multi(np.ones((2, 5)), np.zeros((0, 5, 3)), W).shape == (0, 2, W, W)
    with pytest.raises(ValueError):
        observation_maps_multi(np.ones((2, 5)), L, W)  # (m, 3) is not (R, m, 3)


@pytest.mark.parametrize("P, m, w", [(1, 40, 32), (65, 2100, 32), (17, 30, 64), (3, 7, 4)])
def test_block_edges_and_sizes(P, m, w):
    """Blocks of one pixel, a last block shorter than the others, large and tiny maps."""
    I, L, mask = _hard_case(max(P, 4), m, w, seed=P + m)
    I, mask = I[-P:], mask[-P:]
    got = observation_maps(I, L, w, light_mask=mask, dtype=np.float16)
    np.testing.assert_array_equal(got, _brute_force_f32(I, L, w, mask).astype(np.float16))
