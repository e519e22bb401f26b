"""What a per-pixel observation is of: normals as a camera sees them, and materials drawn
from the BSDF ranges, in torch from a seeded generator, on CPU or CUDA (the first draws of
:func:`cnnps.synth.pixelwise.generate`).

- :func:`sample_normals` ``(n, *, generator)`` -> (n, 3) unit normals facing the camera,
  cosine-weighted with a share near grazing;
- :func:`sample_materials` ``(n, *, ranges, categories, generator)`` -> the paper's BSDF
  parameters per row and each row's category, by the rules of
  :func:`cnnps.synth.bsdf.sample_parameters`.

Frame: x right, y up, z toward the camera.
"""

from __future__ import annotations

import math

import torch

from cnnps.infra.errors import ConfigError
from cnnps.synth.bsdf import DEFAULT_CATEGORIES, PARAM_NAMES, MaterialRanges


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
