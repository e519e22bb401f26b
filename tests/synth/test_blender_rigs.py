"""The Blender renderer's pinhole camera and point lights (cnnps.synth.blender),
checked against analytic references on a unit sphere: silhouette, normals and depth from
rays through the pixel centres of the camera's K, and Lambertian shading max(0, n.l) / r^2."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.ps.camera import pixel_rays
from tests.support.tiny_scenes import THREADS
from tests.support.tiny_scenes import sphere as _sphere

pytest.importorskip("trimesh")

S = 64
FOV = 40.0
CAM = np.array([0.0, 0.0, 5.0])  # the camera's optical centre, world frame


def _expected_K(size, fov_deg):
    """OpenCV K written out independently: focal length from the field of view across
    the image width, principal point at the centre, (0, 0) the centre of the top-left pixel."""
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    c = (size - 1) / 2
    return np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])


def _sphere_hits(K, size, radius=1.0):
    """Analytic ray casting onto a sphere at the world origin from CAM: (hit mask (S,S),
    world points (S,S,3), depth along the optical axis (S,S), unit normals (S,S,3))."""
    rows, cols = np.mgrid[0:size, 0:size]
    d = pixel_rays(K, rows.ravel(), cols.ravel())  # capture frame, z = -1
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    b = u @ CAM  # |CAM + t u|^2 = radius^2
    disc = b**2 - (CAM @ CAM - radius**2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    X = CAM + t[:, None] * u
    depth = CAM[2] - X[:, 2]
    n = X / radius
    return hit.reshape(size, size), X.reshape(size, size, 3), depth.reshape(size, size), n.reshape(size, size, 3)


def _boundary(mask):
    """Pixels of ``mask`` or its complement that touch the other (4-neighbours)."""
    m = np.pad(mask, 1, mode="edge")
    inner = m[1:-1, 1:-1]
    edge = np.zeros_like(inner)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        edge |= inner != m[1 + dr : 1 + dr + mask.shape[0], 1 + dc : 1 + dc + mask.shape[1]]
    return edge


def test_camera_spec_is_checked_before_blender_is_needed():
    from cnnps.synth.blender import BlenderRenderer

    for bad in ({"fov_deg": 0}, {"fov_deg": 180.0}, {"fov_deg": "40"}, {"fov": 40}, {"fov_deg": 40, "shift": 1}):
        with pytest.raises(ConfigError, match="camera"):
            BlenderRenderer(8, samples=1, camera=bad)


@pytest.mark.blender
def test_pinhole_sphere_geometry_depth_and_point_light_match_analytic():
    from cnnps.synth.blender import POINT_POWER, BlenderRenderer

    mesh = _sphere(1.0)
    light = np.array([1.5, 1.0, 3.0])  # world frame
    sun = np.array([0.3, 0.2, 1.0])
    with BlenderRenderer(S, samples=4, threads=THREADS, seed=0, camera={"fov_deg": FOV}) as r:
        r.load_scene(mesh.vertices, mesh.faces, {"bsdf": "lambertian", "Color": 1.0})
        K = _expected_K(S, FOV)
        np.testing.assert_allclose(r.intrinsics(), K, rtol=1e-12)
        np.testing.assert_array_equal(r.camera_origin, CAM)
        mask, normal = r.render_geometry()
        depth = r.render_depth()
        sun_before = r.render(sun)
        img = r.render_point(light, 1.0)
        sun_after = r.render(sun)
        assert r.renders == 3 and POINT_POWER == pytest.approx(4 * math.pi**2)

    hit, X, depth_ref, n_ref = _sphere_hits(K, S)
    # silhouette: the analytic one, but for a few pixels on its boundary
    wrong = mask != hit
    assert hit.sum() > 900 and wrong.sum() <= 12 and not (wrong & ~_boundary(hit)).any(), wrong.sum()
    both = mask & hit & ~_boundary(hit)
    # normals: Blender's smooth shading normals vs the sphere's, at the same pixel rays
    cos = np.clip(np.sum(normal[both] * n_ref[both], axis=1), -1, 1)
    angle = np.degrees(np.arccos(cos))
    assert angle.mean() < 1.0 and angle.max() < 3.0, (angle.mean(), angle.max())
    # depth along the optical axis (5 - z): NaN outside the mask
    assert np.isnan(depth[~mask]).all() and np.isfinite(depth[mask]).all()
    rel = np.abs(depth[both] / depth_ref[both] - 1)
    assert np.median(rel) < 1e-3 and rel.max() < 5e-3, (np.median(rel), rel.max())
    # a depth half a pixel off in the principal point would be far worse than 1e-3:
    # the pixel-centre mapping is what these depths pin down
    K_off = K.copy()
    K_off[:2, 2] += 0.5
    _, _, depth_off, _ = _sphere_hits(K_off, S)
    ok = both & np.isfinite(depth_off) & _sphere_hits(K_off, S)[0]
    assert np.median(np.abs(depth[ok] / depth_off[ok] - 1)) > 3 * np.median(rel)
    # point light of unit radiant intensity: Lambertian max(0, n.l) / r^2 (a convex
    # object, so only attached shadows; a single point light gives no Monte Carlo noise
    # in direct light, and indirect rays leave into a black world)
    L = light - X
    dist = np.linalg.norm(L, axis=-1)
    ndl = np.sum(n_ref * L, axis=-1) / dist
    ref = np.maximum(ndl, 0) / dist**2
    lit = both & (ndl > 0.1)
    assert lit.sum() > 450
    assert (img[lit] >= 0).all() and np.allclose(img[..., 0], img[..., 2])
    ratio = img[lit][:, 0] / ref[lit]
    assert abs(np.median(ratio) - 1) < 0.02 and np.percentile(np.abs(ratio - 1), 90) < 0.03, np.median(ratio)
    assert (img[both & (ndl < -0.05)] == 0).all()  # attached shadow: black
    # the sun stays off under the point light and the point light off under the sun
    np.testing.assert_array_equal(sun_before, sun_after)
    assert (sun_before[mask & ~_boundary(mask)].sum(axis=-1) > 0).mean() > 0.5


@pytest.mark.blender
def test_orthographic_depth_is_five_minus_z():
    """The default camera: depth along the optical axis is 5 - z of the hemisphere that
    faces it, at the pixel centres x = -1 + (c + .5) 2/S, y = 1 - (r + .5) 2/S."""
    from cnnps.synth.blender import BlenderRenderer

    s, radius = 32, 0.9
    with BlenderRenderer(s, samples=1, threads=THREADS, seed=0) as r:
        r.load_scene(_sphere(radius).vertices, _sphere(radius).faces)
        mask, _ = r.render_geometry()
        depth = r.render_depth()
        with pytest.raises(ValueError, match="orthographic"):
            r.intrinsics()
    c = (np.arange(s) + 0.5) * 2.0 / s - 1.0
    x, y = np.meshgrid(c, -c)
    rho2 = x**2 + y**2
    inside = mask & (rho2 < (0.95 * radius) ** 2)
    ref = 5.0 - np.sqrt(radius**2 - rho2[inside])
    assert inside.sum() > 400 and np.isnan(depth[~mask]).all()
    np.testing.assert_allclose(depth[inside], ref, rtol=2e-3)
