"""The meshes stage: parameters, planned views and caching (the mesh library: tests/synth/test_meshes.py)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import file_sha256
from cnnps.stages import meshes
from cnnps.stages.meshes import Params, plan_views
from cnnps.synth.meshes import RADIUS, load_mesh, read_view_mesh


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


def test_stage_prunes_views_no_longer_planned_and_keeps_current_ones(tmp_path, views_data_dir):
    data = tmp_path / "data"
    shutil.copytree(views_data_dir, data)
    before = {v.name: (v / "mesh.ply").stat().st_mtime_ns for v in meshes.list_views(data)}
    assert len(before) == 2
    user = data / "meshes" / "notes"  # not a view folder: never touched
    user.mkdir()
    (user / "readme.txt").write_text("mine")
    leftover = data / "meshes" / ".proc_bowl_0-0-0123abcd.x1y2z3w4.tmp"  # a killed atomic write
    leftover.mkdir()
    meshes.run(Params(procedural=1, procedural_kinds=("bowl",), views_per_mesh=1, seed=0), data)
    after = {v.name: (v / "mesh.ply").stat().st_mtime_ns for v in meshes.list_views(data)}
    (bowl,) = [n for n in before if n.startswith("proc_bowl_")]
    assert after == {bowl: before[bowl]}  # the bowl view kept as it was, the holed one pruned
    assert (user / "readme.txt").read_text() == "mine" and not leftover.exists()


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
        posed = read_view_mesh(v)
        assert np.linalg.norm(posed.vertices, axis=1).max() == pytest.approx(RADIUS, abs=1e-6)
        if meta["kind"] == "file":
            # the posed mesh is the normalised source rotated by the recorded rotation
            base = load_mesh(src / meta["source"])
            np.testing.assert_allclose(posed.vertices, base.vertices @ np.array(meta["rotation"]).T, atol=1e-6)
            assert meta["source_sha256"] == file_sha256(src / meta["source"])
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
