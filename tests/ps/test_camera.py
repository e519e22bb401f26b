"""cnnps.ps.camera against independent references: OpenCV's own projection for the axes,
scipy's rotations for the view rotation, and a reflectance model evaluated in both frames
for the isotropy argument."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cnnps.ps import camera

K = np.array([[800.0, 0.0, 319.5], [0.0, 780.0, 241.0], [0.0, 0.0, 1.0]])


def test_view_directions_match_opencvs_projection():
    rng = np.random.default_rng(0)
    # points in front of the camera, in the capture frame (z < 0: away from the camera)
    X = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(-6, -3, 50)])
    X_cv = X @ camera.OPENCV_TO_CAPTURE.T  # the same points in OpenCV's camera axes
    uv, _ = cv2.projectPoints(X_cv, np.zeros(3), np.zeros(3), K, None)
    uv = uv[:, 0, :]
    v = camera.view_directions(K, uv[:, 1], uv[:, 0])
    np.testing.assert_allclose(v, -X / np.linalg.norm(X, axis=1, keepdims=True), atol=1e-9)
    # right of and above the principal point: the point is right (x > 0) and up (y > 0)
    right_up = camera.view_directions(K, np.array([100.0]), np.array([500.0]))[0]
    assert right_up[0] < 0 and right_up[1] < 0 and right_up[2] > 0  # seen toward the camera


def test_view_rotations_are_the_smallest_rotations_to_z():
    rng = np.random.default_rng(1)
    v = camera.view_directions(K, rng.uniform(0, 480, 200), rng.uniform(0, 640, 200))
    v = np.vstack([v, [0.0, 0.0, 1.0]])
    R = camera.view_rotations(v)
    np.testing.assert_allclose(np.einsum("pij,pj->pi", R, v), np.tile([0.0, 0.0, 1.0], (len(v), 1)), atol=1e-12)
    axis = np.cross(v, [0.0, 0.0, 1.0])
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    rotvec = np.where(norm > 0, axis / np.where(norm > 0, norm, 1), 0) * np.arccos(np.clip(v[:, 2:], -1, 1))
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    with pytest.raises(ValueError, match="face the camera"):
        camera.view_rotations(np.array([[1.0, 0.0, 0.0]]))


def _blinn_phong(n, l, v):
    """An isotropic reflectance (Lambert + Blinn-Phong), only through n.l, n.v and l.v."""
    h = (l + v) / np.linalg.norm(l + v, axis=-1, keepdims=True)
    nl = np.clip(np.sum(n * l, -1), 0, None)
    return nl * (0.6 + 0.4 * np.clip(np.sum(n * h, -1), 0, None) ** 40)


def test_rotating_to_the_view_keeps_an_isotropic_pixel_unchanged():
    rng = np.random.default_rng(2)
    v = camera.view_directions(K, np.array([10.0]), np.array([620.0]))  # a corner pixel: far off-axis
    R = camera.view_rotations(v)[0]
    n = v[0] + 0.6 * rng.normal(size=3)
    n /= np.linalg.norm(n)
    lights = rng.normal(size=(300, 3))
    lights[:, 2] = np.abs(lights[:, 2])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    original = _blinn_phong(n, lights, v[0])
    rotated = _blinn_phong(R @ n, lights @ R.T, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(rotated, original, atol=1e-12)
    assert np.ptp(original) > 0.1  # the check has something to compare


def test_point_lights_give_direction_and_inverse_square_scale():
    points = np.array([[0.0, 0.0, -5.0], [1.0, 0.0, -5.0]])
    lights = np.array([[0.0, 0.0, -3.0], [3.0, 4.0, -5.0]])
    dirs, scale = camera.point_light_directions(points, lights, np.array([2.0, 50.0]))
    np.testing.assert_allclose(dirs[0, 0], [0, 0, 1])
    np.testing.assert_allclose(dirs[0, 1], [0.6, 0.8, 0])
    np.testing.assert_allclose(scale[0], [2.0 / 4.0, 50.0 / 25.0])
    np.testing.assert_allclose(scale[1, 1], 50.0 / 20.0)
    _, rgb = camera.point_light_directions(points, lights, np.ones((2, 3)))
    assert rgb.shape == (2, 2, 3)


@pytest.mark.parametrize("bad, message", [
    (np.eye(2), "3x3"),
    ([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]], "fx > 0"),
    ([[1.0, 0, 1], [0, 1, 1], [0, 1, 1]], "rows"),
    ([[1.0, 0, np.nan], [0, 1, 1], [0, 0, 1]], "non-finite"),
])
def test_bad_intrinsics_are_named(bad, message):
    with pytest.raises(ValueError, match=message):
        camera.check_intrinsics(bad)
