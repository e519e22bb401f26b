"""Observation maps generated pixel by pixel, in torch, on CPU or CUDA (PX-Net style:
Logothetis et al., ICCV 2021): no mesh and no renderer, one BSDF evaluation per
(pixel, light), a few seeded global effects, then the same map rule as
:mod:`cnnps.ps.obsmap`. Design notes, the comparison with Cycles and the speed:
``docs/pixelwise.md``.

- :func:`generate` ``(batch_size, *, generator, device, ...)`` -> ``(maps (B, 1, w, w),
  normals (B, 3))`` float32: per pixel a normal (:func:`sample_normals`), a material of
  ``categories`` drawn from ``ranges`` (:func:`sample_materials`), a light subset by the
  extract stage's rules (:func:`light_subsets`), radiance from :func:`shade`, the effects
  of :class:`Effects` (global light, noise, and the camera: exposure, clipping, black level,
  quantisation, :func:`camera_response`; pixels mixing two surfaces), and the map
  (:func:`observation_maps_torch`); ``rgb=True`` adds R, G, B maps
  (:func:`observation_maps_rgb_torch`).
- :func:`shade` ``(normals (P, 3), lights (m, 3), params)`` -> ``(P, m)`` grey values:
  Blender 5's Principled BSDF as :func:`cnnps.synth.bsdf.to_blender_inputs` sets it up,
  under a sun of irradiance 1 (a white Lambertian patch facing the light reads 1),
  view (0, 0, 1), grey = mean of R, G, B (``cnnps.io.capture``'s default).
- :func:`observation_maps_torch` ``(I (P, m), lights (m, 3), w, light_mask)``: the torch
  form of :func:`cnnps.ps.obsmap.observation_maps` (cell of a light, mean on collisions,
  each map scaled to a largest cell of 1).

Frame: x right, y up, z toward the camera; orthographic view v = (0, 0, 1).

Its parts, one module a concern: the surfaces (:mod:`cnnps.synth.surface_samples`), the
BSDF (:mod:`cnnps.synth.principled_torch`), the light subsets
(:mod:`cnnps.synth.light_subsets`), the effects (:mod:`cnnps.synth.effect_settings`, :mod:`cnnps.synth.pixel_effects`) and the
maps (:mod:`cnnps.synth.obsmap_torch`); this module draws them in order. The names above
are importable from here too.

This module takes every setting as an argument; its defaults are the paper's (every
category of :data:`cnnps.synth.bsdf.DEFAULT_CATEGORIES` at its default ranges, 50 to 1300
of 1300 lights in cones of 20 to 90 degrees). The train stage passes params.yaml's:
``materials.categories`` and ``materials.ranges``, extract's light-subset keys, and
``train.pixelwise``'s own (:func:`cnnps.train.pixelwise_batches.pixelwise_settings`).

Example::

    g = torch.Generator().manual_seed(0)
    maps, normals = generate(256, generator=g, effects=Effects(cast_shadow=0.3, ambient=0.05, quantisation=0.5))
"""

from __future__ import annotations

import numpy as np
import torch

from cnnps.infra.errors import ConfigError
from cnnps.synth.bsdf import DEFAULT_CATEGORIES, MaterialRanges
from cnnps.synth.effect_settings import EFFECT_NAMES, Effects
from cnnps.synth.light_subsets import RULE, light_subsets
from cnnps.synth.lights import hemisphere_lights
from cnnps.synth.obsmap_torch import DEFAULT_WIDTH, observation_maps_rgb_torch, observation_maps_torch
from cnnps.synth.pixel_effects import (
    apply_ambient,
    apply_noise,
    camera_response,
    diffuse_colour,
    draw_camera_and_mix,
    draw_effects,
    draw_shares,
    falloff_fd90,
    interreflect,
    mix_boundaries,
    shared_level,
)
from cnnps.synth.principled_torch import shade
from cnnps.synth.surface_samples import sample_materials, sample_normals

# the generator's API, importable from here (each defined in the module named above)
__all__ = ["EFFECT_NAMES", "DEFAULT_WIDTH", "Effects", "camera_response", "default_lights", "generate", "light_subsets",
           "observation_maps_rgb_torch", "observation_maps_torch", "sample_materials", "sample_normals", "shade"]


def default_lights(generator: torch.Generator, n: int = 1300, jitter_deg: float = 3.0, min_elevation_deg: float = 5.0):
    """(n, 3) float64 numpy light set for one batch: :func:`cnnps.synth.lights.hemisphere_lights`
    (the render stage's jittered spiral) with a seed drawn from ``generator``."""
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device).item())
    return hemisphere_lights(n, jitter_deg, seed=seed, min_elevation_deg=min_elevation_deg)


def _unit_lights(lights, device) -> torch.Tensor:
    """(m, 3) float32 unit directions on ``device`` (the generator's, where draws are made)."""
    L0 = lights if torch.is_tensor(lights) else torch.as_tensor(np.asarray(lights))
    L0 = L0.to(device, torch.float32)
    return L0 / L0.norm(dim=1, keepdim=True)


def _maps(I, L, w: int, mask, rgb: bool) -> torch.Tensor:
    """(B, 1, w, w) grey observation maps, or with ``rgb`` (B, 4, w, w): grey then R, G, B."""
    if rgb:
        return torch.cat([observation_maps_torch(I.mean(-1), L, w, light_mask=mask)[:, None],
                          observation_maps_rgb_torch(I, L, w, light_mask=mask)], 1)
    return observation_maps_torch(I, L, w, light_mask=mask)[:, None]


def generate(
    batch_size: int,
    *,
    generator: torch.Generator,
    device="cpu",
    ranges: MaterialRanges | dict | None = None,
    categories=DEFAULT_CATEGORIES,
    lights=None,
    n_lights: int = 1300,
    w: int = DEFAULT_WIDTH,
    min_lights: int = RULE.min_lights,
    max_lights: int = RULE.max_lights,
    cone_min_deg: float = RULE.cone_min_deg,
    cone_max_deg: float = RULE.cone_max_deg,
    sparse_fraction: float = 0.0,
    sparse_min_lights: int = RULE.sparse_min_lights,
    grazing_fraction: float = 0.1,
    effects: Effects = Effects(),
    diffuse_model: str = "lambert",
    sheen_model: str = "microfiber",
    rgb: bool = False,
    return_details: bool = False,
):
    """``batch_size`` training samples: (maps (B, 1, w, w) float32, normals (B, 3) float32),
    on ``device``, the same for the same generator state. Every random draw is made on
    the generator's device: a CPU generator gives the same draws whatever ``device`` is
    (made on the CPU and moved); a CUDA generator draws on the GPU (another stream of
    numbers, as reproducible), which a GPU needs: with a CPU generator the step waits for
    the draws (docs/pixelwise.md#a-gpu-recipe-toolsgpu_recipepy).

    ``lights``: (m, 3) unit directions shared by the batch (frame: x right, y up, z toward
    the camera), or None: a jittered spiral of ``n_lights`` (:func:`default_lights`) drawn
    from the generator. ``categories`` (each pixel's drawn uniformly) and ``ranges``: the
    materials (:func:`sample_materials`; the second surfaces of ``boundary_mix`` too);
    ``min_lights``, ``max_lights``, ``cone_min_deg``, ``cone_max_deg``, ``sparse_fraction``,
    ``sparse_min_lights``: each pixel's light subset (:func:`light_subsets`). Steps:
    :func:`sample_normals`, :func:`sample_materials`, :func:`light_subsets`, :func:`shade`,
    effects (:class:`Effects`: mixing at depth discontinuities, cast shadows,
    inter-reflection, then gains, ambient, noise, then the camera: exposure, clipping,
    black level, quantisation, :func:`camera_response`), :func:`observation_maps_torch`.

    Order of the draws: lights (when None), normals, materials, light subsets, cast
    shadows (B x 4), inter-reflection (B x 7), gains (m), ambient (B), noise levels (B x 2),
    the noise field (B x m, or B x m x 3 with ``rgb``; drawn when ``noise`` or one of
    ``saturation``, ``quantisation``, ``boundary_mix`` is on), then, only when one of
    those three is on: the camera's uniforms (B x 5), the mixing uniforms (B x 2: which
    pixels, alpha), the second surfaces' normals and materials (B each), then, only when a
    share is under 1 or ``grazing_falloff`` is on, the shares' uniforms (B x 4). Every effect
    draws whether it is on or off, so turning one on changes no other draw; with the three
    at 0 (and the shares at 1, the falloff at 0) the generator's draws, and so the maps, are
    those of :class:`Effects` without them.

    ``rgb=True`` shades R, G, B (:func:`shade` with ``rgb=True``), applies every effect per
    channel (the inter-reflection's colour, the noise, the clip and the quantisation are per
    channel; the gains, the ambient level and the shadows are shared), and returns maps
    (B, 4, w, w): channel 0 the grey map (mean of R, G, B, as without ``rgb``), channels
    1-3 :func:`observation_maps_rgb_torch`. ``return_details=True`` adds a dict of the
    draws: params, category, mask (B, m), intensities ((B, m) or (B, m, 3): the values the
    maps are made of; with the camera effects in units of the camera's full scale), lights;
    with the camera effects ``camera`` (:func:`camera_response`'s dict); with
    ``boundary_mix`` ``mix`` (``mixed`` (B,) bool, ``alpha`` (B,) (1 where not mixed),
    ``normals``, ``params``, ``category`` of the second surfaces); with ``interreflection``
    ``interreflection`` (``strength`` r (B,), the neighbour's ``normal`` (B, 3) and
    ``colour`` ρ_n (B, 3), the pixel's ``reflectance`` ρ_pixel (B, 3); ``strength`` is 0
    on the pixels ``interreflection_share`` left out); with ``grazing_falloff``
    ``falloff_fd90`` (B,): each pixel's fd90, 1 where its diffuse is Lambert's.

    Example::

        g = torch.Generator().manual_seed(0)
        fx = Effects(cast_shadow=0.3, saturation=0.1, quantisation=0.5, boundary_mix=0.05)
        maps, normals = generate(256, generator=g, effects=fx)   # (256, 1, 32, 32), (256, 3)
    """
    if batch_size < 1:
        raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
    g = generator
    gdev = g.device
    L0 = _unit_lights(default_lights(g, n_lights) if lights is None else lights, gdev)
    B = batch_size
    normals = sample_normals(B, generator=g, device=gdev, grazing_fraction=grazing_fraction)
    params, cat = sample_materials(B, ranges=ranges, categories=categories, generator=g, device=gdev)
    mask = light_subsets(L0, B, generator=g, min_lights=min_lights, max_lights=max_lights, cone_min_deg=cone_min_deg,
                         cone_max_deg=cone_max_deg, sparse_fraction=sparse_fraction, sparse_min_lights=sparse_min_lights)
    fx = effects
    blocked, ir, gains, amb, s_noise, z_noise, later = draw_effects(fx, L0, B, g, rgb)
    if later:  # drawn only when one of these effects is on: at 0 they leave the generator as it was
        cam_u, mix_u, normals_b, params_b, cat_b = draw_camera_and_mix(B, g, grazing_fraction, ranges, categories)
    share_u = draw_shares(B, g) if fx.per_pixel_draws else None

    dev = torch.device(device)
    normals_d, L = normals.to(dev), L0.to(dev)
    params_d = {k: v.to(dev) for k, v in params.items()}
    mask_d = mask.to(dev)
    details = {}

    def per_light(x):  # (B, m) -> broadcastable against I
        return x[..., None] if rgb else x

    fd90 = None
    if fx.grazing_falloff:
        fd90 = falloff_fd90(fx, share_u).to(dev)
        details["falloff_fd90"] = fd90
    I = shade(normals_d, L, params_d, diffuse_model=diffuse_model, sheen_model=sheen_model, rgb=rgb, fd90=fd90)
    alpha = None
    if fx.boundary_mix:
        shading = {"diffuse_model": diffuse_model, "sheen_model": sheen_model, "rgb": rgb}
        I, details["mix"] = mix_boundaries(I, L, fx.boundary_mix, mix_u.to(dev), normals_b.to(dev),
                                            {k: v.to(dev) for k, v in params_b.items()}, cat_b, shading)
        alpha = details["mix"]["alpha"]
    if fx.cast_shadow:
        I = torch.where(per_light(blocked.to(dev)), torch.zeros_like(I), I)
    if fx.interreflection:
        rho_pix = diffuse_colour(params_d)
        if alpha is not None:
            al = alpha[:, None]
            rho_pix = al * rho_pix + (1.0 - al) * diffuse_colour(details["mix"]["params"])
        r = shared_level(fx.interreflection * ir[:, 0:1], fx.interreflection_share, share_u, 0)
        I, details["interreflection"] = interreflect(I, L, normals_d, rho_pix, r.to(dev), ir.to(dev), rgb)
    if fx.intensity_error:
        I = I * per_light(gains.to(dev)[None])
    if fx.ambient:
        I = apply_ambient(I, mask_d, shared_level(amb, fx.ambient_share, share_u, 1).to(dev), rgb)
    if fx.noise:
        I = apply_noise(I, mask_d, s_noise.to(dev), z_noise.to(dev), rgb)
    if fx.camera:
        I, details["camera"] = camera_response(I, mask_d, cam_u.to(dev), saturation=fx.saturation,
                                               quantisation=fx.quantisation)
    maps = _maps(I, L, w, mask_d, rgb)
    if return_details:
        details.update({"params": params_d, "category": cat, "mask": mask_d, "intensities": I, "lights": L})
        return maps, normals_d, details
    return maps, normals_d
