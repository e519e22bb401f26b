"""Per-pixel confidence measures against independent computations."""

from __future__ import annotations

import numpy as np

from cnnps.ps.confidence import (
    lambertian_residual,
    least_squares_confidence,
    lit,
    lit_condition,
    lit_share,
    network_confidence,
)


def _lights(m, rng):
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.3
    return L / np.linalg.norm(L, axis=1, keepdims=True)


def test_lit_condition_is_the_singular_value_ratio_of_the_used_lights():
    rng = np.random.default_rng(0)
    L = _lights(20, rng)
    use = rng.random((50, 20)) < 0.4
    use[0] = False
    use[1, :2] = True
    use[1, 2:] = False  # two lights: rank 2
    got = lit_condition(L, use)
    for i in range(50):
        s = np.linalg.svd(L[use[i]], compute_uv=False) if use[i].sum() else np.zeros(3)
        want = s[2] / s[0] if len(s) == 3 and s[0] > 0 else 0.0
        assert abs(got[i] - want) < 1e-6, i
    per_pixel = np.broadcast_to(L, (50, 20, 3))
    assert np.allclose(lit_condition(per_pixel, use), got, atol=1e-9)


def test_the_residual_is_zero_for_lambertian_values_and_grows_with_a_highlight():
    rng = np.random.default_rng(1)
    L = _lights(30, rng)
    n = _lights(40, rng)
    albedo = rng.uniform(0.2, 0.9, 40)
    I = albedo[:, None] * np.clip(n @ L.T, 0, None)
    use = lit(I, None)
    assert np.all(lambertian_residual(I, L, n, albedo, use) < 1e-12)
    J = I.copy()
    J[:, 0] += 0.5  # a highlight under one light
    r = lambertian_residual(J, L, n, albedo, np.ones_like(use))
    for i in range(40):  # the formula, pixel by pixel
        want = np.linalg.norm(J[i] - albedo[i] * np.clip(L @ n[i], 0, None)) / np.linalg.norm(J[i])
        assert abs(r[i] - want) < 1e-12


def test_lit_leaves_out_missing_and_dark_observations():
    I = np.array([[1.0, 0.01, 0.5, 0.9], [0.0, 0.0, 0.0, 0.0]])
    missing = np.array([[False, False, False, True], [False] * 4])
    assert lit(I, missing).tolist() == [[True, False, True, False], [False] * 4]
    assert lit_share(I, missing).tolist() == [2 / 3, 0.0]


def test_confidences_fall_as_their_measures_grow():
    spread = np.array([0.5, 1.0, 2.0, 4.0])
    c = network_confidence(spread, np.ones(4))
    assert np.all(np.diff(c) < 0) and np.all((c > 0) & (c <= 1))
    assert network_confidence(np.array([2.0]), np.array([0.5]))[0] < network_confidence(np.array([2.0]),
                                                                                       np.array([1.0]))[0]
    assert np.all(np.diff(least_squares_confidence(np.array([0.0, 0.1, 0.5, 1.5]))) <= 0)
