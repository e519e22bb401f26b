"""Which lights each training pixel sees: the light-subset rule, its settings declared once
(:class:`LightSubsetRule`), checked once (:func:`check_light_subsets`), and drawn in numpy
(:func:`sample_light_masks`: the extract stage and the patch loader) and in torch
(:func:`light_subsets`: the per-pixel generator), side by side.

The rule (the extract stage's docstring, steps 1 and 2): a cone about +z of half-angle
U(``cone_min_deg``, ``cone_max_deg``), widened to hold min(``min_lights``, m) lights; k
lights of it at random, k uniform in [min(``min_lights``, m), min(``max_lights``, m)]; a
share ``sparse_fraction`` of sparse pixels with k log-uniform in [``sparse_min_lights``,
``min_lights``) instead (:func:`sparse_subset_sizes`). Every place that takes these
settings (params.yaml's ``extract`` keys, ``train.synthesis``,
:class:`cnnps.train.patch_dataset.PatchSampling` and the functions here) takes its defaults
from :data:`RULE`. This module imports torch only inside :func:`light_subsets`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numpy as np

from cnnps.infra.errors import ConfigError

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class LightSubsetRule:
    """The light-subset settings and their defaults (the paper's: 50 to 1300 lights in cones
    of 20 to 90 degrees; sparse maps from 6 lights)."""

    min_lights: int = 50
    max_lights: int = 1300
    cone_min_deg: float = 20.0
    cone_max_deg: float = 90.0
    sparse_min_lights: int = 6  # a sparse map's k is log-uniform in [sparse_min_lights, min_lights)


RULE = LightSubsetRule()
SETTINGS = tuple(f.name for f in fields(LightSubsetRule))  # their names, in order


def check_light_subsets(where: str, settings, sparse_fraction: float = 0.0) -> None:
    """Raise :class:`ConfigError` naming ``where`` (e.g. ``extract``) when the settings of
    ``settings`` (any object with the :data:`SETTINGS` attributes) break the rule:
    1 <= min_lights <= max_lights, 0 < cone_min_deg <= cone_max_deg <= 180,
    sparse_min_lights >= 1, and with a sparse share sparse_min_lights < min_lights."""
    lo, hi = settings.min_lights, settings.max_lights
    if not 1 <= lo <= hi:
        raise ConfigError(f"{where}: need 1 <= min_lights <= max_lights, got {lo} and {hi}")
    if not 0.0 < settings.cone_min_deg <= settings.cone_max_deg <= 180.0:
        raise ConfigError(f"{where}: need 0 < cone_min_deg <= cone_max_deg <= 180, "
                          f"got {settings.cone_min_deg}, {settings.cone_max_deg}")
    if settings.sparse_min_lights < 1:
        raise ConfigError(f"{where}.sparse_min_lights must be >= 1, got {settings.sparse_min_lights}")
    if sparse_fraction and settings.sparse_min_lights >= lo:
        raise ConfigError(f"{where}: need sparse_min_lights < min_lights, got {settings.sparse_min_lights} and {lo}")


def sample_light_masks(
    rng: np.random.Generator,
    lights: np.ndarray,
    n_pixels: int,
    min_lights: int,
    max_lights: int,
    cone_min_deg: float,
    cone_max_deg: float,
    *,
    sparse_fraction: float = 0.0,
    sparse_min_lights: int = RULE.sparse_min_lights,
    sparse_rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw per-pixel light subsets restricted to cones about +z.

    Returns (mask (P, m) bool, cone_deg (P,) float64 half-angle actually used, k (P,)
    lights used). The rules are in :mod:`cnnps.stages.extract`'s docstring (steps 1, 2);
    :func:`light_subsets` is the same rule in torch.

    ``sparse_fraction`` > 0 (with ``sparse_rng``, its own stream): each pixel is sparse
    with that probability and then uses :func:`sparse_subset_sizes` lights instead of
    the dense size; the cone, the subset keys and ``rng``'s draws are the same either way,
    and the cone always holds ``min(min_lights, m)`` > k lights, so a sparse pixel gets
    exactly its k.
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
    k = rng.integers(lo, hi + 1, size=P)
    if sparse_fraction > 0:
        if sparse_rng is None:
            raise ValueError("sparse_fraction > 0 needs sparse_rng (its own stream)")
        sparse = sparse_rng.random(P) < sparse_fraction
        k = np.where(sparse, sparse_subset_sizes(sparse_rng, P, sparse_min_lights, lo), k)
    k = np.minimum(k, n_in)
    keys = rng.random((P, m))
    keys[~in_cone] = 2.0  # never chosen
    kth = np.take_along_axis(np.sort(keys, axis=1), (k - 1)[:, None], axis=1)
    mask = keys <= kth
    cone_deg = np.degrees(np.arccos(cos_used))
    return mask, cone_deg, mask.sum(axis=1)


def sparse_subset_sizes(rng: np.random.Generator, n: int, sparse_min_lights: int, dense_min: int) -> np.ndarray:
    """n sparse subset sizes, log-uniform over the integers [a, b] with
    ``a = min(sparse_min_lights, dense_min)`` and ``b = max(a, dense_min - 1)``:
    ``k = floor(exp(U(ln a, ln(b + 1))))``, so ``P(k) = ln((k + 1) / k) / ln((b + 1) / a)``
    (for [6, 49]: 6 lights 7.3 %, 6-11 lights 33 %, 6-20 lights 59 %)."""
    a = max(1, min(int(sparse_min_lights), int(dense_min)))
    b = max(a, int(dense_min) - 1)
    k = np.floor(np.exp(rng.uniform(np.log(a), np.log(b + 1), size=n))).astype(np.int64)
    return np.clip(k, a, b)


def light_subsets(
    lights: torch.Tensor,
    n: int,
    *,
    generator: torch.Generator,
    min_lights: int = RULE.min_lights,
    max_lights: int = RULE.max_lights,
    cone_min_deg: float = RULE.cone_min_deg,
    cone_max_deg: float = RULE.cone_max_deg,
    sparse_fraction: float = 0.0,
    sparse_min_lights: int = RULE.sparse_min_lights,
) -> torch.Tensor:
    """(n, m) bool per-pixel light subsets by the extract rules
    (:func:`cnnps.synth.training_samples.sample_light_masks`): a cone about +z of
    half-angle U(cone_min_deg, cone_max_deg), widened to hold min(min_lights, m) lights,
    k ~ U{min(min_lights, m) .. min(max_lights, m)} lights of it at random; a share
    ``sparse_fraction`` of pixels use k log-uniform in [sparse_min_lights, min_lights)
    (:func:`cnnps.synth.training_samples.sparse_subset_sizes`'s law)."""
    import torch  # here: the numpy form above imports without torch (the extract stage's)

    dev = lights.device
    m = lights.shape[0]
    z = lights[:, 2].clamp(-1.0, 1.0)
    lo, hi = min(min_lights, m), min(max_lights, m)
    half = cone_min_deg + (cone_max_deg - cone_min_deg) * torch.rand(n, generator=generator, device=dev, dtype=torch.float64)
    cos_half = torch.cos(torch.deg2rad(half)).to(z.dtype)
    z_lo = torch.sort(z, descending=True).values[lo - 1]
    in_cone = z[None, :] >= torch.minimum(cos_half, z_lo)[:, None]
    n_in = in_cone.sum(1)
    k = torch.randint(lo, hi + 1, (n,), generator=generator, device=dev)
    if sparse_fraction > 0:
        a = max(1, min(int(sparse_min_lights), lo))
        b = max(a, lo - 1)
        sp = torch.rand(n, generator=generator, device=dev) < sparse_fraction
        uu = torch.rand(n, generator=generator, device=dev, dtype=torch.float64)
        ks = torch.floor(torch.exp(math.log(a) + uu * (math.log(b + 1) - math.log(a)))).long().clamp(a, b)
        k = torch.where(sp, ks, k)
    k = torch.minimum(k, n_in)
    keys = torch.rand(n, m, generator=generator, device=dev)
    keys = torch.where(in_cone, keys, torch.full_like(keys, 2.0))
    kth = torch.sort(keys, dim=1).values.gather(1, (k - 1).clamp(min=0)[:, None])
    return (keys <= kth) & (k[:, None] > 0)
