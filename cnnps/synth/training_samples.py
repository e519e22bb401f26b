"""Training samples from a rendered capture: per-pixel light subsets, augmentations and
the rotated observation-map rows (the rules are in :mod:`cnnps.stages.extract`'s docstring,
steps 1 to 4).

- :func:`sample_light_masks`: per pixel a cone about the view axis (+z) of random
  half-angle, widened to hold at least ``min_lights``, and a random subset of k lights in it;
- :func:`add_ambient`: the ambient offset augmentation (real attached shadows are not black);
- :func:`build_rows`: maps and normals for every rotation angle about z, built by the same
  :func:`cnnps.core.obsmap.observation_maps_multi` that prediction uses.
"""

from __future__ import annotations

import numpy as np

from cnnps.core.obsmap import observation_maps_multi
from cnnps.core.rotation import rotate_z


def sample_light_masks(
    rng: np.random.Generator,
    lights: np.ndarray,
    n_pixels: int,
    min_lights: int,
    max_lights: int,
    cone_min_deg: float,
    cone_max_deg: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw per-pixel light subsets restricted to cones about +z.

    Returns (mask (P, m) bool, cone_deg (P,) float64 half-angle actually used, k (P,)
    lights used). The rules are in this module's docstring.
    """
    lights = np.asarray(lights, dtype=np.float64)
    m = lights.shape[0]
    P = n_pixels
    z = np.clip(lights[:, 2], -1.0, 1.0)
    lo = min(min_lights, m)
    hi = min(max_lights, m)
    half = rng.uniform(cone_min_deg, cone_max_deg, size=P)
    cos_half = np.cos(np.radians(half))
    # widen cones holding fewer than `lo` lights to the lo-th nearest light to the axis
    z_lo = np.sort(z)[::-1][lo - 1]
    cos_used = np.minimum(cos_half, z_lo)
    in_cone = z[None, :] >= cos_used[:, None]  # (P, m)
    n_in = in_cone.sum(axis=1)
    k = np.minimum(rng.integers(lo, hi + 1, size=P), n_in)
    keys = rng.random((P, m))
    keys[~in_cone] = 2.0  # never chosen
    kth = np.take_along_axis(np.sort(keys, axis=1), (k - 1)[:, None], axis=1)
    mask = keys <= kth
    cone_deg = np.degrees(np.arccos(cos_used))
    return mask, cone_deg, mask.sum(axis=1)


def add_ambient(rng: np.random.Generator, I: np.ndarray, mask: np.ndarray, ambient_max: float) -> np.ndarray:
    """``I + a * max(I over the pixel's chosen lights)`` with one ``a ~ U(0, ambient_max)``
    per pixel (row), added to every light: real attached shadows are not black (DiLiGenT
    BALL: ~3 % of the pixel's brightest value from ambient light and the black level),
    while rendered ones are exactly 0. I: (P, m); mask: (P, m) chosen lights."""
    a = rng.uniform(0.0, ambient_max, size=(I.shape[0], 1))
    top = np.where(mask, I, 0.0).max(axis=1, keepdims=True)
    return I + (a * top).astype(I.dtype)


def build_rows(
    intensities: np.ndarray,
    normals: np.ndarray,
    lights: np.ndarray,
    light_mask: np.ndarray,
    angles: np.ndarray,
    w: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Maps (R, P, w, w) float16 and normals (R, P, 3) float32 for every rotation angle:
    rotation r uses lights and normals rotated about z by ``angles[r]``."""

    # one call for all angles: the masked values are shared, only the cells move
    rot_lights = np.stack([rotate_z(lights, a) for a in angles])
    maps = observation_maps_multi(intensities, rot_lights, w, light_mask=light_mask, dtype=np.float16)
    rot_normals = np.empty((len(angles), len(normals), 3), np.float32)
    for r, a in enumerate(angles):
        rot_normals[r] = rotate_z(normals, a)
    return maps, rot_normals
