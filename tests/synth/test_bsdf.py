"""The paper's material ranges and their Blender 5 Principled BSDF mapping (cnnps.synth.bsdf)."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.core.errors import ConfigError
from cnnps.synth import bsdf
from cnnps.synth.bsdf import MaterialRanges, specular_to_ior, to_blender_inputs


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
