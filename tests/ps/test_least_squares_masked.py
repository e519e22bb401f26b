"""Least squares that leave missing (saturated) observations out."""

import numpy as np
import pytest

from cnnps.ps.least_squares import least_squares, least_squares_masked
from cnnps.ps.metrics import angular_error_deg
from tests.support.synthetic import random_lights, shading, sphere_normals


def _clipped_scene(m=30, seed=0, level=0.7):
    normals, mask = sphere_normals(40)
    L = random_lights(m, seed, 45)
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.5, 1.0, mask.sum())
    n = normals[mask]
    I = albedo[:, None] * shading(normals, L)[:, mask].T  # (P, m)
    missing = I >= level
    return n, albedo, np.minimum(I, level), L, missing


def test_nothing_missing_is_least_squares_exactly():
    n, _, I, L, _ = _clipped_scene()
    for t in (None, 0.0, 0.1):
        want = least_squares(I, L, shadow_threshold=t, return_valid=True)
        for missing in (None, np.zeros(I.shape, bool)):
            got = least_squares_masked(I, L, missing, shadow_threshold=t, return_valid=True)
            for a, b in zip(got, want):
                np.testing.assert_array_equal(a, b)


def test_missing_observations_are_left_out():
    n, albedo, I, L, missing = _clipped_scene()
    assert missing.any(axis=1).mean() > 0.2  # many pixels clipped
    N, rho, valid = least_squares_masked(I, L, missing, shadow_threshold=0.0, return_valid=True)
    ok = valid
    assert ok.mean() > 0.97
    assert angular_error_deg(N[ok], n[ok]).max() < 1e-4  # the clipped values did not count (arccos rounding)
    np.testing.assert_allclose(rho[ok], albedo[ok], rtol=1e-9)
    # with the clipped values counted, the fit is wrong where they are
    N_kept, _ = least_squares(I, L, shadow_threshold=0.0)
    assert angular_error_deg(N_kept, n)[missing.any(axis=1)].mean() > 1.0
    # a missing value may be NaN: it is never looked at while enough lights remain
    I_nan = np.where(missing, np.nan, I)
    N2, _, valid2 = least_squares_masked(I_nan, L, missing, shadow_threshold=0.0, return_valid=True)
    np.testing.assert_allclose(N2[valid2], N[valid2], atol=1e-12)


def test_against_per_pixel_lstsq_without_threshold():
    n, _, I, L, missing = _clipped_scene(level=0.8)
    N, _, valid = least_squares_masked(I, L, missing, return_valid=True)
    rows = np.flatnonzero(missing.any(axis=1))[:50]
    for p in rows:
        use = ~missing[p]
        b = np.linalg.lstsq(L[use], I[p, use], rcond=None)[0]
        np.testing.assert_allclose(N[p], b / np.linalg.norm(b), atol=1e-9)


def test_too_few_lights_fall_back_and_are_not_valid():
    L = random_lights(6, 1, 40)
    n = np.array([0.0, 0.0, 1.0])
    I = np.tile(L @ n, (3, 1))
    missing = np.zeros(I.shape, bool)
    missing[0, :4] = True  # 2 lights left: under-determined
    missing[1, 0] = True  # 5 left: fine
    N, rho, valid = least_squares_masked(I, L, missing, return_valid=True)
    assert valid.tolist() == [False, True, True]
    # the fallback uses the stored values of the missing observations
    np.testing.assert_allclose(N[0], least_squares(I[:1], L)[0][0], atol=1e-12)
    np.testing.assert_allclose(N[1], n, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        least_squares_masked(I, L, missing[:, :3])
