"""The meshes stage: loading, normalisation, poses, views and caching."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import trimesh

from cnnps.core.errors import ConfigError, InputError
from cnnps.stages import meshes
from cnnps.stages.meshes import RADIUS, Params, load_mesh, plan_views, pose_mesh, random_rotation


@pytest.mark.slow
@pytest.mark.shared
def test_every_shared_mesh_loads_into_the_unit_sphere(shared_meshes):
    files = sorted(p for p in shared_meshes.iterdir() if p.suffix.lower() in meshes.MESH_EXTENSIONS)
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


def test_pose_mesh_rotates_about_the_origin(sphere_mesh):
    R = random_rotation(np.random.default_rng(1))
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.2))
    posed = pose_mesh(box, R)
    np.testing.assert_allclose(posed.vertices, box.vertices @ R.T)
    np.testing.assert_allclose(np.linalg.norm(posed.vertices, axis=1), np.linalg.norm(box.vertices, axis=1))
    assert posed is not box and np.array_equal(box.vertices, trimesh.creation.box(extents=(1.0, 0.5, 0.2)).vertices)


def test_params_validation(tmp_path):
    with pytest.raises(ConfigError, match="nothing to do"):
        Params()
    with pytest.raises(ConfigError, match="views_per_mesh"):
        Params(procedural=1, views_per_mesh=0)
    with pytest.raises(ConfigError, match="unknown kind"):
        Params(procedural=1, procedural_kinds=("cube",))
    with pytest.raises(ConfigError, match="extensions"):
        Params(mesh_dir=str(tmp_path), extensions=(".fbx",))
    assert Params(mesh_dir=str(tmp_path), extensions=["OBJ"]).extensions == (".obj",)


def test_missing_mesh_folder_is_a_config_error_before_any_work(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        meshes.run(Params(mesh_dir=str(tmp_path / "absent"), procedural=2), tmp_path / "data")
    assert not (tmp_path / "data").exists()


def _src(tmp_path, shared_meshes, names):
    src = tmp_path / "src"
    src.mkdir(exist_ok=True)
    for n in names:
        shutil.copy(shared_meshes / n, src / n)
    return src


@pytest.mark.shared
def test_stage_writes_posed_views_and_caches_by_content(tmp_path, shared_meshes):
    src = _src(tmp_path, shared_meshes, ["bumpy.off", "spot_low_resolution.obj"])
    data = tmp_path / "data"
    params = Params(mesh_dir=str(src), procedural=1, procedural_kinds=("blob",), views_per_mesh=2, seed=5)
    meshes.run(params, data)
    views = meshes.list_views(data)
    assert len(views) == 6
    for v in views:
        meta = json.loads((v / "view.json").read_text())
        assert v.name == meta["view_id"] and v.name.endswith(meta["key"][:8])
        posed = meshes.read_view_mesh(v)
        assert np.linalg.norm(posed.vertices, axis=1).max() == pytest.approx(RADIUS, abs=1e-6)
        if meta["kind"] == "file":
            # the posed mesh is the normalised source rotated by the recorded rotation
            base = load_mesh(src / meta["source"])
            np.testing.assert_allclose(posed.vertices, base.vertices @ np.array(meta["rotation"]).T, atol=1e-6)
            assert meta["source_sha256"] == meshes.file_sha256(src / meta["source"])
    rotations = [json.loads((v / "view.json").read_text())["rotation"] for v in views]
    assert len({json.dumps(r) for r in rotations}) == 6  # every view its own pose

    # rerun: nothing rewritten
    mtimes = {v.name: (v / "mesh.ply").stat().st_mtime_ns for v in views}
    meshes.run(params, data)
    assert {v.name: (v / "mesh.ply").stat().st_mtime_ns for v in meshes.list_views(data)} == mtimes

    # adding a mesh only adds its views; the others keep their ids and files
    shutil.copy(shared_meshes / "torus.obj", src / "torus.obj")
    meshes.run(params, data)
    after = {v.name: (v / "mesh.ply").stat().st_mtime_ns for v in meshes.list_views(data)}
    assert len(after) == 8 and all(after[k] == t for k, t in mtimes.items())

    # removing one prunes its views
    (src / "bumpy.off").unlink()
    meshes.run(params, data)
    names = [v.name for v in meshes.list_views(data)]
    assert len(names) == 6 and not any(n.startswith("bumpy-") for n in names)


@pytest.mark.shared
def test_view_ids_depend_on_seed_and_content_not_on_file_order(tmp_path, shared_meshes):
    src = _src(tmp_path, shared_meshes, ["bumpy.off", "torus.obj"])
    a = {v.view_id for v in plan_views(Params(mesh_dir=str(src), seed=0))}
    b = {v.view_id for v in plan_views(Params(mesh_dir=str(src), seed=1))}
    assert len(a) == 2 and not a & b
    (src / "aaa.obj").write_text((src / "torus.obj").read_text() + "# a copy\n")  # sorts first
    c = {v.view_id for v in plan_views(Params(mesh_dir=str(src), seed=0))}
    assert a < c and len(c) == 3
