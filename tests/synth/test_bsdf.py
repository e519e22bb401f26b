"""The paper's material ranges and their Blender 5 Principled BSDF mapping (cnnps.synth.bsdf)."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.synth import bsdf
from cnnps.synth.bsdf import MaterialRanges, specular_to_ior, to_blender_inputs


def test_default_ranges_are_the_papers():
    r = MaterialRanges()
    assert r.diffuse.metallic == (0, 0) and r.specular.metallic == (0, 0) and r.metallic.metallic == (1, 1)
    assert r.diffuse.specular == (0, 1) and r.specular.specular == (0, 4) and r.metallic.specular == (0, 1)
    assert r.metallic.roughness == (0.3, 0.7) and r.diffuse.roughness == (0, 1)
    for c in bsdf.DEFAULT_CATEGORIES:
        cr = r.get(c)
        assert cr.base_color == cr.sheen == cr.sheen_tint == (0, 1)
    # the materials stage draws the paper's three unless told otherwise; narrow is opt-in
    assert bsdf.DEFAULT_CATEGORIES == ("diffuse", "specular", "metallic")
    assert bsdf.CATEGORIES == bsdf.DEFAULT_CATEGORIES + ("narrow",)


def test_narrow_category_ranges_are_editable():
    n = MaterialRanges().narrow
    assert n.roughness == (0.02, 0.15) and n.specular == (0.5, 2.0) and n.metallic == (0, 0)
    assert n.base_color == (0, 1) and n.sheen == n.sheen_tint == (0, 0)
    assert n.high_specular_min_roughness == 0.02  # its own lower bound: the floor changes no default draw
    r = MaterialRanges.from_dict({"Narrow": {"metallic": [0, 1], "roughness": [0.05, 0.1]}})
    assert r.narrow.metallic == (0, 1) and r.narrow.roughness == (0.05, 0.1) and r.narrow.specular == (0.5, 2.0)
    assert r.specular == MaterialRanges().specular
    assert MaterialRanges().to_dict()["narrow"]["roughness"] == [0.02, 0.15]
    with pytest.raises(ConfigError, match="high_specular_min_roughness"):
        MaterialRanges.from_dict({"narrow": {"roughness": [0.0, 0.01]}})  # all below the floor, specular up to 2


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


def test_narrow_samples_lie_in_their_ranges_and_map_to_blender():
    cr = MaterialRanges().narrow
    t = bsdf.sample_parameters(cr, 20000, np.random.default_rng(4))
    for name in bsdf.PARAM_NAMES:
        lo, hi = getattr(cr, name)
        assert t[name].min() >= np.float32(lo) and t[name].max() <= np.float32(hi), name
    # uniform over the whole range (the floor is the range's lower bound: no rescaling)
    assert t["roughness"].min() < 0.021 and t["roughness"].max() > 0.149
    assert np.mean(t["roughness"] < 0.05) == pytest.approx(0.03 / 0.13, abs=0.02)
    assert np.mean(t["specular"] > 1) == pytest.approx(2 / 3, abs=0.02)
    assert (t["metallic"] == 0).all() and (t["sheen"] == 0).all()
    b = to_blender_inputs(t)
    np.testing.assert_allclose(b["Roughness"], t["roughness"])
    np.testing.assert_allclose(b["Specular IOR Level"], t["specular"])
    np.testing.assert_allclose(bsdf.blender_f0(b), 0.08 * t["specular"], rtol=1e-6)  # F0 0.04-0.16
    assert bsdf.blender_f0(b).min() >= 0.04 - 1e-6 and bsdf.blender_f0(b).max() <= 0.16 + 1e-6
    assert (b["Metallic"] == 0).all() and (b["Sheen Weight"] == 0).all() and (b["IOR"] == 1.5).all()
    np.testing.assert_allclose(b["Base Color"][:, :3], t["base_color"])
    # the paper's categories draw exactly what they drew before narrow existed (pinned)
    old = bsdf.sample_parameters(MaterialRanges().specular, 3, np.random.default_rng(0))
    np.testing.assert_array_equal(old["specular"], np.float32([3.429617166519165, 0.13434229791164398, 2.918621778488159]))
    np.testing.assert_array_equal(old["roughness"], np.float32([0.21687284111976624, 0.8631789088249207, 0.5643881559371948]))


def test_categories_and_ranges_are_checked_once_with_the_section_named():
    from cnnps.synth.bsdf import checked_categories, checked_ranges

    assert checked_categories("eval", ["Specular", "metallic"]) == ("specular", "metallic")
    for bad, message in ((["glass"], "eval.categories: unknown category 'glass'"), ([], "eval.categories is empty"),
                         (["narrow", "narrow"], "eval.categories has duplicates"),
                         ("diffuse", "eval.categories must be a list of category names")):
        with pytest.raises(ConfigError, match=message):
            checked_categories("eval", bad)
    assert checked_ranges("materials", None) == MaterialRanges()
    assert checked_ranges("eval", {"metallic": {"roughness": [0.1, 0.5]}}).metallic.roughness == (0.1, 0.5)
    with pytest.raises(ConfigError, match=r"train.synthesis.ranges: unknown category 'glass'"):
        checked_ranges("train.synthesis", {"glass": {}})
    with pytest.raises(ConfigError, match=r"eval.ranges must be a mapping of categories"):
        checked_ranges("eval", 3)
