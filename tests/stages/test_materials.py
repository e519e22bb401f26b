"""The materials stage: parameters, scene keys, caching and pruning (the library: tests/synth/)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cnnps.core.errors import ConfigError
from cnnps.stages import materials
from cnnps.stages.materials import Params
from cnnps.synth import bsdf
from cnnps.synth.meshes import read_view_mesh
from cnnps.synth.raster import rasterize


def test_params_validation():
    with pytest.raises(ConfigError, match="unknown category"):
        Params(categories=("plastic",))
    with pytest.raises(ConfigError, match="size"):
        Params(size=4)
    with pytest.raises(ConfigError, match="superpixels"):
        Params(superpixels=0)
    with pytest.raises(ConfigError, match="lo 0.9 > hi 0.1"):
        Params(ranges={"metallic": {"roughness": [0.9, 0.1]}})
    p = Params(categories=["Diffuse", "METALLIC"], ranges={"specular": {"specular": [0, 2]}})
    assert p.categories == ("diffuse", "metallic") and p.ranges.specular.specular == (0, 2)


def test_no_views_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="run the meshes stage"):
        materials.run(Params(), tmp_path / "data")


def test_scene_keys_change_only_for_the_changed_category(tmp_path):
    base = Params(size=32, superpixels=20)
    changed = Params(size=32, superpixels=20, ranges={"specular": {"specular": [0, 2]}})
    for cat in bsdf.CATEGORIES:
        same = materials.scene_key("view", cat, base) == materials.scene_key("view", cat, changed)
        assert same == (cat != "specular")
    assert materials.scene_key("view", "diffuse", base) != materials.scene_key("view", "diffuse", Params(size=64, superpixels=20))
    assert materials.scene_key("view", "diffuse", base) != materials.scene_key("other", "diffuse", base)


def test_stage_writes_scenes_and_redoes_only_changed_ones(tmp_path, views_data_dir):
    data = tmp_path / "data"
    shutil.copytree(views_data_dir, data)
    params = Params(size=48, superpixels=60, seed=2)
    materials.run(params, data)
    scenes = sorted(p for p in (data / "materials").iterdir())
    assert len(scenes) == 6 and all(p.name.rsplit("-", 1)[1] in bsdf.CATEGORIES for p in scenes)
    for s in scenes:
        meta = json.loads((s / "material.json").read_text())
        view = data / "meshes" / meta["view_id"]
        assert s.name == f"{view.name}-{meta['category']}"
        mask, normal = rasterize(read_view_mesh(view), 48)
        np.testing.assert_array_equal(np.load(s / "normal.npy"), normal)
        assert (np.load(s / "labels.npy") >= 0).sum() == mask.sum() > 200
    mtimes = {s.name: (s / "material.json").stat().st_mtime_ns for s in scenes}
    materials.run(Params(size=48, superpixels=60, seed=2, ranges={"specular": {"specular": [0, 2]}}), data)
    after = {s.name: (s / "material.json").stat().st_mtime_ns for s in (data / "materials").iterdir()}
    assert after.keys() == mtimes.keys()
    for name in mtimes:
        assert (after[name] != mtimes[name]) == name.endswith("-specular"), name
    spec = next(s for s in scenes if s.name.endswith("-specular"))
    assert np.load(spec / "specular.npy").max() <= 2.0
    # dropping a category prunes its scenes
    materials.run(Params(size=48, superpixels=60, seed=2, categories=("diffuse",)), data)
    assert sorted(p.name.rsplit("-", 1)[1] for p in (data / "materials").iterdir()) == ["diffuse", "diffuse"]
