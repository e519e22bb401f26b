"""Least-squares Lambertian photometric stereo on analytic scenes."""

import numpy as np
import pytest

from cnnps.ps.least_squares import least_squares
from cnnps.ps.metrics import angular_error_deg
from tests.support.synthetic import random_lights, shading, sphere_normals


def _sphere_scene(m=40, seed=0, max_tilt_deg=60.0, size=48):
    normals, mask = sphere_normals(size)
    L = random_lights(m, seed, max_tilt_deg)
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 1.0, mask.sum())
    n = normals[mask]
    I = albedo[:, None] * shading(normals, L)[:, mask].T  # (P, m), shadows clipped at 0
    return n, albedo, I, L


def test_no_shadows_one_pseudo_inverse_is_exact():
    # lights within 20 deg of z and normals within ~45 deg of z: nothing is in shadow
    n, albedo, I, L = _sphere_scene(max_tilt_deg=20)
    keep = n[:, 2] > 0.72
    n, albedo, I = n[keep], albedo[keep], I[keep]
    assert np.all(I > 0)
    N, rho = least_squares(I, L)
    assert angular_error_deg(N, n).max() < 0.01
    np.testing.assert_allclose(rho, albedo, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(N, axis=1), 1.0, rtol=1e-12)


def test_attached_shadows_need_the_threshold():
    n, albedo, I, L = _sphere_scene(max_tilt_deg=70)
    assert (I == 0).mean() > 0.05  # the scene really has attached shadows
    N_plain, _ = least_squares(I, L)
    assert angular_error_deg(N_plain, n).max() > 1.0  # the plain fit is biased there
    N, rho, valid = least_squares(I, L, shadow_threshold=0.0, return_valid=True)
    assert valid.mean() > 0.95
    assert angular_error_deg(N[valid], n[valid]).max() < 0.01
    np.testing.assert_allclose(rho[valid], albedo[valid], rtol=1e-6)


def test_relative_threshold_is_independent_of_albedo_and_exposure():
    n, albedo, I, L = _sphere_scene(max_tilt_deg=70)
    N1, rho1 = least_squares(I, L, shadow_threshold=0.1)
    N2, rho2 = least_squares(I * 37.0, L, shadow_threshold=0.1)
    np.testing.assert_allclose(N1, N2, atol=1e-12)
    np.testing.assert_allclose(rho2, 37.0 * rho1, rtol=1e-9)


def test_pixels_with_too_few_lights_fall_back_and_are_flagged():
    L = random_lights(6, seed=3, max_tilt_deg=50)
    n = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 0.9]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    I = np.maximum(n @ L.T, 0)
    I[1, 2:] = 0.0  # pixel 1: only two lit lights
    N, rho, valid = least_squares(I, L, shadow_threshold=0.0, return_valid=True)
    assert valid.tolist() == [True, False]
    assert angular_error_deg(N[0], n[0]) < 1e-6
    N_all, rho_all = least_squares(I, L)
    np.testing.assert_allclose(N[1], N_all[1])  # fallback = all-lights solution
    dark, _, v = least_squares(np.zeros((1, 6)), L, shadow_threshold=0.0, return_valid=True)
    assert not v[0] and np.all(dark == 0)


def test_chunked_solution_matches(monkeypatch):
    import cnnps.ps.least_squares as lam

    n, albedo, I, L = _sphere_scene(max_tilt_deg=70)
    ref = least_squares(I, L, shadow_threshold=0.05)
    monkeypatch.setattr(lam, "_CHUNK", 97)
    out = least_squares(I, L, shadow_threshold=0.05)
    np.testing.assert_allclose(out[0], ref[0], atol=1e-12)


def test_bad_arguments():
    L = random_lights(5)
    with pytest.raises(ValueError):
        least_squares(np.ones((3, 4)), L)
    with pytest.raises(ValueError):
        least_squares(np.ones((3, 5)), L, shadow_threshold=1.0)
    coplanar = np.array([[1, 0, 0], [0, 1, 0], [0.6, 0.8, 0], [-1, 0, 0]], float)
    with pytest.raises(ValueError, match="coplanar"):
        least_squares(np.ones((2, 4)), coplanar)
