"""Superpixel material maps: SLIC superpixels inside a mask, one random BSDF row each.

- :func:`slic_labels`: SLIC superpixels inside the mask (on the normal map, say),
  relabelled densely in row-major order of first appearance;
- :func:`sample_material_maps`: one random parameter row per superpixel drawn from a
  category's ranges (:mod:`cnnps.synth.bsdf`), spread into per-pixel maps;
- :func:`write_material_maps`: one scene folder (``<param>.npy``, ``labels.npy``,
  ``mask.png``, ``normal.npy``, ``preview.png``, ``material.json``), written atomically.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cnnps.infra.atomic import atomic_dir
from cnnps.infra.errors import InputError
from cnnps.io.capture import MASK_FILE
from cnnps.synth.bsdf import (
    PARAM_NAMES,
    CategoryRanges,
    MaterialRanges,
    sample_parameters,
)


@dataclass
class MaterialMaps:
    labels: np.ndarray  # (S,S) int32, superpixel index, -1 outside the mask
    params: dict[str, np.ndarray]  # base_color (S,S,3), others (S,S); float32, 0 outside
    table: dict[str, np.ndarray]  # per superpixel: base_color (P,3), others (P,)
    category: str
    mask: np.ndarray  # (S,S) bool


def slic_labels(mask: np.ndarray, n_segments: int, image: np.ndarray | None = None, compactness: float = 0.1) -> np.ndarray:
    """SLIC labels (S,S) int32 inside ``mask`` (−1 outside), relabelled 0..P'−1.

    ``image``: (S,S,C) or (S,S) features to segment (e.g. the normal map); ``None`` uses
    the pixel coordinates (compact, grid-like cells). SLIC with a mask is deterministic
    (scikit-image seeds its k-means placement itself).
    """
    from skimage.segmentation import slic

    mask = np.asarray(mask, dtype=bool)
    labels = np.full(mask.shape, -1, dtype=np.int32)
    if not mask.any():
        return labels
    if image is None:
        yy, xx = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]].astype(np.float64)
        image = np.stack([yy, xx], axis=-1) / max(mask.shape)
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 2:
        image = image[..., None]
    n = int(min(n_segments, mask.sum()))
    seg = slic(image, n_segments=n, compactness=compactness, mask=mask, start_label=0, channel_axis=-1, convert2lab=False, enforce_connectivity=True)
    seg = np.where(mask, seg, -1)
    # relabel densely (0..P'-1) in order of first appearance (row-major)
    inside = seg[mask]
    _, first, inv = np.unique(inside, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    labels[mask] = rank[inv].astype(np.int32)
    return labels


def sample_material_maps(
    mask: np.ndarray,
    category: str,
    superpixels: int = 5000,
    seed: int = 0,
    ranges: MaterialRanges | CategoryRanges | None = None,
    image: np.ndarray | None = None,
    compactness: float = 0.1,
    *,
    labels: np.ndarray | None = None,
) -> MaterialMaps:
    """Per-superpixel random parameters of ``category`` as per-pixel maps.

    ``superpixels``: SLIC segments P (paper: 5000 for training, 100 for test).
    ``image``: features for SLIC (the normal map is a good choice; ``None`` = coordinates).
    ``ranges``: :class:`MaterialRanges` (the category's ranges are taken) or a
    :class:`CategoryRanges`; ``None`` = the paper's defaults. ``labels``: precomputed
    superpixel labels (skips SLIC).
    """
    mask = np.asarray(mask, dtype=bool)
    cat = category.lower()
    if isinstance(ranges, CategoryRanges):
        cr = ranges
    else:
        cr = (ranges or MaterialRanges()).get(cat)
    if labels is None:
        labels = slic_labels(mask, superpixels, image, compactness)
    labels = np.asarray(labels, dtype=np.int32)
    n = int(labels.max()) + 1 if mask.any() else 0
    rng = np.random.default_rng(seed)
    table = sample_parameters(cr, n, rng)
    params: dict[str, np.ndarray] = {}
    inside = labels >= 0
    for name in PARAM_NAMES:
        col = table[name]
        shape = mask.shape + col.shape[1:]
        out = np.zeros(shape, dtype=np.float32)
        out[inside] = col[labels[inside]]
        params[name] = out
    return MaterialMaps(labels, params, table, cat, mask)


def preview_image(maps: MaterialMaps) -> np.ndarray:
    """(S, 2S, 3) uint8 sRGB-ish picture: base colour (left); roughness, specular/4, sheen as R, G, B (right)."""
    base = np.clip(maps.params["base_color"], 0, 1)
    right = np.stack([maps.params["roughness"], maps.params["specular"] / 4.0, maps.params["sheen"]], axis=-1)
    img = np.clip(np.concatenate([base, right], axis=1), 0, 1)
    img[np.concatenate([~maps.mask, ~maps.mask], axis=1)] = 0.15
    return (img * 255 + 0.5).astype(np.uint8)


def write_material_maps(out_dir: str | Path, maps: MaterialMaps, normal: np.ndarray | None = None, meta: dict | None = None) -> None:
    """Write a scene folder atomically: ``<param>.npy``, ``labels.npy``, ``mask.png``,
    ``normal.npy``, ``preview.png`` and ``material.json`` (``meta`` merged in)."""
    import cv2

    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        for name, arr in maps.params.items():
            np.save(tmp / f"{name}.npy", arr.astype(np.float32))
        np.save(tmp / "labels.npy", maps.labels.astype(np.int32))
        if normal is not None:
            np.save(tmp / "normal.npy", np.asarray(normal, dtype=np.float32))
        if not cv2.imwrite(str(tmp / MASK_FILE), maps.mask.astype(np.uint8) * 255):
            raise InputError(tmp / MASK_FILE, "cannot write image")
        if not cv2.imwrite(str(tmp / "preview.png"), preview_image(maps)[..., ::-1]):
            raise InputError(tmp / "preview.png", "cannot write image")
        info = {
            "category": maps.category,
            "superpixels_found": int(maps.labels.max()) + 1 if maps.mask.any() else 0,
            "pixels": int(maps.mask.sum()),
            "params": list(maps.params),
            "table": {k: v.tolist() for k, v in maps.table.items()},
        }
        info.update(meta or {})
        (tmp / "material.json").write_text(json.dumps(info, indent=1) + "\n")
