"""Rotations about z and test-time rotation averaging."""

import numpy as np
import pytest

from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.rotation import (
    average_rotated_predictions,
    normalize,
    rotate_z,
    rotation_angles,
    rotation_z,
)


def _normals(P=500, seed=0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(P, 3))
    n[:, 2] = np.abs(n[:, 2])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_rotate_z_quarter_turn_is_counter_clockwise():
    x, y, z = np.eye(3)
    np.testing.assert_allclose(rotate_z(x, np.pi / 2), y, atol=1e-15)
    np.testing.assert_allclose(rotate_z(y, np.pi / 2), -x, atol=1e-15)
    np.testing.assert_allclose(rotate_z(z, 1.234), z)


def test_rotate_z_matches_matrix_and_inverts():
    n = _normals()
    for theta in (0.3, -2.0, np.pi):
        np.testing.assert_allclose(rotate_z(n, theta), n @ rotation_z(theta).T, atol=1e-14)
        np.testing.assert_allclose(rotate_z(rotate_z(n, theta), -theta), n, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(rotate_z(n, 0.7), axis=1), 1.0)


def test_rotate_z_per_vector_angles():
    n = _normals(20)
    th = np.linspace(0, 3, 20)
    out = rotate_z(n, th)
    for i in range(20):
        np.testing.assert_allclose(out[i], rotate_z(n[i], th[i]), atol=1e-14)


def test_rotation_angles():
    a = rotation_angles(10)
    np.testing.assert_allclose(np.degrees(a), np.arange(10) * 36.0)
    assert rotation_angles(1).tolist() == [0.0]
    with pytest.raises(ValueError):
        rotation_angles(0)


def test_normalize_keeps_zero_vectors():
    v = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(normalize(v), [[0.6, 0.8, 0.0], [0, 0, 0]])


def test_average_is_exact_for_an_equivariant_predictor():
    n = _normals()
    angles = rotation_angles(10)
    preds = np.stack([rotate_z(n, a) for a in angles])  # predictor on rotated lights
    out = average_rotated_predictions(preds, angles)
    assert angular_error_deg(out, n).max() < 1e-6
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-12)


def test_average_reduces_noise_of_an_equivariant_predictor():
    rng = np.random.default_rng(1)
    n = _normals(2000)
    angles = rotation_angles(10)
    preds = np.stack([normalize(rotate_z(n, a) + rng.normal(0, 0.05, n.shape)) for a in angles])
    single = angular_error_deg(rotate_z(preds[3], -angles[3]), n).mean()
    averaged = angular_error_deg(average_rotated_predictions(preds, angles), n).mean()
    assert averaged < 0.5 * single


def test_a_predictor_ignoring_rotation_does_not_pass():
    n = _normals()
    angles = rotation_angles(10)
    preds = np.stack([n for _ in angles])  # ignores the rotated lights
    out = average_rotated_predictions(preds, angles)
    tilted = n[:, 2] < 0.9
    assert angular_error_deg(out[tilted], n[tilted]).min() > 20
    # undoing the rotation with the wrong sign is also caught
    preds = np.stack([rotate_z(n, -a) for a in angles])
    out = average_rotated_predictions(preds, angles)
    assert angular_error_deg(out[tilted], n[tilted]).min() > 20


def test_average_checks_shapes():
    with pytest.raises(ValueError):
        average_rotated_predictions(np.zeros((3, 5, 3)), rotation_angles(4))
