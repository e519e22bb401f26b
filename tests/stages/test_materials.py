"""The materials stage: parameters, scene keys, caching and pruning (the library: tests/synth/)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
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


def test_narrow_is_opt_in_and_existing_scene_keys_are_unchanged():
    """Adding the narrow category changed no default and no key of the paper's categories."""
    assert Params().categories == ("diffuse", "specular", "metallic")
    pinned = {  # computed before the narrow category existed
        "diffuse": "80ec0e2619c3dab8728bb4da14b9e66210ecd2ce317aad42087fa450c7ae9dcb",
        "specular": "17173eebba568015076367f7d3a71f5b553b1fded42973eb53fcbb27b6b3c92c",
        "metallic": "31155c1ae4b73faace6f86cd878a3c53d03098e3c1f164f8d347696f3538c4b8",
    }
    for cat, key in pinned.items():
        assert materials.scene_key("view", cat, Params()) == key, cat
    p = Params(categories=["diffuse", "Narrow"], ranges={"narrow": {"specular": [0.5, 1.0]}})
    assert p.categories == ("diffuse", "narrow") and p.ranges.narrow.specular == (0.5, 1.0)
    assert materials.scene_key("view", "diffuse", p) == pinned["diffuse"]
    assert materials.scene_key("view", "narrow", p) != materials.scene_key("view", "narrow", Params())


def test_stage_writes_narrow_scenes_next_to_existing_ones(tmp_path, views_data_dir):
    data = tmp_path / "data"
    shutil.copytree(views_data_dir, data)
    materials.run(Params(size=32, superpixels=20, categories=("diffuse",)), data)
    before = {s.name: (s / "material.json").stat().st_mtime_ns for s in (data / "materials").iterdir()}
    materials.run(Params(size=32, superpixels=20, categories=("diffuse", "narrow")), data)
    after = {s.name: s for s in (data / "materials").iterdir()}
    assert sorted(n.rsplit("-", 1)[1] for n in after) == ["diffuse", "diffuse", "narrow", "narrow"]
    for name, mtime in before.items():
        assert (after[name] / "material.json").stat().st_mtime_ns == mtime  # untouched
    cr = bsdf.MaterialRanges().narrow
    for name, sdir in after.items():
        if name.endswith("-narrow"):
            meta = json.loads((sdir / "material.json").read_text())
            assert meta["category"] == "narrow"
            rough = np.load(sdir / "roughness.npy")
            inside = np.load(sdir / "labels.npy") >= 0
            assert cr.roughness[0] - 1e-6 <= rough[inside].min() and rough[inside].max() <= cr.roughness[1] + 1e-6
            assert (np.load(sdir / "metallic.npy") == 0).all()
