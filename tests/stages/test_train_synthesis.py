"""Per-pixel training maps draw what params.yaml says: the materials of
``materials.categories`` / ``materials.ranges`` and the light subsets of extract's keys,
through the config layer (``train.synthesis``), with run keys unchanged at the defaults."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import yaml

from cnnps.infra.errors import ConfigError
from cnnps.pipeline import config as cfg
from cnnps.stages import train
from cnnps.train.pixelwise_batches import pixelwise_fewest_lights, pixelwise_maker

EDITED = {
    "materials": {"categories": ["specular"], "ranges": {"specular": {"roughness": [0.2, 0.3]}}},
    "extract": {"min_lights": 20, "max_lights": 40, "cone_min_deg": 30.0, "cone_max_deg": 40.0,
                "sparse_min_lights": 4},
    "train": {"max_steps": 1, "pixelwise": {"share": 1.0, "lights": 300, "sparse_fraction": 0.25}},
}


def _train_params(tmp_path, sections: dict) -> train.Params:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(sections, sort_keys=False))
    return cfg.build_params(cfg.load_config(path), "train", check_files=False)


def test_an_edited_range_and_light_subsets_reach_the_per_pixel_maps(tmp_path, monkeypatch):
    """The maps the training loop makes (pixelwise_maker) are drawn from the params
    file's materials and extract keys: every pixel's category is the one chosen, its
    roughness in the edited range, its light subset within extract's bounds and cone."""
    p = _train_params(tmp_path, EDITED)
    syn = p.synthesis
    assert (syn.categories, syn.ranges.specular.roughness) == (("specular",), (0.2, 0.3))
    assert (syn.min_lights, syn.max_lights, syn.cone_min_deg, syn.cone_max_deg, syn.sparse_min_lights) == (
        20, 40, 30.0, 40.0, 4)

    from cnnps.synth import pixelwise

    seen = {}
    real = pixelwise.generate

    def generate(n, **kw):  # the loop's call, with the draws kept
        maps, normals, seen["details"] = real(n, return_details=True, **kw)
        seen["kw"] = kw
        return maps, normals

    monkeypatch.setattr(pixelwise, "generate", generate)
    make = pixelwise_maker(p)
    maps, normals = make(2000, torch.Generator().manual_seed(0), torch.device("cpu"), 16)
    assert maps.shape == (2000, 1, 16, 16) and normals.shape == (2000, 3)
    d, kw = seen["details"], seen["kw"]
    assert kw["categories"] == ("specular",) and kw["n_lights"] == 300 and d["lights"].shape == (300, 3)
    assert set(d["category"].tolist()) == {0}  # the index into ("specular",): no other category
    rough, spec, metal = d["params"]["roughness"], d["params"]["specular"], d["params"]["metallic"]
    assert 0.2 <= rough.min() and rough.max() <= 0.3
    assert rough.max() - rough.min() > 0.09  # drawn across the range, not pinned to one end
    assert 0.0 <= spec.min() and spec.max() <= 4.0 and spec.max() > 1.0 and (metal == 0).all()  # specular's ranges
    k = d["mask"].sum(1)
    dense = k >= 20
    assert k.max() <= 40 and dense.float().mean() > 0.6  # sparse ones (a quarter): 4 .. 19 lights
    assert k[~dense].min() >= 4 and (~dense).any()
    # every chosen light inside a cone of at most 40 degrees (300 spiral lights: a 30-degree
    # cone already holds 20, so no cone is widened)
    z = d["lights"][:, 2].expand_as(d["mask"])
    assert (z[d["mask"]] >= math.cos(math.radians(40.0)) - 1e-6).all()
    assert pixelwise_fewest_lights(p) == 4


def test_the_defaults_are_the_sections_defaults_and_keep_the_maps():
    """``Params()`` (no params file) and an empty params file draw the same: the materials
    and extract stages' defaults, which are generate()'s; the maps are generate()'s own."""
    built = cfg.build_params(cfg.config_from_dict({}), "train", check_files=False)
    assert built.synthesis == train.Params().synthesis == train.SynthesisParams()
    from cnnps.synth import pixelwise

    p = train.Params(max_steps=1, pixelwise={"share": 1.0})
    a = pixelwise_maker(p)(64, torch.Generator().manual_seed(3), torch.device("cpu"), 8)
    b = pixelwise.generate(64, generator=torch.Generator().manual_seed(3), w=8)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_train_cannot_set_what_materials_and_extract_set():
    c = cfg.config_from_dict({"train": {"synthesis": {"max_lights": 100}}}, "x.yaml")
    with pytest.raises(ConfigError, match=r"x.yaml: train.synthesis is not set in train: it is materials.categories, "
                                          r"materials.ranges, extract.min_lights, .*extract.sparse_min_lights"):
        cfg.build_params(c, "train", check_files=False)
    c = cfg.config_from_dict({"materials": {"categories": ["glass"]}}, "x.yaml")
    with pytest.raises(ConfigError, match="x.yaml: materials.categories: unknown category 'glass'"):
        cfg.build_params(c, "train", check_files=False)  # the source's own check, naming its key
    with pytest.raises(ConfigError, match="train.synthesis: need 1 <= min_lights <= max_lights"):
        train.Params(synthesis={"min_lights": 60, "max_lights": 50})
    with pytest.raises(ConfigError, match="train.pixelwise.lights"):
        train.Params(pixelwise={"lights": 2})
    c = cfg.config_from_dict({"extract": {"min_lights": 6},
                              "train": {"max_steps": 1, "pixelwise": {"share": 1.0, "sparse_fraction": 0.2}}}, "x.yaml")
    with pytest.raises(ConfigError, match="x.yaml: train.pixelwise.sparse_fraction needs extract.sparse_min_lights < "
                                          "extract.min_lights .*got 6 and 6"):
        cfg.build_params(c, "train", check_files=False)


def test_run_keys_hold_the_synthesis_only_where_it_changes_the_maps(tmp_path):
    """Runs at the defaults keep their keys; an edited range or light subset is a new run
    for per-pixel training, and changes nothing for shards-only training (the shards'
    manifest, in the key, holds what made them)."""
    def key(p):
        return train.run_key(p, "m", precision="fp32")

    base = dict(max_steps=5, pixelwise={"share": 1.0})
    p0 = train.Params(**base)
    assert p0.flat() == train.Params(**base, synthesis=train.SynthesisParams()).flat()
    assert not any(k.startswith("synthesis_") or k == "pixelwise_lights" for k in p0.flat())
    edited = _train_params(tmp_path, EDITED)
    assert key(edited) != key(train.Params(**{**base, "pixelwise": {"share": 1.0, "lights": 300,
                                                                     "sparse_fraction": 0.25}}))
    assert edited.result_key()["synthesis_ranges"] == {"specular": {**edited.synthesis.ranges.specular.to_dict()}}
    assert edited.result_key()["synthesis_categories"] == ["specular"]
    # editing a category that is not drawn changes nothing
    narrow = train.Params(**base, synthesis={"ranges": {"narrow": {"roughness": [0.05, 0.1]}}})
    assert key(narrow) == key(p0)
    for syn in ({"max_lights": 200}, {"categories": ["metallic"]}, {"ranges": {"metallic": {"roughness": [0.4, 0.5]}}}):
        assert key(train.Params(**base, synthesis=syn)) != key(p0)
        shards = train.Params(synthesis=syn)  # share 0
        assert key(shards) == key(train.Params())
    # what a model file records (meta["params"]) reads back to the same params and key
    assert train.Params.from_record(dataclasses.asdict(edited)) == edited
