"""The steps of the per-pixel generator's effects (their settings:
:class:`cnnps.synth.effect_settings.Effects`): cast shadows, inter-reflection, light-intensity errors, ambient light, noise, the camera
(exposure, clipping, black level, quantisation: :func:`camera_response`) and pixels that
mix two surfaces at depth discontinuities; their laws are those of the shard path
(:mod:`cnnps.synth.training_samples`) where it has them.

:func:`cnnps.synth.pixelwise.generate` makes the draws (``draw_*``, in a fixed order,
whether an effect is on or off) and applies the steps in its order; the draws' order is
part of the seeded output and documented there.
"""

from __future__ import annotations

import math

import torch

from cnnps.synth.effect_settings import (
    BLACK_LEVEL_MAX,
    EIGHT_BIT_SHARE,
    EXPOSURE_RANGE,
    FD90_RANGE,
    MIX_ALPHA_RANGE,
    SATURATION_RANGE,
    Effects,
)
from cnnps.synth.principled_torch import shade
from cnnps.synth.surface_samples import sample_materials, sample_normals


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


def diffuse_colour(params: dict[str, torch.Tensor]) -> torch.Tensor:
    """(P, 3) the colour a surface reflects indirect light with: its diffuse colour, or for
    metals (metallic > 0.5) its base colour."""
    return torch.where(params["metallic"][:, None] > 0.5, params["base_color"],
                       params["base_color"] * (1.0 - params["metallic"][:, None]))


def draw_effects(fx: Effects, L0, B: int, g: torch.Generator, rgb: bool):
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


def draw_camera_and_mix(B: int, g: torch.Generator, grazing_fraction: float, ranges, categories):
    """The draws of the camera and boundary-mixing effects, in order: the camera's
    uniforms (B, 5), the mixing uniforms (B, 2), the second surfaces' normals, materials
    and categories."""
    cam_u = torch.rand(B, 5, generator=g, device=g.device)
    mix_u = torch.rand(B, 2, generator=g, device=g.device)
    normals_b = sample_normals(B, generator=g, device=g.device, grazing_fraction=grazing_fraction)
    params_b, cat_b = sample_materials(B, ranges=ranges, categories=categories, generator=g, device=g.device)
    return cam_u, mix_u, normals_b, params_b, cat_b


def draw_shares(B: int, g: torch.Generator):
    """The draws of the shares and the grazing falloff (B, 4): which pixels get the
    inter-reflection (column 0 < share), the ambient term (1), a falloff (2), and its fd90 (3);
    made last, and only when one of them is on (:attr:`Effects.per_pixel_draws`)."""
    return torch.rand(B, 4, generator=g, device=g.device)


def falloff_fd90(fx: Effects, u: torch.Tensor) -> torch.Tensor:
    """(B,) each pixel's fd90: drawn in FD90_RANGE where ``u[:, 2] < grazing_falloff``, else 1."""
    lo, hi = FD90_RANGE
    return torch.where(u[:, 2] < fx.grazing_falloff, lo + (hi - lo) * u[:, 3], torch.ones_like(u[:, 3]))


def apply_noise(I, mask, s, z, rgb: bool):
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


def mix_boundaries(I, L, share: float, mix_u, normals_b, params_b, cat_b, shading: dict):
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


def interreflect(I, L, normals, rho_pix, r, ir, rgb: bool):
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


def shared_level(level: torch.Tensor, share: float, share_u, column: int) -> torch.Tensor:
    """``level`` (B, 1), zero on the pixels a ``share`` under 1 leaves out (``share_u``'s
    ``column`` at or over it)."""
    if share >= 1.0:
        return level
    return level * (share_u[:, column:column + 1] < share).to(level.device)


def apply_ambient(I, mask, amb: torch.Tensor, rgb: bool) -> torch.Tensor:
    """``I`` plus ambient light ``amb`` (B, 1) times each pixel's brightest used grey value."""
    grey = I.mean(-1) if rgb else I
    top = torch.where(mask, grey, torch.zeros_like(mask, dtype=I.dtype)).amax(1, keepdim=True)
    return I + ((amb * top)[..., None] if rgb else amb * top)
