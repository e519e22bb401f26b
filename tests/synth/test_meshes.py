"""Mesh loading, cleaning, normalisation and poses (cnnps.synth.meshes)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cnnps.infra.errors import InputError
from cnnps.synth.meshes import (
    MESH_EXTENSIONS,
    RADIUS,
    load_mesh,
    pose_mesh,
    random_rotation,
    read_view_mesh,
)


@pytest.mark.slow
@pytest.mark.shared
def test_every_shared_mesh_loads_into_the_unit_sphere(shared_meshes):
    files = sorted(p for p in shared_meshes.iterdir() if p.suffix.lower() in MESH_EXTENSIONS)
    assert len(files) >= 20
    for path in files:
        m = load_mesh(path)
        norms = np.linalg.norm(m.vertices, axis=1)
        assert norms.max() == pytest.approx(RADIUS, abs=1e-9), path.name
        lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
        np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-9, err_msg=path.name)
        assert len(m.faces) > 100 and m.area > 0, path.name
        assert m.is_winding_consistent, path.name
        if m.is_watertight:
            assert m.volume > 0, f"{path.name}: normals point inward"


def test_loaded_mesh_merges_seams_drops_bad_faces_and_points_outward(tmp_path):
    # an inside-out cube, written with a duplicate face and a degenerate face, 100 units wide
    cube = trimesh.creation.box(extents=(100, 100, 100))
    faces = np.vstack([cube.faces[:, ::-1], cube.faces[:1, ::-1], [[0, 0, 1]]])
    lines = [f"v {x} {y} {z}" for x, y, z in cube.vertices + 500] + [f"f {a+1} {b+1} {c+1}" for a, b, c in faces]
    path = tmp_path / "cube.obj"
    path.write_text("\n".join(lines) + "\n")
    m = load_mesh(path)
    assert len(m.faces) == 12
    assert m.volume > 0
    np.testing.assert_allclose(np.linalg.norm(m.vertices, axis=1), RADIUS)  # all 8 corners on the sphere


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("empty.obj", "", "empty"),
        ("garbage.ply", "this is not a ply file\n", "cannot read"),
        ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
        ("flat.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate"),
        ("mesh.xyz", "1 2 3\n", "unsupported"),
    ],
)
def test_bad_mesh_files_raise_input_error_naming_the_file(tmp_path, name, content, problem):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError) as exc:
        load_mesh(path)
    assert exc.value.path == path
    assert problem in str(exc.value)
    assert "\n" not in str(exc.value)


def test_missing_mesh_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


def test_random_rotation_is_a_seeded_uniform_rotation():
    R = random_rotation(np.random.default_rng(3))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(R, random_rotation(np.random.default_rng(3)))
    assert not np.allclose(R, random_rotation(np.random.default_rng(4)))
    # uniform on SO(3): the rotated z axis is uniform on the sphere (mean ~ 0, E[z^2] = 1/3)
    rng = np.random.default_rng(0)
    zs = np.array([random_rotation(rng)[:, 2] for _ in range(4000)])
    assert np.abs(zs.mean(axis=0)).max() < 0.05
    np.testing.assert_allclose((zs**2).mean(axis=0), 1 / 3, atol=0.03)


def test_pose_mesh_rotates_about_the_origin():
    R = random_rotation(np.random.default_rng(1))
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.2))
    posed = pose_mesh(box, R)
    np.testing.assert_allclose(posed.vertices, box.vertices @ R.T)
    np.testing.assert_allclose(np.linalg.norm(posed.vertices, axis=1), np.linalg.norm(box.vertices, axis=1))
    assert posed is not box and np.array_equal(box.vertices, trimesh.creation.box(extents=(1.0, 0.5, 0.2)).vertices)


def test_read_view_mesh_reads_the_posed_file_as_written(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.2))
    posed = pose_mesh(box, random_rotation(np.random.default_rng(2)))
    (tmp_path / "v").mkdir()
    posed.export(str(tmp_path / "v" / "mesh.ply"), encoding="binary")
    back = read_view_mesh(tmp_path / "v")
    np.testing.assert_allclose(back.vertices, posed.vertices, atol=1e-6)  # no re-centring or scaling
    np.testing.assert_array_equal(back.faces, posed.faces)
    with pytest.raises(InputError, match="run the meshes stage"):
        read_view_mesh(tmp_path / "absent")
