"""Superpixel material maps (cnnps.synth.material_maps): ranges, constancy per superpixel, seeds, files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from cnnps.synth import bsdf
from cnnps.synth.bsdf import MaterialRanges
from cnnps.synth.material_maps import (
    sample_material_maps,
    slic_labels,
    write_material_maps,
)
from cnnps.synth.raster import rasterize


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
    write_material_maps(out, maps, normal, {"key": "abc", "seed": 0})
    names = {p.name for p in out.iterdir()}
    assert names == {f"{n}.npy" for n in bsdf.PARAM_NAMES} | {"labels.npy", "normal.npy", "mask.png", "preview.png", "material.json"}
    np.testing.assert_array_equal(np.load(out / "roughness.npy"), maps.params["roughness"])
    assert np.array_equal(cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED) > 0, mask)
    meta = json.loads((out / "material.json").read_text())
    assert meta["category"] == "specular" and meta["key"] == "abc"
    assert len(meta["table"]["specular"]) == maps.labels.max() + 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp leftovers




def test_slic_labels_are_dense_row_major_and_connected():
    mask = np.zeros((40, 40), bool)
    mask[5:35, 8:30] = True
    labels = slic_labels(mask, 12)
    assert (labels[~mask] == -1).all()
    n = labels.max() + 1
    np.testing.assert_array_equal(np.unique(labels[mask]), np.arange(n))
    first = [np.flatnonzero(labels.ravel() == k)[0] for k in range(n)]
    assert first == sorted(first)  # numbered in order of first appearance, row-major
    from scipy.ndimage import label as components

    for k in range(n):
        assert components(labels == k)[1] == 1, k  # enforce_connectivity: one piece each
