"""The materials stage: rasteriser, superpixel material maps, Blender mapping, scene keys."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest
import trimesh

from cnnps.core.errors import ConfigError
from cnnps.stages import materials
from cnnps.synth import bsdf
from cnnps.synth.bsdf import MaterialRanges, specular_to_ior, to_blender_inputs
from cnnps.stages.meshes import read_view_mesh
from cnnps.stages.materials import Params, pixel_centres, rasterize, rasterize_full, sample_material_maps


def _angles_deg(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


# --------------------------------------------------------------------------- rasteriser


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


def test_first_hit_wins_and_back_faces_are_flipped():
    # small sphere in front (z = +0.5) of a large one: the front one is seen where they overlap
    front = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    front.apply_translation((0.0, 0.0, 0.5))
    back = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    r = rasterize_full(trimesh.util.concatenate([back, front]), 64)
    x, y = pixel_centres(64)
    X, Y = np.meshgrid(x, y)
    centre = X**2 + Y**2 < 0.25**2
    np.testing.assert_allclose(r.depth[centre], 0.5 + np.sqrt(0.09 - X[centre] ** 2 - Y[centre] ** 2), atol=2e-3)
    # an inside-out sphere shows its back faces: normals still face the camera
    inv = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    inv.invert()
    mask, n = rasterize(inv, 64)
    assert (n[mask][:, 2] > 0).mean() > 0.99


def test_rasterizer_is_fast_enough_for_100k_faces():
    big = trimesh.creation.icosphere(subdivisions=7, radius=0.9)  # 327 680 faces
    big.vertex_normals  # noqa: B018 - computed once, as for a loaded mesh
    t = time.perf_counter()
    mask, _ = rasterize(big, 256)
    elapsed = time.perf_counter() - t
    assert mask.sum() > 40000
    assert elapsed < 5.0, f"rasterising 327k faces at 256x256 took {elapsed:.2f} s"


# --------------------------------------------------------------------------- ranges and Blender mapping


def test_default_ranges_are_the_papers():
    r = MaterialRanges()
    assert r.diffuse.metallic == (0, 0) and r.specular.metallic == (0, 0) and r.metallic.metallic == (1, 1)
    assert r.diffuse.specular == (0, 1) and r.specular.specular == (0, 4) and r.metallic.specular == (0, 1)
    assert r.metallic.roughness == (0.3, 0.7) and r.diffuse.roughness == (0, 1)
    for c in bsdf.CATEGORIES:
        cr = r.get(c)
        assert cr.base_color == cr.sheen == cr.sheen_tint == (0, 1)


def test_ranges_from_dict_override_and_validate():
    r = MaterialRanges.from_dict({"Specular": {"specular": [0, 2], "sheenTint": 0.5}})
    assert r.specular.specular == (0, 2) and r.specular.sheen_tint == (0.5, 0.5)
    assert r.specular.metallic == (0, 0) and r.diffuse == MaterialRanges().diffuse
    for bad, msg in [
        ({"specular": {"roughness": [0.8, 0.2]}}, "lo 0.8 > hi 0.2"),
        ({"diffuse": {"roughness": [0, 1.5]}}, "physical limits"),
        ({"diffuse": {"specular": [0, 20]}}, "physical limits"),
        ({"plastic": {}}, "unknown category"),
        ({"diffuse": {"shininess": [0, 1]}}, "unknown key"),
        ({"diffuse": {"roughness": "rough"}}, "number or"),
        ({"specular": {"roughness": [0, 0.01]}}, "high_specular_min_roughness"),
    ]:
        with pytest.raises(ConfigError, match=msg):
            MaterialRanges.from_dict(bad)


def test_specular_to_ior_known_points():
    assert specular_to_ior(0.5) == pytest.approx(1.5)
    assert specular_to_ior(0.0) == pytest.approx(1.0)
    assert specular_to_ior(4.0) == pytest.approx(3.6046, abs=1e-3)
    assert bsdf.ior_to_specular(1.5) == pytest.approx(0.5)
    s = np.linspace(0, 4, 9)
    np.testing.assert_allclose(bsdf.ior_to_specular(specular_to_ior(s)), s, atol=1e-12)


def test_blender_inputs_reproduce_disney_f0_and_sheen_tint():
    p = {"base_color": (0.2, 0.4, 0.8), "metallic": 0.0, "specular": 0.5, "roughness": 0.3, "sheen": 0.6, "sheen_tint": 0.5}
    b = to_blender_inputs(p)
    assert b["IOR"] == 1.5 and b["Specular IOR Level"] == 0.5
    assert bsdf.blender_f0(b) == pytest.approx(0.04)  # Disney F0 = 0.08 s
    assert b["Base Color"] == pytest.approx((0.2, 0.4, 0.8, 1.0))
    assert b["Sheen Tint"] == pytest.approx((0.6, 0.7, 0.9, 1.0))  # mix(white, base, 0.5)
    assert b["Sheen Weight"] == pytest.approx(0.6) and b["Roughness"] == 0.3
    assert b["Diffuse Roughness"] == 0.0 and b["Alpha"] == 1.0
    # specular 4: F0 = 0.32, i.e. the IOR 3.6 the old mapping needed, with no cap
    b4 = to_blender_inputs({**p, "specular": 4.0})
    assert bsdf.blender_f0(b4) == pytest.approx(0.32)
    assert ((specular_to_ior(4.0) - 1) / (specular_to_ior(4.0) + 1)) ** 2 == pytest.approx(0.32)
    # metals carry no sheen (Disney puts sheen in the dielectric lobe)
    assert to_blender_inputs({**p, "metallic": 1.0})["Sheen Weight"] == 0.0


def test_blender_inputs_vectorise_over_a_table():
    rng = np.random.default_rng(0)
    table = bsdf.sample_parameters(MaterialRanges().specular, 50, rng)
    b = to_blender_inputs(table)
    assert b["Base Color"].shape == (50, 4) and b["Sheen Tint"].shape == (50, 4)
    np.testing.assert_allclose(b["Specular IOR Level"], table["specular"])
    np.testing.assert_allclose(bsdf.blender_f0(b), 0.08 * table["specular"], rtol=1e-6)


def test_sample_parameters_stay_in_range_and_exclude_near_mirrors():
    rng = np.random.default_rng(1)
    cr = MaterialRanges().specular
    t = bsdf.sample_parameters(cr, 20000, rng)
    assert t["base_color"].shape == (20000, 3)
    for name in bsdf.PARAM_NAMES:
        lo, hi = getattr(cr, name)
        assert t[name].min() >= lo and t[name].max() <= hi
    high = t["specular"] > cr.high_specular
    assert high.mean() == pytest.approx(0.75, abs=0.02)
    assert t["roughness"][high].min() >= cr.high_specular_min_roughness
    assert t["roughness"][~high].min() < 0.01  # the low-specular ones may still be mirror-like


# --------------------------------------------------------------------------- material maps


@pytest.fixture(scope="module")
def sphere_mask_normal():
    m = trimesh.creation.icosphere(subdivisions=5, radius=0.9)
    return rasterize(m, 96)


@pytest.mark.parametrize("category", bsdf.CATEGORIES)
def test_maps_fall_in_the_category_ranges_and_are_constant_per_superpixel(sphere_mask_normal, category):
    mask, normal = sphere_mask_normal
    P = 100
    maps = sample_material_maps(mask, category, P, seed=3, image=normal)
    labels = maps.labels
    assert labels.dtype == np.int32 and (labels[~mask] == -1).all() and (labels[mask] >= 0).all()
    n = labels.max() + 1
    assert 0.8 * P <= n <= 1.1 * P
    assert np.array_equal(np.unique(labels[mask]), np.arange(n))
    cr = MaterialRanges().get(category)
    for name in bsdf.PARAM_NAMES:
        arr = maps.params[name]
        assert arr.dtype == np.float32
        assert arr.shape == mask.shape + ((3,) if name == "base_color" else ())
        assert not arr[~mask].any()
        lo, hi = getattr(cr, name)
        assert arr[mask].min() >= lo - 1e-6 and arr[mask].max() <= hi + 1e-6
        # every pixel carries its superpixel's row
        np.testing.assert_array_equal(arr[mask], maps.table[name][labels[mask]])
    if category == "metallic":
        assert (maps.params["metallic"][mask] == 1).all()
    if category == "specular":
        assert maps.table["specular"].max() > 2  # uses the 0-4 range
    # distinct rows: the maps are not constant over the object
    assert len(np.unique(maps.table["roughness"])) > 0.9 * n


def test_maps_are_seeded(sphere_mask_normal):
    mask, normal = sphere_mask_normal
    a = sample_material_maps(mask, "diffuse", 50, seed=1, image=normal)
    b = sample_material_maps(mask, "diffuse", 50, seed=1, image=normal)
    c = sample_material_maps(mask, "diffuse", 50, seed=2, image=normal)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.params["base_color"], b.params["base_color"])
    assert not np.array_equal(a.params["base_color"], c.params["base_color"])


def test_write_material_maps_folder(tmp_path, sphere_mask_normal):
    import cv2

    mask, normal = sphere_mask_normal
    maps = sample_material_maps(mask, "specular", 40, seed=0, image=normal)
    out = tmp_path / "scene"
    materials.write_material_maps(out, maps, normal, {"key": "abc", "seed": 0})
    names = {p.name for p in out.iterdir()}
    assert names == {f"{n}.npy" for n in bsdf.PARAM_NAMES} | {"labels.npy", "normal.npy", "mask.png", "preview.png", "material.json"}
    np.testing.assert_array_equal(np.load(out / "roughness.npy"), maps.params["roughness"])
    assert np.array_equal(cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED) > 0, mask)
    meta = json.loads((out / "material.json").read_text())
    assert meta["category"] == "specular" and meta["key"] == "abc"
    assert len(meta["table"]["specular"]) == maps.labels.max() + 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp leftovers


# --------------------------------------------------------------------------- stage


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
