"""Blender 5's Principled BSDF in torch: the per-pixel generator's shading
(:func:`shade`), a twin of what Cycles renders for the materials
:func:`cnnps.synth.bsdf.to_blender_inputs` sets up (GGX with multiple-scattering energy
compensation, the dielectric Fresnel layer over a Lambertian or Burley diffuse, the
microfiber sheen), under suns of irradiance 1 seen from v = (0, 0, 1). How it agrees with
Cycles, and what is Cycles' and what the papers': ``docs/pixelwise.md``.

Frame: x right, y up, z toward the camera.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from cnnps.infra.errors import ConfigError


E_TABLE_SIZE = 32  # GGX directional albedo table: 32 roughness x 32 cos(view) nodes, like Cycles'


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
