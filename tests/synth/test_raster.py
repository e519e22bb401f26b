"""The orthographic rasteriser (cnnps.synth.raster): pixel centres, first hits, normals, flip rule."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cnnps.synth.raster import pixel_centres, rasterize, rasterize_full


@pytest.fixture(scope="module")
def sphere_mesh():
    """A well-tessellated sphere of radius 0.9 at the origin (icosphere, 20480 faces)."""
    return trimesh.creation.icosphere(subdivisions=5, radius=0.9)


def _angles_deg(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def test_pixel_centres_follow_the_frame():
    x, y = pixel_centres(4)
    np.testing.assert_allclose(x, [-0.75, -0.25, 0.25, 0.75])
    np.testing.assert_allclose(y, [0.75, 0.25, -0.25, -0.75])  # row 0 on top


def test_rasterized_sphere_matches_the_analytic_sphere(sphere_mesh):
    S, r = 128, 0.9
    mask, normal = rasterize(sphere_mesh, S)
    x, y = pixel_centres(S)
    X, Y = np.meshgrid(x, y)
    rho2 = (X**2 + Y**2) / r**2
    # the inscribed polyhedron is a hair smaller than the sphere: only rim pixels may differ
    assert np.array_equal(mask[rho2 < 0.99], np.ones((rho2 < 0.99).sum(), bool))
    assert not mask[rho2 > 1].any()
    gt = np.dstack([X / r, Y / r, np.sqrt(np.clip(1 - rho2, 0, 1))])
    inner = mask & (rho2 < 0.95)
    err = _angles_deg(normal[inner], gt[inner])
    assert err.mean() < 0.5 and err.max() < 1.5
    np.testing.assert_allclose(np.linalg.norm(normal[mask], axis=1), 1, atol=1e-5)
    assert not normal[~mask].any()
    assert normal.dtype == np.float32 and mask.dtype == bool


def test_first_hit_wins():
    # small sphere in front (z = +0.5) of a large one: the front one is seen where they overlap
    front = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    front.apply_translation((0.0, 0.0, 0.5))
    back = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    r = rasterize_full(trimesh.util.concatenate([back, front]), 64)
    x, y = pixel_centres(64)
    X, Y = np.meshgrid(x, y)
    centre = X**2 + Y**2 < 0.25**2
    np.testing.assert_allclose(r.depth[centre], 0.5 + np.sqrt(0.09 - X[centre] ** 2 - Y[centre] ** 2), atol=2e-3)
    n_front = len(back.faces)  # concatenate keeps the order: the front sphere's faces come last
    assert (r.face[centre] >= n_front).all()
    ring = (X**2 + Y**2 > 0.35**2) & (X**2 + Y**2 < 0.55**2)  # only the large sphere there
    assert r.mask[ring].all() and (r.face[ring] < n_front).all()


def test_inside_out_sphere_shows_its_back_faces_flipped_to_face_the_camera():
    """An inverted sphere (every face wound backwards): its vertex normals point inward,
    the front hemisphere is hit from behind, and the flip rule negates the interpolated
    normal, so the result is minus the analytic inward normal -(x, y, z)/r."""
    S, r = 64, 0.6
    inv = trimesh.creation.icosphere(subdivisions=4, radius=r)
    inv.invert()
    raster = rasterize_full(inv, S)
    x, y = pixel_centres(S)
    X, Y = np.meshgrid(x, y)
    rho2 = (X**2 + Y**2) / r**2
    inner = rho2 < 0.95
    assert raster.mask[inner].all() and not raster.mask[rho2 > 1].any()
    inward = -np.dstack([X / r, Y / r, np.sqrt(np.clip(1 - rho2, 0, 1))])
    err = _angles_deg(raster.normal[inner], -inward[inner])
    # Tolerance from the geometry, not from a measurement: subdivision 4 has edges of
    # ~4.3 deg, so a face lies up to r(1 - cos(4.3 deg / sqrt 3)) ~ 0.001 r inside the sphere;
    # the hit below the sphere point turns the interpolated (radial) normal by at most
    # 0.001 tan(theta) rad ~ 0.25 deg at the rim of `inner` (sin theta < 0.975), and
    # trimesh's angle-weighted vertex normals of the icosphere deviate from radial by
    # 0.15 deg: 0.4 deg at most (measured 0.30). Plain float64 arithmetic: no dependence
    # on threads or load.
    assert err.max() < 0.5 and err.mean() < 0.1
    # the depth is the front hemisphere's (the first hit), not the back one's: faces lie
    # up to 0.001 r inside the sphere, i.e. 0.001 r / cos(theta) < 0.0045 r below it along z
    np.testing.assert_allclose(raster.depth[inner], r * np.sqrt(1 - rho2[inner]), atol=5e-3 * r)
    # the same pixels and normals as the sphere the right way round
    outward = rasterize_full(trimesh.creation.icosphere(subdivisions=4, radius=r), S)
    np.testing.assert_array_equal(raster.mask, outward.mask)
    np.testing.assert_allclose(raster.normal, outward.normal, atol=1e-6)


def test_open_mesh_seen_from_behind_is_flipped():
    """One triangle wound clockwise as seen from the camera (geometric normal -z): its
    normal is negated to +z, as Cycles shades back-facing hits."""
    tri = trimesh.Trimesh([[-0.5, -0.5, 0.0], [0.0, 0.5, 0.0], [0.5, -0.5, 0.0]], [[0, 1, 2]], process=False)
    assert tri.face_normals[0, 2] < 0
    mask, n = rasterize(tri, 16)
    assert mask.sum() > 20
    np.testing.assert_allclose(n[mask], np.tile([0.0, 0.0, 1.0], (int(mask.sum()), 1)), atol=1e-6)


def test_large_mesh_is_rasterised_in_chunks_like_a_small_one(monkeypatch):
    """327 680 faces at 256 x 256 (several chunks of candidate pairs) give the analytic
    disk and normals; forcing many more, smaller chunks changes nothing (no time bound:
    speed is a benchmark's business, not a test's)."""
    from cnnps.synth import raster as raster_mod

    S, r = 256, 0.9
    big = trimesh.creation.icosphere(subdivisions=7, radius=r)  # 327 680 faces
    a = rasterize_full(big, S)
    x, y = pixel_centres(S)
    X, Y = np.meshgrid(x, y)
    rho2 = (X**2 + Y**2) / r**2
    assert a.mask[rho2 < 0.999].all() and not a.mask[rho2 > 1].any()
    inner = rho2 < 0.95
    gt = np.dstack([X / r, Y / r, np.sqrt(np.clip(1 - rho2, 0, 1))])
    # edges 8x shorter than subdivision 4's: the 0.4 deg bound argued for it shrinks ~64x (0.2: ample)
    assert _angles_deg(a.normal[inner], gt[inner]).max() < 0.2
    monkeypatch.setattr(raster_mod, "_CHUNK", 1 << 16)
    b = rasterize_full(big, S)
    np.testing.assert_array_equal(a.face, b.face)
    np.testing.assert_array_equal(a.normal, b.normal)
