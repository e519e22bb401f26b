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

This module takes every setting as an argument; its defaults are the paper's (every
category of :data:`cnnps.synth.bsdf.DEFAULT_CATEGORIES` at its default ranges, 50 to 1300
of 1300 lights in cones of 20 to 90 degrees). The train stage passes params.yaml's:
``materials.categories`` and ``materials.ranges``, extract's light-subset keys, and
``train.pixelwise``'s own (:func:`cnnps.train.loop.pixelwise_settings`).

Example::

    g = torch.Generator().manual_seed(0)
    maps, normals = generate(256, generator=g, effects=Effects(cast_shadow=0.3, ambient=0.05, quantisation=0.5))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from cnnps.infra.errors import ConfigError
from cnnps.synth.bsdf import DEFAULT_CATEGORIES, PARAM_NAMES, MaterialRanges
from cnnps.synth.lights import hemisphere_lights

DEFAULT_WIDTH = 32
E_TABLE_SIZE = 32  # GGX directional albedo table: 32 roughness x 32 cos(view) nodes, like Cycles'


# --------------------------------------------------------------------------- normals


def sample_normals(
    n: int, *, generator: torch.Generator, device="cpu", grazing_fraction: float = 0.1, grazing_max_nz: float = 0.3
) -> torch.Tensor:
    """(n, 3) float32 unit normals facing the camera (n_z > 0).

    Distribution: the normals a camera sees on real objects. A surface element with normal
    n covers an image area proportional to its projected area n_z, so over a closed convex
    object the visible normals have density ∝ n_z on the hemisphere (cosine-weighted; a
    sphere's image gives exactly this), NOT uniform over the solid angle (which would
    over-weight the limb by 1/n_z). Non-convex objects (DiLiGenT's) add occluding contours
    and creases, where n_z → 0 is more common than on a sphere, and the network's errors
    concentrate there; so a share ``grazing_fraction`` of the normals have n_z uniform in
    (0, ``grazing_max_nz``] (uniform azimuth), the rest are cosine-weighted.
    Draws (in order): n uniforms (which kind), 2n uniforms (cosine), 2n (grazing).
    """
    if not 0.0 <= grazing_fraction <= 1.0:
        raise ConfigError(f"grazing_fraction must be in [0, 1], got {grazing_fraction}")
    u = torch.rand(n, 3, generator=generator, device=device, dtype=torch.float64)
    kind = u[:, 0]
    # cosine-weighted: n_z = sqrt(1 - u) (Malley), azimuth uniform
    nz_cos = torch.sqrt(1.0 - u[:, 1])
    g = torch.rand(n, 1, generator=generator, device=device, dtype=torch.float64)[:, 0]
    nz_graze = (1.0 - g) * grazing_max_nz  # (0, max]
    nz = torch.where(kind < grazing_fraction, nz_graze, nz_cos).clamp(1e-3, 1.0)
    phi = 2.0 * math.pi * u[:, 2]
    r = torch.sqrt(torch.clamp(1.0 - nz * nz, min=0.0))
    out = torch.stack([r * torch.cos(phi), r * torch.sin(phi), nz], dim=1)
    return out.to(torch.float32)


# --------------------------------------------------------------------------- materials


def sample_materials(
    n: int,
    *,
    ranges: MaterialRanges | dict | None = None,
    categories=DEFAULT_CATEGORIES,
    generator: torch.Generator,
    device="cpu",
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """n paper-parameter rows (``base_color`` (n, 3), the others (n,), float32) and the
    category index of each row (into ``categories``, drawn uniformly).

    Uniform draws from ``ranges`` (a :class:`cnnps.synth.bsdf.MaterialRanges`, or a mapping
    of per-category overrides as params.yaml's ``materials.ranges``; None = the defaults)
    with the same rules as :func:`cnnps.synth.bsdf.sample_parameters`,
    including the near-mirror exclusion (specular > ``high_specular`` draws roughness above
    ``high_specular_min_roughness``), but from a torch generator and on ``device``."""
    if ranges is None:
        ranges = MaterialRanges()
    elif isinstance(ranges, dict):
        ranges = MaterialRanges.from_dict(ranges)
    cats = [ranges.get(c) for c in categories]
    if not cats:
        raise ConfigError("categories must name at least one material category")
    cat = torch.randint(len(cats), (n,), generator=generator, device=device)
    u = {
        "base_color": torch.rand(n, 3, generator=generator, device=device),
        **{k: torch.rand(n, generator=generator, device=device) for k in PARAM_NAMES[1:]},
    }

    def table(fn):
        return torch.tensor([fn(c) for c in cats], dtype=torch.float32, device=device)[cat]

    out = {}
    for name in PARAM_NAMES:
        lo = table(lambda c: getattr(c, name)[0])
        hi = table(lambda c: getattr(c, name)[1])
        uu = u[name]
        if uu.ndim == 2:
            lo, hi = lo[:, None], hi[:, None]
        out[name] = lo + uu * (hi - lo)
    r_lo = table(lambda c: c.roughness[0])
    r_hi = table(lambda c: c.roughness[1])
    floor = torch.maximum(r_lo, table(lambda c: c.high_specular_min_roughness))
    high = out["specular"] > table(lambda c: c.high_specular)
    out["roughness"] = torch.where(high & (floor > r_lo), floor + u["roughness"] * (r_hi - floor), out["roughness"])
    return out, cat


# --------------------------------------------------------------------------- Principled BSDF


def fresnel_dielectric(cos_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Unpolarised dielectric Fresnel reflectance (Cycles' ``fresnel_dielectric_cos``)."""
    c = cos_i.abs()
    g2 = eta * eta - 1.0 + c * c
    tir = g2 < 0
    g = torch.sqrt(g2.clamp(min=0.0))
    a = (g - c) / (g + c).clamp(min=1e-12)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    f = 0.5 * a * a * (1.0 + b * b)
    return torch.where(tir, torch.ones_like(f), f)


def ggx_d(alpha2: torch.Tensor, cos_nh: torch.Tensor) -> torch.Tensor:
    """GGX (Trowbridge-Reitz) normal distribution, ∫ D(h) (n·h) dh = 1."""
    c2 = cos_nh * cos_nh
    return alpha2 / (math.pi * (1.0 + (alpha2 - 1.0) * c2) ** 2)


def ggx_lambda(alpha2: torch.Tensor, cos_n: torch.Tensor) -> torch.Tensor:
    """Smith Λ of GGX (Heitz 2014, Eq. 72)."""
    c2 = (cos_n * cos_n).clamp(min=1e-12)
    return 0.5 * (torch.sqrt(1.0 + alpha2 * (1.0 / c2 - 1.0).clamp(min=0.0)) - 1.0)


def ggx_single(alpha2, cos_nh, cos_nv, cos_nl):
    """D G2 / (4 cos_nv): the single-scattering GGX lobe with F = 1, times cos_nl (the
    form Cycles' ``bsdf_microfacet_eval`` returns); height-correlated Smith G2."""
    g2 = 1.0 / (1.0 + ggx_lambda(alpha2, cos_nv) + ggx_lambda(alpha2, cos_nl))
    return ggx_d(alpha2, cos_nh) * g2 / (4.0 * cos_nv)


def _vndf_reflections(alpha: torch.Tensor, mu: torch.Tensor, u1: torch.Tensor, u2: torch.Tensor):
    """Heitz 2018 visible-normal sampling (as Cycles' ``microfacet_ggx_sample_vndf``) for
    the view (sqrt(1 - mu²), 0, mu) at points (u1, u2) of the unit square; returns (view ·
    microfacet normal, z of the reflected direction), broadcast over the inputs."""
    sin = torch.sqrt((1.0 - mu * mu).clamp(0.0, 1.0))
    vx, vz = alpha * sin, mu + 0.0 * alpha
    ln = torch.sqrt(vx * vx + vz * vz)
    vx, vz = vx / ln, vz / ln
    # T1 = (0, 1, 0) (the view has no y), T2 = Vh x T1 = (-vz, 0, vx)
    r = torch.sqrt(u1)
    phi = 2.0 * math.pi * u2
    t1 = r * torch.cos(phi)
    t2 = r * torch.sin(phi)
    s = 0.5 * (1.0 + vz)
    t2 = (1.0 - s) * torch.sqrt((1.0 - t1 * t1).clamp(min=0.0)) + s * t2
    wz = torch.sqrt((1.0 - t1 * t1 - t2 * t2).clamp(min=0.0))
    nx = -t2 * vz + wz * vx
    ny = t1
    nz = t2 * vx + wz * vz
    hx, hy, hz = alpha * nx, alpha * ny, nz.clamp(min=0.0)
    hl = torch.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hz = hx / hl, hz / hl
    cos_vh = sin * hx + mu * hz
    return cos_vh, 2.0 * cos_vh * hz - mu


def _grid(k: int, dtype=torch.float64, device="cpu"):
    u = (torch.arange(k, dtype=dtype, device=device) + 0.5) / k
    a, b = torch.meshgrid(u, u, indexing="ij")
    return a.reshape(1, -1), b.reshape(1, -1)


@lru_cache(maxsize=1)
def ggx_albedo_table(size: int = E_TABLE_SIZE, samples: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """(E (size, size) indexed [roughness node, cos(view) node], E_avg (size,)): the
    directional albedo of the single-scattering GGX lobe (F = 1) and its cosine-weighted
    average, on nodes roughness = sqrt(alpha) = i/(size-1), mu = j/(size-1), computed by
    stratified visible-normal quadrature (samples x samples points). Cycles' ``ggx_E`` and
    ``ggx_Eavg`` tables hold the same integrals on the same axes."""
    r = torch.linspace(0.0, 1.0, size, dtype=torch.float64)
    mu = torch.linspace(0.0, 1.0, size, dtype=torch.float64).clamp(min=1e-4)
    u1, u2 = _grid(samples)
    alpha = (r * r).clamp(min=1e-7)[:, None, None]
    a2 = alpha * alpha
    m = mu[None, :, None]
    _, oz = _vndf_reflections(alpha, m, u1[None], u2[None])
    li = ggx_lambda(a2, m)
    w = torch.where(oz > 0, (1.0 + li) / (1.0 + li + ggx_lambda(a2, oz.clamp(min=1e-6))), torch.zeros_like(oz))
    E = w.mean(dim=2)
    E[0, :] = 1.0  # a mirror reflects everything
    mus = torch.linspace(0.0, 1.0, size, dtype=torch.float64)
    E_avg = 2.0 * torch.trapezoid(E * mus[None, :], mus, dim=1)
    return E.numpy().astype(np.float32), E_avg.numpy().astype(np.float32)


def _ggx_energy(rough: torch.Tensor, mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """E(rough, mu) (bilinear) and E_avg(rough) (linear) from :func:`ggx_albedo_table`."""
    E_np, Eavg_np = ggx_albedo_table()
    E = torch.from_numpy(E_np).to(rough.device)
    Eavg = torch.from_numpy(Eavg_np).to(rough.device)
    n = E.shape[0]
    t = rough.clamp(0.0, 1.0) * (n - 1)
    i0 = t.floor().long().clamp(max=n - 2)
    f = t - i0
    s = mu.clamp(0.0, 1.0) * (n - 1)
    j0 = s.floor().long().clamp(max=n - 2)
    g = s - j0
    e = (E[i0, j0] * (1 - f) * (1 - g) + E[i0 + 1, j0] * f * (1 - g) + E[i0, j0 + 1] * (1 - f) * g
         + E[i0 + 1, j0 + 1] * f * g)
    ea = Eavg[i0] * (1 - f) + Eavg[i0 + 1] * f
    return e.clamp(min=1e-4), ea


def _multiscatter(rough, mu, Fss):
    """Cycles' ``microfacet_ggx_preserve_energy`` factor on the single-scattering lobe:
    1 + Fms (1 - E)/E with Fms = Fss E_avg / (1 - Fss (1 - E_avg)) (Kulla & Conty 2017);
    and E (the lobe's F = 1 albedo at this view). Fss (..., C)."""
    E, Eavg = _ggx_energy(rough, mu)
    missing = ((1.0 - E) / E)[..., None]
    Eavg = Eavg[..., None]
    Fms = Fss * Eavg / (1.0 - Fss * (1.0 - Eavg))
    return 1.0 + Fms * missing, E


def specular_eta(specular: torch.Tensor, ior: float = 1.5) -> torch.Tensor:
    """The IOR Cycles' Principled uses for ``IOR`` = ``ior`` and ``Specular IOR Level`` =
    ``specular`` (:func:`cnnps.synth.bsdf.to_blender_inputs`): F0 = F0(ior) · 2 · level,
    eta = (1 + √F0)/(1 − √F0); 1 (no specular layer) at level 0."""
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * specular.clamp(min=0.0)
    sf = torch.sqrt(f0.clamp(0.0, 0.999999))
    return (1.0 + sf) / (1.0 - sf)


def _fresnel_layer_average(alpha: torch.Tensor, mu: torch.Tensor, eta: torch.Tensor, k: int = 8) -> torch.Tensor:
    """(P,) the dielectric Fresnel averaged over the F = 1 GGX lobe seen from mu
    (the quantity of Cycles' ``ggx_gen_schlick_ior_s`` table), by k x k stratified
    visible-normal quadrature."""
    u1, u2 = _grid(k, alpha.dtype, alpha.device)
    a = alpha.clamp(min=1e-7)[:, None]
    m = mu[:, None]
    cos_vh, oz = _vndf_reflections(a, m, u1, u2)
    a2 = a * a
    li = ggx_lambda(a2, m)
    w = torch.where(oz > 0, (1.0 + li) / (1.0 + li + ggx_lambda(a2, oz.clamp(min=1e-6))), torch.zeros_like(oz))
    F = fresnel_dielectric(cos_vh, eta[:, None])
    return (F * w).sum(1) / w.sum(1).clamp(min=1e-12)


def kulla_conty_fss(eta: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted average of the dielectric Fresnel (Kulla & Conty 2017 fit, eta ≥ 1)."""
    return (eta - 1.0) / (4.08567 + 1.00071 * eta)


SHEEN_ROUGHNESS = 0.5  # the Principled BSDF's Sheen Roughness as cnnps.synth.bsdf sets it


def sheen_ltc(mu: torch.Tensor, roughness: float | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(a, b, R): the microfiber sheen's LTC coefficients and directional albedo at
    cos(n, v) = ``mu`` (Zeltner, Burley & Chiang 2022, "Practical Multiple-Scattering Sheen
    Using Linearly Transformed Cosines": their rational fits of the inverse matrix entries
    a = 1/M_00, b = -M_02/M_00 and their Gaussian fit of the albedo R, over the roughness
    range [0.01, 1]). Cycles reads the same quantities from a 32 x 32 table of the
    same data."""
    x = mu.clamp(0.0, 1.0)
    y = torch.as_tensor(roughness, dtype=mu.dtype, device=mu.device).clamp(0.01, 1.0)
    a = (2.58126 * x + 0.813703 * y) * y / (1.0 + 0.310327 * x * x + 2.60994 * x * y)
    b = torch.sqrt(1.0 - x) * (y - 1.0) * y ** 3 / (0.0000254053 + 1.71228 * x - 1.71506 * x * y + 1.34174 * y * y)
    s = y * (0.0206607 + 1.58491 * y) / (0.0379424 + y * (1.32227 + y))
    m = y * (-0.193854 + y * (-1.14885 + y * (1.7932 - 0.95943 * y * y))) / (0.046391 + y)
    o = y * (0.000654023 + (-0.0207818 + 0.119681 * y) * y) / (1.26264 + y * (-1.92021 + y))
    R = torch.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2.0 * math.pi)) + o
    return a, b, R.clamp(0.0, 1.0)


def microfiber_sheen(normals: torch.Tensor, L: torch.Tensor, roughness: float = SHEEN_ROUGHNESS,
                     cos_nl: torch.Tensor | None = None):
    """(π · BSDF · cos (P, m), albedo R (P, 1)) of the microfiber sheen lobe seen from
    v = (0, 0, 1): R · D_LTC(l), the clamped cosine transformed by the inverse matrix
    [[a, 0, b], [0, a, 0], [0, 0, 1]] in the frame whose x axis is v's tangential
    direction (:func:`sheen_ltc`); ``L`` (1 or P, m, 3) unit light directions;
    ``cos_nl`` (P, m) their cosines with the normals when the caller has them."""
    mu = normals[:, 2:3].clamp(min=1e-4)  # (P, 1)
    a, b, R = sheen_ltc(mu, roughness)
    z = (normals[:, None, :] * L).sum(-1) if cos_nl is None else cos_nl  # (P, m) = cos(n, l)
    s = torch.sqrt((1.0 - mu * mu).clamp(min=1e-12))
    x = (L[..., 2] - mu * z) / s  # l . X, X = (v - n mu) / |v - n mu|
    # |M^-1 l|^2 with x^2 + y^2 = 1 - z^2 (x matters only through b, which is 0 where n = v)
    len2 = a * a * (1.0 - z * z).clamp(min=0.0) + 2.0 * a * b * x * z + (b * b + 1.0) * z * z
    d = z.clamp(min=0.0) * (a / len2.clamp(min=1e-12)) ** 2  # π · D_LTC(l)
    return R * d, R


def _diffuse_lobe(diffuse_model: str, cnl, rough, cos_lh, cos_nv, fd90=None):
    """(P, m) the diffuse lobe times cos: Lambert's ``cnl``, or Burley 2012's with its
    retro-reflection (``rough`` (P,), ``cos_lh`` (P, m), ``cos_nv`` (P, 1)); ``fd90``
    (P,) or None: Lambert's lobe darkened toward grazing light by Burley's light factor
    1 + (fd90 - 1)(1 - cos)^5 at a fixed fd90 (1 = Lambert's)."""
    if diffuse_model == "lambert":
        if fd90 is not None:
            return cnl * (1.0 + (fd90.to(cnl.dtype)[:, None] - 1.0) * (1.0 - cnl) ** 5)
        return cnl
    if fd90 is not None:
        raise ConfigError("a grazing falloff (fd90) needs diffuse_model 'lambert'")
    if diffuse_model == "burley":
        fd90 = 0.5 + 2.0 * rough[:, None] * cos_lh * cos_lh
        fl = (1.0 - cnl) ** 5
        fv = (1.0 - cos_nv) ** 5
        return cnl * (1.0 + (fd90 - 1.0) * fl) * (1.0 + (fd90 - 1.0) * fv)
    raise ConfigError(f"diffuse_model must be 'lambert' or 'burley', got {diffuse_model!r}")


def shade(
    normals: torch.Tensor,
    lights: torch.Tensor,
    params: dict[str, torch.Tensor],
    *,
    diffuse_model: str = "lambert",
    sheen_model: str = "microfiber",
    multiscatter: bool = True,
    rgb: bool = False,
    fd90: torch.Tensor | None = None,
) -> torch.Tensor:
    """(P, m) grey pixel values (mean of R, G, B; ``rgb=True``: (P, m, 3)) of P surface
    points with unit ``normals`` (P, 3) under m suns of irradiance 1 from unit ``lights``
    (m, 3) or (P, m, 3), seen from v = (0, 0, 1); ``params`` the paper's parameters per
    point (``base_color`` (P, 3), the others (P,)). A white Lambertian patch facing a
    light reads 1 (the capture renderer's scale: pixel = π · BSDF · cos).

    The model is Blender 5's Principled BSDF as :func:`cnnps.synth.bsdf.to_blender_inputs`
    sets it up (``docs/pixelwise.md`` lists what is Cycles' and what is the papers'):
    metal (weight ``metallic``): GGX, F = Schlick(F0 = base_color) (F82-tint with a white
    tint), multiple scattering by energy compensation; dielectric (weight 1 − metallic):
    a GGX specular layer with the real dielectric Fresnel at the IOR that gives
    F0 = 0.08 · specular, the same compensation, over a diffuse base attenuated by the
    layer's albedo (Cycles' ``closure_layering_weight``); the diffuse is Lambertian
    (``diffuse_model="lambert"``, Blender's Diffuse Roughness 0) or Burley 2012 with its
    retro-reflection (``"burley"``, the paper's); ``fd90`` (P,) darkens the Lambertian
    diffuse toward grazing light by Burley's light factor 1 + (fd90 − 1)(1 − n·l)^5 alone
    (no retro-reflection; 1 leaves a point Lambertian). Sheen, weight sheen · (1 − metallic) and
    tint mix(white, base_color, sheen_tint): ``"microfiber"`` (Blender's: Zeltner et al.
    2022, :func:`microfiber_sheen`, roughness 0.5, a layer over everything else, which it
    attenuates by 1 − max over R, G, B of weight · tint · its albedo, as Cycles'
    ``closure_layering_weight``), ``"disney"`` (Burley 2012: sheen · tint · (1 − l·h)^5,
    added) or ``"none"``.
    """
    dt = normals.dtype
    n = normals[:, None, :]  # (P, 1, 3)
    L = lights if lights.ndim == 3 else lights[None]
    cos_nl = (n * L).sum(-1)  # (P, m)
    cos_nv = normals[:, 2:3].clamp(min=1e-4)  # (P, 1)
    hx, hy, hz = L[..., 0], L[..., 1], L[..., 2] + 1.0
    hl = torch.sqrt(hx * hx + hy * hy + hz * hz).clamp(min=1e-12)
    cos_nh = ((n[..., 0] * hx + n[..., 1] * hy + n[..., 2] * hz) / hl).clamp(min=0.0)
    cos_lh = (hz / hl)  # = v·h = l·h
    lit = (cos_nl > 0) & (normals[:, 2:3] > 0)
    cnl = cos_nl.clamp(min=0.0)

    base = params["base_color"].to(dt)  # (P, 3)
    metallic = params["metallic"].to(dt)[:, None]
    specular = params["specular"].to(dt)
    rough = params["roughness"].to(dt).clamp(0.0, 1.0)
    sheen = params["sheen"].to(dt)[:, None]
    sheen_tint = params["sheen_tint"].to(dt)[:, None]

    alpha = rough * rough
    a2 = (alpha * alpha)[:, None]
    singular = (alpha * alpha <= 5e-7)[:, None]  # Cycles evaluates no lobe this sharp
    lobe = ggx_single(a2, cos_nh, cos_nv, cnl) * ~singular  # (P, m)
    mu = cos_nv[:, 0]

    # metal: F82-tint with white tint = Schlick(F0 = base)
    schlick = (1.0 - cos_lh).clamp(0.0, 1.0) ** 5  # (P, m)
    if multiscatter:
        ms_metal, _ = _multiscatter(rough, mu, base + (1.0 - base) / 21.0)  # (P, 3)
    else:
        ms_metal = torch.ones_like(base)

    # dielectric specular layer
    eta = specular_eta(specular)
    F_d = fresnel_dielectric(cos_lh, eta[:, None])  # (P, m)
    if multiscatter:
        ms_d, E = _multiscatter(rough, mu, kulla_conty_fss(eta)[:, None])  # (P, 1)
    else:
        ms_d = torch.ones_like(mu)[:, None]
        E, _ = _ggx_energy(rough, mu)
    has_spec = eta > 1.0 + 1e-6
    layer_albedo = torch.where(
        has_spec & ~singular[:, 0], (E * ms_d[:, 0]) * _fresnel_layer_average(alpha, mu, eta), torch.zeros_like(mu)
    )
    layer_albedo = torch.where(singular[:, 0] & has_spec, fresnel_dielectric(mu, eta), layer_albedo)
    diffuse_w = (1.0 - layer_albedo).clamp(0.0, 1.0)[:, None]  # (P, 1)

    fd = _diffuse_lobe(diffuse_model, cnl, rough, cos_lh, cos_nv, fd90)
    if sheen_model not in ("microfiber", "disney", "none"):
        raise ConfigError(f"sheen_model must be 'microfiber', 'disney' or 'none', got {sheen_model!r}")
    tint = 1.0 + sheen_tint * (base - 1.0)  # (P, 3)
    w_sheen = (sheen * (1.0 - metallic)) * tint if sheen_model != "none" else torch.zeros_like(base)
    if sheen_model == "microfiber":
        sheen_lobe, sheen_albedo = microfiber_sheen(normals, L, cos_nl=cos_nl)  # (P, m), (P, 1)
        below = (1.0 - (w_sheen * sheen_albedo).amax(1, keepdim=True)).clamp(0.0, 1.0)  # (P, 1)
    else:
        sheen_lobe, below = schlick * cnl, torch.ones_like(mu)[:, None]
    d = (1.0 - metallic) * below  # (P, 1)
    metallic = metallic * below
    if rgb:
        F_metal = base[:, None, :] + (1.0 - base[:, None, :]) * schlick[..., None]
        out = (d[..., None] * ((diffuse_w * fd)[..., None] * base[:, None, :] + (math.pi * F_d * lobe * ms_d)[..., None])
               + metallic[..., None] * math.pi * F_metal * (lobe[..., None] * ms_metal[:, None, :])
               + w_sheen[:, None, :] * sheen_lobe[..., None])
        return out * lit[..., None]
    # grey = mean over R, G, B; every term is linear in a per-pixel colour, so the mean
    # is taken on the (P,) coefficients and the (P, m) work is done once
    c_diff = d * diffuse_w * base.mean(1, keepdim=True)
    c_spec = d * math.pi * ms_d
    c_m0 = metallic * math.pi * (base * ms_metal).mean(1, keepdim=True)
    c_m1 = metallic * math.pi * ((1.0 - base) * ms_metal).mean(1, keepdim=True)
    c_sheen = w_sheen.mean(1, keepdim=True)
    out = c_diff * fd + lobe * (c_spec * F_d + c_m0 + c_m1 * schlick) + c_sheen * sheen_lobe
    return out * lit


# --------------------------------------------------------------------------- light subsets


def light_subsets(
    lights: torch.Tensor,
    n: int,
    *,
    generator: torch.Generator,
    min_lights: int = 50,
    max_lights: int = 1300,
    cone_min_deg: float = 20.0,
    cone_max_deg: float = 90.0,
    sparse_fraction: float = 0.0,
    sparse_min_lights: int = 6,
) -> torch.Tensor:
    """(n, m) bool per-pixel light subsets by the extract rules
    (:func:`cnnps.synth.training_samples.sample_light_masks`): a cone about +z of
    half-angle U(cone_min_deg, cone_max_deg), widened to hold min(min_lights, m) lights,
    k ~ U{min(min_lights, m) .. min(max_lights, m)} lights of it at random; a share
    ``sparse_fraction`` of pixels use k log-uniform in [sparse_min_lights, min_lights)
    (:func:`cnnps.synth.training_samples.sparse_subset_sizes`'s law)."""
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


# --------------------------------------------------------------------------- effects


EFFECT_NAMES = ("cast_shadow", "interreflection", "ambient", "intensity_error", "noise", "saturation",
                "quantisation", "boundary_mix", "interreflection_share", "ambient_share",
                "grazing_falloff")  # the fields of Effects, in order
SATURATION_RANGE = (1.0, 4.0)  # a saturated pixel's brightest observation lands at k x clip, k log-uniform here
EXPOSURE_RANGE = (1.0 / 64.0, 0.5)  # an unsaturated quantised pixel's brightest lands at k x full scale
BLACK_LEVEL_MAX = 2.0 / 255.0  # black-level offset U(-max, max) of full scale per quantised pixel
EIGHT_BIT_SHARE = 0.5  # share of quantised pixels stored in 8 bits (255 levels); the rest 16 bits (65535)
MIX_ALPHA_RANGE = (0.5, 1.0)  # foreground weight of a pixel straddling a depth discontinuity
FD90_RANGE = (0.3, 1.0)  # Burley's grazing factor fd90 of a pixel whose diffuse falls off, uniform here


@dataclass(frozen=True)
class Effects:
    """Global effects and capture realism, each off at 0 (probabilities and strengths in [0, 1];
    the two shares are on at 1, every pixel).

    - ``cast_shadow``: probability that a pixel has an occluder: a spherical cap of
      directions (axis at a random azimuth, elevation U(0°, 45°), half-angle U(20°, 60°))
      whose lights reach the pixel only through the ambient and indirect terms;
    - ``interreflection``: light bounced off a nearby lit surface of a random colour
      (random normal facing the pixel's hemisphere, RGB albedo ρ_n ~ U(0, 1)^3): per pixel
      r ~ U(0, interreflection) and indirect value r · ρ_pixel · ρ_n · max(0, n_n · l) per
      channel (ρ_pixel the pixel's diffuse, or for metals its base, colour); grey maps
      take the mean over R, G, B of this coloured term, RGB maps keep it per channel;
    - ``ambient``: a ~ U(0, ambient) per pixel times the pixel's brightest chosen value,
      added to every light (as :func:`cnnps.synth.training_samples.add_ambient`);
    - ``intensity_error``: per batch and light factor max(1 + N(0, σ), 0)
      (:func:`cnnps.synth.training_samples.light_gains`' law);
    - ``noise``: read and shot noise with per-pixel levels U(0, noise)
      (:func:`cnnps.synth.training_samples.add_noise`'s law), clipped at 0;
    - ``saturation``: probability that a pixel is over-exposed: its values are multiplied
      by an exposure that puts its brightest chosen value at k times the clip level 1,
      k log-uniform in :data:`SATURATION_RANGE`, and clipped at 1 (each channel in RGB);
    - ``quantisation``: probability that a pixel is stored as an integer image: an
      exposure puts its brightest chosen value at k of full scale (k as for
      ``saturation`` when the pixel is saturated, else log-uniform in
      :data:`EXPOSURE_RANGE`), a black-level offset U(-:data:`BLACK_LEVEL_MAX`,
      :data:`BLACK_LEVEL_MAX`) is added, values are clamped to [0, 1] and rounded to
      8 bits (1/255 steps, share :data:`EIGHT_BIT_SHARE`) or 16 bits (1/65535);
    - ``boundary_mix``: probability that a pixel straddles a depth discontinuity: its
      direct shading is alpha · (its own surface) + (1 − alpha) · (a second surface with
      an independently drawn normal and material), alpha ~ U(:data:`MIX_ALPHA_RANGE`);
      the target normal stays the first (foreground) surface's;
    - ``interreflection_share`` and ``ambient_share``: the probability that a pixel gets
      the inter-reflection, or the ambient term, at all (1: every pixel, as the two
      strengths alone mean); a real object's convex parts see neither, and every pixel
      lifted by them teaches the network maps no convex pixel shows;
    - ``grazing_falloff``: probability that a pixel's diffuse darkens toward grazing light
      as real matte surfaces do (DiLiGenT's BALL): Lambert's lobe times
      1 + (fd90 − 1)(1 − n·l)^5, fd90 ~ U(:data:`FD90_RANGE`) per pixel (``shade``'s
      ``fd90``; needs ``diffuse_model="lambert"``).

    Example: ``Effects(cast_shadow=0.3, saturation=0.1, quantisation=0.5, boundary_mix=0.05)``;
    ``Effects(interreflection=0.3, interreflection_share=0.3, grazing_falloff=0.3)``.
    """

    cast_shadow: float = 0.0
    interreflection: float = 0.0
    ambient: float = 0.0
    intensity_error: float = 0.0
    noise: float = 0.0
    saturation: float = 0.0
    quantisation: float = 0.0
    boundary_mix: float = 0.0
    interreflection_share: float = 1.0
    ambient_share: float = 1.0
    grazing_falloff: float = 0.0

    def __post_init__(self):
        for name in EFFECT_NAMES:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ConfigError(f"pixelwise effect {name} must be in [0, 1], got {v!r}")

    @property
    def camera(self) -> bool:
        """True when a pixel may be exposed, clipped or quantised."""
        return bool(self.saturation or self.quantisation)

    @property
    def per_pixel_draws(self) -> bool:
        """True when the shares or the grazing falloff need draws of their own."""
        return self.interreflection_share < 1.0 or self.ambient_share < 1.0 or self.grazing_falloff > 0.0


def cast_shadow_mask(lights: torch.Tensor, n: int, probability: float, *, generator: torch.Generator) -> torch.Tensor:
    """(n, m) bool, True where the light is blocked by the pixel's occluder (see :class:`Effects`)."""
    dev = lights.device
    u = torch.rand(n, 4, generator=generator, device=dev)
    has = u[:, 0] < probability
    if not probability:
        return torch.zeros(n, lights.shape[0], dtype=torch.bool, device=dev)
    az = 2.0 * math.pi * u[:, 1]
    el = torch.deg2rad(45.0 * u[:, 2])
    half = torch.deg2rad(20.0 + 40.0 * u[:, 3])
    axis = torch.stack([torch.cos(el) * torch.cos(az), torch.cos(el) * torch.sin(az), torch.sin(el)], 1).to(lights.dtype)
    inside = (axis @ lights.T) >= torch.cos(half).to(lights.dtype)[:, None]
    return inside & has[:, None]


def camera_response(
    intensities: torch.Tensor, light_mask: torch.Tensor, u: torch.Tensor, *, saturation: float, quantisation: float
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The ``saturation`` and ``quantisation`` effects of :class:`Effects` on P pixels.

    ``intensities`` (P, m) grey or (P, m, C) per-channel values (≥ 0), ``light_mask``
    (P, m) bool (the chosen lights), ``u`` (P, 5) uniforms in [0, 1) on the same device:
    column 0 picks the saturated pixels (u < ``saturation``), 1 the exposure level, 2 the
    quantised pixels (u < ``quantisation``), 3 the bit depth (u < :data:`EIGHT_BIT_SHARE`:
    8 bits), 4 the black level. A pixel that is saturated or quantised (or both) is
    multiplied by its exposure e = k / peak, peak its brightest value over the chosen
    lights (and channels), k log-uniform in :data:`SATURATION_RANGE` (saturated) or
    :data:`EXPOSURE_RANGE` (otherwise); a quantised pixel then gets the black level
    b = :data:`BLACK_LEVEL_MAX` · (2 u₄ − 1); values are clamped to [0, 1] (the clip at 1
    is the saturation), and a quantised pixel's are rounded to multiples of 1/255 or
    1/65535. Other pixels are returned unchanged.

    Returns (values of the same shape, in units of the full scale 1 where changed;
    ``{"exposure" (P,) (1 where unchanged), "saturated" (P,) bool, "bits" (P,) int64
    (8, 16, or 0: not quantised), "black_level" (P,)}``).

    Example::

        I2, cam = camera_response(I, mask, torch.rand(len(I), 5, generator=g), saturation=0.1, quantisation=0.5)
    """
    I = intensities
    P = I.shape[0]
    shp = (P,) + (1,) * (I.ndim - 1)
    sat = u[:, 0] < saturation
    qnt = u[:, 2] < quantisation
    (s0, s1), (e0, e1) = SATURATION_RANGE, EXPOSURE_RANGE
    log_k = torch.where(sat, math.log(s0) + u[:, 1] * (math.log(s1) - math.log(s0)),
                        math.log(e0) + u[:, 1] * (math.log(e1) - math.log(e0)))
    chosen = light_mask if I.ndim == 2 else light_mask[..., None]
    peak = torch.where(chosen, I, torch.zeros_like(I)).reshape(P, -1).amax(1)
    on = sat | qnt
    exposure = torch.where(on & (peak > 0), torch.exp(log_k).to(I.dtype) / peak.clamp(min=1e-30),
                           torch.ones_like(peak))
    eight = u[:, 3] < EIGHT_BIT_SHARE
    bits = torch.where(qnt, torch.where(eight, 8, 16), 0)
    black = torch.where(qnt, BLACK_LEVEL_MAX * (2.0 * u[:, 4] - 1.0), torch.zeros_like(u[:, 4])).to(I.dtype)
    levels = torch.where(eight, 255.0, 65535.0).to(I.dtype).view(shp)
    x = (I * exposure.view(shp) + black.view(shp)).clamp(0.0, 1.0)
    x = torch.where(qnt.view(shp), torch.round(x * levels) / levels, x)
    out = torch.where(on.view(shp), x, I)
    return out, {"exposure": exposure, "saturated": sat, "bits": bits, "black_level": black}


# --------------------------------------------------------------------------- observation maps


def light_cells_torch(lights: torch.Tensor, w: int = DEFAULT_WIDTH) -> torch.Tensor:
    """(m,) or (..., m) flat cell index row * w + col of unit directions, as
    :func:`cnnps.ps.obsmap.light_cells` (computed in float64, truncated, clipped)."""
    L = lights.to(torch.float64)
    col = (w * (L[..., 0] + 1.0) / 2.0).long().clamp(0, w - 1)
    row = (w * (L[..., 1] + 1.0) / 2.0).long().clamp(0, w - 1)
    return row * w + col


def _cell_means(intensities: torch.Tensor, lights: torch.Tensor, w: int, light_mask: torch.Tensor | None):
    """(P, w * w) float32: per cell the mean of max(I, 0) over the chosen lights in it (0 if none)."""
    I = intensities.to(torch.float32)
    P, m = I.shape
    v = I.clamp(min=0.0)
    v = torch.where(torch.isnan(v), torch.zeros_like(v), v)
    if light_mask is not None:
        v = torch.where(light_mask, v, torch.zeros_like(v))
        cnt = light_mask.to(torch.float32)
    else:
        cnt = torch.ones_like(v)
    cell = light_cells_torch(lights, w)
    cell = cell.expand(P, m) if cell.ndim == 1 else cell
    sums = torch.zeros(P, w * w, dtype=torch.float32, device=I.device).scatter_add_(1, cell, v)
    counts = torch.zeros(P, w * w, dtype=torch.float32, device=I.device).scatter_add_(1, cell, cnt)
    return sums / counts.clamp(min=1.0)


def observation_maps_torch(
    intensities: torch.Tensor, lights: torch.Tensor, w: int = DEFAULT_WIDTH, light_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """(P, w, w) float32 maps, the rule of :func:`cnnps.ps.obsmap.observation_maps`:
    values max(I, 0) (0 where ``light_mask`` is False), summed per cell and divided by the
    number of lights used in it, each map divided by its largest cell (an all-dark map stays
    0). ``lights`` (m, 3) shared, or (P, m, 3) per pixel."""
    P = intensities.shape[0]
    maps = _cell_means(intensities, lights, w, light_mask)
    peak = maps.amax(1, keepdim=True)
    maps = maps / torch.where(peak > 0, peak, torch.ones_like(peak))
    return maps.view(P, w, w)


def observation_maps_rgb_torch(
    intensities: torch.Tensor, lights: torch.Tensor, w: int = DEFAULT_WIDTH, light_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """(P, C, w, w) float32 colour maps of ``intensities`` (P, m, C) (C = 3: R, G, B): each
    channel by the rule of :func:`observation_maps_torch`, all channels of a pixel divided
    by one number, the largest cell over its channels (so the map keeps the pixel's colour;
    an all-dark pixel stays 0). ``lights`` (m, 3) shared, or (P, m, 3) per pixel;
    ``light_mask`` (P, m)."""
    P, m, C = intensities.shape
    I = intensities.permute(0, 2, 1).reshape(P * C, m)
    L = lights if lights.ndim == 2 else lights.repeat_interleave(C, 0)
    mk = None if light_mask is None else light_mask.repeat_interleave(C, 0)
    maps = _cell_means(I, L, w, mk).view(P, C * w * w)
    peak = maps.amax(1, keepdim=True)
    maps = maps / torch.where(peak > 0, peak, torch.ones_like(peak))
    return maps.view(P, C, w, w)


# --------------------------------------------------------------------------- the generator


def default_lights(generator: torch.Generator, n: int = 1300, jitter_deg: float = 3.0, min_elevation_deg: float = 5.0):
    """(n, 3) float64 numpy light set for one batch: :func:`cnnps.synth.lights.hemisphere_lights`
    (the render stage's jittered spiral) with a seed drawn from ``generator``."""
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device).item())
    return hemisphere_lights(n, jitter_deg, seed=seed, min_elevation_deg=min_elevation_deg)


def _diffuse_colour(params: dict[str, torch.Tensor]) -> torch.Tensor:
    """(P, 3) the colour a surface reflects indirect light with: its diffuse colour, or for
    metals (metallic > 0.5) its base colour."""
    return torch.where(params["metallic"][:, None] > 0.5, params["base_color"],
                       params["base_color"] * (1.0 - params["metallic"][:, None]))


def _draw_effects(fx: Effects, L0, B: int, g: torch.Generator, rgb: bool):
    """The draws every effect makes whether on or off (so turning one on changes no other
    draw), in order: cast shadows (B, m) blocked, inter-reflection uniforms (B, 7), light
    gains (m,), ambient levels (B, 1), noise levels (B, 2), the noise field (B, m[, 3]) or
    None, and whether the later draws (camera, boundary mixing) are due."""
    gdev = g.device
    m = L0.shape[0]
    blocked = cast_shadow_mask(L0, B, fx.cast_shadow, generator=g)
    ir = torch.rand(B, 7, generator=g, device=gdev)
    gains = torch.clamp(1.0 + fx.intensity_error * torch.randn(m, generator=g, device=gdev), min=0.0)
    amb = fx.ambient * torch.rand(B, 1, generator=g, device=gdev)
    s_noise = fx.noise * torch.rand(B, 2, generator=g, device=gdev)
    later = fx.camera or bool(fx.boundary_mix)
    chans = (3,) if rgb else ()
    z_noise = torch.randn(B, m, *chans, generator=g, device=gdev) if (fx.noise or later) else None
    return blocked, ir, gains, amb, s_noise, z_noise, later


def _draw_camera_and_mix(B: int, g: torch.Generator, grazing_fraction: float, ranges, categories):
    """The draws of the camera and boundary-mixing effects, in order: the camera's
    uniforms (B, 5), the mixing uniforms (B, 2), the second surfaces' normals, materials
    and categories."""
    cam_u = torch.rand(B, 5, generator=g, device=g.device)
    mix_u = torch.rand(B, 2, generator=g, device=g.device)
    normals_b = sample_normals(B, generator=g, device=g.device, grazing_fraction=grazing_fraction)
    params_b, cat_b = sample_materials(B, ranges=ranges, categories=categories, generator=g, device=g.device)
    return cam_u, mix_u, normals_b, params_b, cat_b


def _draw_shares(B: int, g: torch.Generator):
    """The draws of the shares and the grazing falloff (B, 4): which pixels get the
    inter-reflection (column 0 < share), the ambient term (1), a falloff (2), and its fd90 (3);
    made last, and only when one of them is on (:attr:`Effects.per_pixel_draws`)."""
    return torch.rand(B, 4, generator=g, device=g.device)


def _falloff_fd90(fx: Effects, u: torch.Tensor) -> torch.Tensor:
    """(B,) each pixel's fd90: drawn in FD90_RANGE where ``u[:, 2] < grazing_falloff``, else 1."""
    lo, hi = FD90_RANGE
    return torch.where(u[:, 2] < fx.grazing_falloff, lo + (hi - lo) * u[:, 3], torch.ones_like(u[:, 3]))


def _add_noise(I, mask, s, z, rgb: bool):
    """I plus signal-dependent noise: variance (s0 peak)^2 + s1^2 peak I, ``peak`` each
    pixel's brightest used value (grey), ``z`` the standard normal field; clamped at 0."""
    grey = I.mean(-1) if rgb else I
    peak = torch.where(mask, grey, torch.zeros_like(mask, dtype=I.dtype)).amax(1)
    if rgb:
        peak = peak[:, None, None]
        var = (s[:, 0, None, None] * peak) ** 2 + (s[:, 1, None, None] ** 2 * peak) * I.clamp(min=0.0)
    else:
        var = (s[:, 0] * peak)[:, None] ** 2 + (s[:, 1] ** 2 * peak)[:, None] * I.clamp(min=0.0)
    return (I + torch.sqrt(var) * z).clamp(min=0.0)


def _mix_boundaries(I, L, share: float, mix_u, normals_b, params_b, cat_b, shading: dict):
    """(I with a ``share`` of the pixels mixed with a second surface, the mix's details):
    a pixel is mixed where ``mix_u[:, 0] < share``, with weight alpha drawn in
    MIX_ALPHA_RANGE from ``mix_u[:, 1]`` on its own values and 1 - alpha on those of the
    second surface (``normals_b``, ``params_b``) under the same lights ``L``."""
    B = I.shape[0]
    mixed = mix_u[:, 0] < share
    a0, a1 = MIX_ALPHA_RANGE
    alpha = torch.where(mixed, a0 + (a1 - a0) * mix_u[:, 1], torch.ones(B, device=I.device))
    idx = torch.nonzero(mixed)[:, 0]
    if idx.numel():
        Ib = shade(normals_b[idx], L, {k: v[idx] for k, v in params_b.items()}, **shading)
        a = alpha[idx].view(-1, *([1] * (I.ndim - 1)))
        I = I.index_copy(0, idx, a * I[idx] + (1.0 - a) * Ib)
    return I, {"mixed": mixed, "alpha": alpha, "normals": normals_b, "params": params_b, "category": cat_b}


def _interreflect(I, L, normals, rho_pix, r, ir, rgb: bool):
    """(I plus light bounced off a neighbour, the bounce's details): the neighbour's normal
    is the pixel's turned by up to 90 degrees toward a random azimuth (``ir[:, 1:3]``), its
    RGB albedo ``ir[:, 3:6]`` colours the bounce; ``r`` (B, 1) its strength, ``rho_pix``
    (B, 3) the pixel's diffuse colour."""
    az = 2.0 * math.pi * ir[:, 1]
    tilt = 0.5 * math.pi * ir[:, 2]
    t = torch.stack([torch.cos(az), torch.sin(az), torch.zeros_like(az)], 1)
    t = t - (t * normals).sum(1, keepdim=True) * normals
    t = t / t.norm(dim=1, keepdim=True).clamp(min=1e-6)
    n2 = torch.cos(tilt)[:, None] * normals + torch.sin(tilt)[:, None] * t
    rho2 = ir[:, 3:6]  # the neighbour's RGB albedo: the bounced light's colour
    lit2 = (n2 @ L.T).clamp(min=0.0)  # (B, m)
    if rgb:
        I = I + (r * lit2)[..., None] * (rho_pix * rho2)[:, None, :]
    else:
        I = I + r * (rho_pix * rho2).mean(1, keepdim=True) * lit2
    return I, {"strength": r[:, 0], "normal": n2, "colour": rho2, "reflectance": rho_pix}


def _unit_lights(lights, device) -> torch.Tensor:
    """(m, 3) float32 unit directions on ``device`` (the generator's, where draws are made)."""
    L0 = lights if torch.is_tensor(lights) else torch.as_tensor(np.asarray(lights))
    L0 = L0.to(device, torch.float32)
    return L0 / L0.norm(dim=1, keepdim=True)


def _shared(level: torch.Tensor, share: float, share_u, column: int) -> torch.Tensor:
    """``level`` (B, 1), zero on the pixels a ``share`` under 1 leaves out (``share_u``'s
    ``column`` at or over it)."""
    if share >= 1.0:
        return level
    return level * (share_u[:, column:column + 1] < share).to(level.device)


def _add_ambient(I, mask, amb: torch.Tensor, rgb: bool) -> torch.Tensor:
    """``I`` plus ambient light ``amb`` (B, 1) times each pixel's brightest used grey value."""
    grey = I.mean(-1) if rgb else I
    top = torch.where(mask, grey, torch.zeros_like(mask, dtype=I.dtype)).amax(1, keepdim=True)
    return I + ((amb * top)[..., None] if rgb else amb * top)


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
    min_lights: int = 50,
    max_lights: int = 1300,
    cone_min_deg: float = 20.0,
    cone_max_deg: float = 90.0,
    sparse_fraction: float = 0.0,
    sparse_min_lights: int = 6,
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
    blocked, ir, gains, amb, s_noise, z_noise, later = _draw_effects(fx, L0, B, g, rgb)
    if later:  # drawn only when one of these effects is on: at 0 they leave the generator as it was
        cam_u, mix_u, normals_b, params_b, cat_b = _draw_camera_and_mix(B, g, grazing_fraction, ranges, categories)
    share_u = _draw_shares(B, g) if fx.per_pixel_draws else None

    dev = torch.device(device)
    normals_d, L = normals.to(dev), L0.to(dev)
    params_d = {k: v.to(dev) for k, v in params.items()}
    mask_d = mask.to(dev)
    details = {}

    def per_light(x):  # (B, m) -> broadcastable against I
        return x[..., None] if rgb else x

    fd90 = None
    if fx.grazing_falloff:
        fd90 = _falloff_fd90(fx, share_u).to(dev)
        details["falloff_fd90"] = fd90
    I = shade(normals_d, L, params_d, diffuse_model=diffuse_model, sheen_model=sheen_model, rgb=rgb, fd90=fd90)
    alpha = None
    if fx.boundary_mix:
        shading = {"diffuse_model": diffuse_model, "sheen_model": sheen_model, "rgb": rgb}
        I, details["mix"] = _mix_boundaries(I, L, fx.boundary_mix, mix_u.to(dev), normals_b.to(dev),
                                            {k: v.to(dev) for k, v in params_b.items()}, cat_b, shading)
        alpha = details["mix"]["alpha"]
    if fx.cast_shadow:
        I = torch.where(per_light(blocked.to(dev)), torch.zeros_like(I), I)
    if fx.interreflection:
        rho_pix = _diffuse_colour(params_d)
        if alpha is not None:
            al = alpha[:, None]
            rho_pix = al * rho_pix + (1.0 - al) * _diffuse_colour(details["mix"]["params"])
        r = _shared(fx.interreflection * ir[:, 0:1], fx.interreflection_share, share_u, 0)
        I, details["interreflection"] = _interreflect(I, L, normals_d, rho_pix, r.to(dev), ir.to(dev), rgb)
    if fx.intensity_error:
        I = I * per_light(gains.to(dev)[None])
    if fx.ambient:
        I = _add_ambient(I, mask_d, _shared(amb, fx.ambient_share, share_u, 1).to(dev), rgb)
    if fx.noise:
        I = _add_noise(I, mask_d, s_noise.to(dev), z_noise.to(dev), rgb)
    if fx.camera:
        I, details["camera"] = camera_response(I, mask_d, cam_u.to(dev), saturation=fx.saturation,
                                               quantisation=fx.quantisation)
    maps = _maps(I, L, w, mask_d, rgb)
    if return_details:
        details.update({"params": params_d, "category": cat, "mask": mask_d, "intensities": I, "lights": L})
        return maps, normals_d, details
    return maps, normals_d
