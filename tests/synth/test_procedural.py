"""Procedural shapes: seeded, inside the unit sphere, and not convex."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.synth.meshes import RADIUS
from cnnps.synth.procedural import PROCEDURAL_KINDS, make_shape


def _inside_hull_fraction(mesh, depth=0.05, n=3000, seed=0):
    """Fraction of surface samples lying deeper than ``depth`` inside the convex hull (0 for a convex shape)."""
    from scipy.spatial import ConvexHull

    pts, _ = __import__("trimesh").sample.sample_surface(mesh, n, seed=seed)
    eq = ConvexHull(mesh.vertices).equations  # n.x + b <= 0 inside
    # distance to the hull boundary (in chunks: hulls of fine meshes have ~10^4 facets)
    dist = np.concatenate([-(p @ eq[:, :3].T + eq[:, 3]).max(axis=1) for p in np.array_split(pts, 10)])
    return float((dist > depth).mean())


@pytest.mark.parametrize("kind", PROCEDURAL_KINDS)
def test_same_seed_same_mesh_other_seed_other_mesh(kind):
    a, b, c = make_shape(kind, 11), make_shape(kind, 11), make_shape(kind, 12)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)


@pytest.mark.parametrize("kind", PROCEDURAL_KINDS)
def test_shapes_are_non_convex_closed_and_in_the_unit_sphere(kind):
    for seed in range(3):
        m = make_shape(kind, seed)
        assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(RADIUS, abs=1e-9)
        assert 1000 < len(m.faces) < 150_000
        assert m.is_watertight and m.is_winding_consistent
        # a convex shape has every surface point on its hull; these have a good share well inside
        assert _inside_hull_fraction(m) > 0.1, (kind, seed)
        if kind != "assembly":  # assemblies overlap: their summed volume means nothing
            assert 0 < m.volume / m.convex_hull.volume < 0.9, (kind, seed)


def test_convexity_measure_is_zero_for_a_sphere():
    import trimesh

    assert _inside_hull_fraction(trimesh.creation.icosphere(subdivisions=3)) == 0.0
    bowl = trimesh.creation.icosphere(subdivisions=3)
    bowl.vertices[bowl.vertices[:, 2] > 0.5, 2] *= -1  # push the top cap in: a dimple
    assert _inside_hull_fraction(bowl) > 0.05


def test_unknown_kind_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown procedural kind"):
        make_shape("teapot", 0)
