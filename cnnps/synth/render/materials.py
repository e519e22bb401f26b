"""Renderer materials: the dicts :class:`cnnps.synth.blender.BlenderRenderer`
builds its BSDF from (white Lambertian, or Blender Principled inputs from the paper's
parameter maps) and a capture's material drawn on superpixels of Blender's mask.

Material maps are extended outward by nearest neighbour (:func:`extend_maps`), so a
silhouette pixel that Blender covers but the materials' rasteriser did not still gets its
neighbour's material.

Example::

    lambertian_material(0.8)                                   # {"bsdf": "lambertian", "Color": 0.8}
    capture_material("specular", 100, seed=0)(mask)            # a Principled dict drawn on the mask
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import derive_seed
from cnnps.synth.render.settings import MATERIAL_KINDS


def extend_maps(maps: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, np.ndarray]:
    """Fill every map outside ``mask`` with its nearest mask pixel's value."""
    from scipy.ndimage import distance_transform_edt

    if not mask.any() or mask.all():
        return maps
    _, (ri, ci) = distance_transform_edt(~mask, return_indices=True)
    return {k: (v[ri, ci] if np.ndim(v) >= 2 else v) for k, v in maps.items()}


def lambertian_material(albedo=1.0) -> dict:
    """Renderer material: a Lambertian (Diffuse BSDF, roughness 0) of ``albedo`` (scalar, RGB or map)."""
    return {"bsdf": "lambertian", "Color": albedo}


def principled_material(params: dict[str, np.ndarray]) -> dict:
    """Renderer material (Blender Principled inputs) from paper parameter maps, through
    :func:`cnnps.synth.bsdf.to_blender_inputs`: RGBA colours become RGB, maps that hold one
    value everywhere become constants (no texture)."""
    from cnnps.synth.bsdf import to_blender_inputs

    out: dict[str, Any] = {"bsdf": "principled"}
    for name, value in to_blender_inputs(params).items():
        arr = np.asarray(value, dtype=np.float32)
        if arr.ndim >= 1 and arr.shape[-1] == 4 and (arr.ndim == 1 or arr.ndim == 3):
            arr = arr[..., :3]  # RGBA -> RGB (alpha 1)
        if arr.ndim >= 2:
            flat = arr.reshape(arr.shape[0] * arr.shape[1], -1)
            if np.all(flat == flat[0]):
                arr = flat[0] if flat.shape[1] > 1 else flat[0, 0]
        out[name] = arr
    return out


def capture_material(material: str, superpixels: int, seed: int, ranges=None):
    """The renderer material of a capture: the white Lambertian dict for ``lambertian``,
    else a callable ``mask -> material dict`` drawing the category on ``superpixels``
    superpixels of the mask with ``seed`` from ``ranges`` (a
    :class:`cnnps.synth.bsdf.CategoryRanges` or :class:`~cnnps.synth.bsdf.MaterialRanges`;
    None = the category's default ranges); a ConfigError for an unknown category."""
    if material not in MATERIAL_KINDS:
        raise ConfigError(f"material must be one of {', '.join(MATERIAL_KINDS)}, got {material!r}")
    if superpixels < 1:
        raise ConfigError(f"superpixels must be >= 1, got {superpixels}")
    if material == "lambertian":
        return lambertian_material()

    def mat(mask: np.ndarray) -> dict:
        from cnnps.synth.material_maps import sample_material_maps

        maps = sample_material_maps(mask, material, superpixels, derive_seed(int(seed), "material"), ranges)
        return principled_material(extend_maps(dict(maps.params), mask))

    return mat
