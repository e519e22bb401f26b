"""Pixel-by-pixel observation maps (cnnps.synth.pixelwise): numbers against independent
references (numpy observation maps, Lambert's law, GGX normalisation, reciprocity,
white furnace), seeds, and the effects' switches."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cnnps.ps.obsmap import observation_maps
from cnnps.synth import obsmap_torch as omt
from cnnps.synth import pixelwise as px
from cnnps.synth import principled_torch as pt
from cnnps.synth.bsdf import MaterialRanges
from cnnps.synth.lights import hemisphere_lights, uniform_lights


def _params(P, **kw):
    base = {"base_color": torch.full((P, 3), 0.5), "metallic": torch.zeros(P), "specular": torch.zeros(P),
            "roughness": torch.full((P,), 0.5), "sheen": torch.zeros(P), "sheen_tint": torch.zeros(P)}
    for k, v in kw.items():
        base[k] = torch.as_tensor(v, dtype=torch.float32).expand_as(base[k]).clone()
    return base


def _hemisphere_grid(k=400, dtype=torch.float64, sphere=False):
    """(k*k, 3) directions on the upper hemisphere (or the whole sphere) and their solid
    angle weights (midpoint rule in cos, phi)."""
    c = (torch.arange(k, dtype=dtype) + 0.5) / k
    if sphere:
        c = 2 * c - 1
    ph = (torch.arange(k, dtype=dtype) + 0.5) / k * 2 * math.pi
    C, PH = torch.meshgrid(c, ph, indexing="ij")
    s = torch.sqrt(1 - C * C)
    d = torch.stack([s * torch.cos(PH), s * torch.sin(PH), C], -1).reshape(-1, 3)
    return d, torch.full((k * k,), (4 if sphere else 2) * math.pi / (k * k), dtype=dtype)


# --------------------------------------------------------------------------- observation maps


@pytest.mark.parametrize("w", [8, 32])
def test_torch_obsmap_equals_numpy(w):
    rng = np.random.default_rng(0)
    L = hemisphere_lights(300, 3.0, seed=1)
    I = rng.normal(0.3, 0.5, (64, 300)).astype(np.float32)  # negatives are clipped
    mask = rng.random((64, 300)) < 0.4
    mask[0] = False  # a pixel with no light
    I[1] = -1.0  # an all-dark pixel
    ref = observation_maps(I, L, w, light_mask=mask)
    got = px.observation_maps_torch(torch.from_numpy(I), torch.from_numpy(L), w, torch.from_numpy(mask)).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-7)
    ref2 = observation_maps(I, L, w)
    got2 = px.observation_maps_torch(torch.from_numpy(I), torch.from_numpy(L), w).numpy()
    np.testing.assert_allclose(got2, ref2, rtol=0, atol=2e-7)


def test_light_cells_match_numpy():
    from cnnps.ps.obsmap import light_cells

    L = np.r_[hemisphere_lights(500, 10.0, seed=3), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]]
    row, col = light_cells(L, 32)
    np.testing.assert_array_equal(omt.light_cells_torch(torch.from_numpy(L), 32).numpy(), row * 32 + col)


# --------------------------------------------------------------------------- the BSDF


def test_lambertian_material_is_albedo_times_cosine():
    g = torch.Generator().manual_seed(0)
    n = px.sample_normals(50, generator=g)
    L = torch.from_numpy(uniform_lights(40)).float()
    albedo = torch.rand(50, 3, generator=g)
    p = _params(50, specular=0.0, metallic=0.0, sheen=0.0, roughness=0.7)
    p["base_color"] = albedo
    I = px.shade(n, L, p)
    ref = albedo.mean(1, keepdim=True) * (n @ L.T).clamp(min=0)
    torch.testing.assert_close(I, ref, rtol=1e-5, atol=1e-6)


def test_ggx_d_is_normalised():
    # D depends on cos(theta_h) only: ∫ D c dω = 2π ∫_0^1 D(c) c dc (midpoint rule, 200k nodes)
    c = (torch.arange(200_000, dtype=torch.float64) + 0.5) / 200_000
    for alpha in (0.05, 0.3, 0.8, 1.0):
        a2 = torch.tensor(alpha**2, dtype=torch.float64)
        total = (pt.ggx_d(a2, c) * c).mean().item() * 2 * math.pi
        assert total == pytest.approx(1.0, abs=1e-4), alpha


def test_specular_lobe_is_reciprocal():
    g = torch.Generator().manual_seed(1)
    a = px.sample_normals(200, generator=g, grazing_fraction=0).double()
    b = px.sample_normals(200, generator=g, grazing_fraction=0).double()
    a2 = torch.tensor(0.2, dtype=torch.float64)
    h = (a + b) / (a + b).norm(dim=1, keepdim=True)  # surface normal (0, 0, 1): cosines are the z's
    f_ab = pt.ggx_single(a2, h[:, 2], a[:, 2], b[:, 2]) / b[:, 2]  # BRDF f(a -> b)
    f_ba = pt.ggx_single(a2, h[:, 2], b[:, 2], a[:, 2]) / a[:, 2]
    torch.testing.assert_close(f_ab, f_ba)
    eta = torch.tensor(1.5, dtype=torch.float64)
    torch.testing.assert_close(pt.fresnel_dielectric((a * h).sum(1), eta), pt.fresnel_dielectric((b * h).sum(1), eta))


def test_fresnel_dielectric_known_values():
    eta = torch.tensor([1.5, 1.5, 1.0])
    F = pt.fresnel_dielectric(torch.tensor([1.0, 0.0, 0.5]), eta)
    torch.testing.assert_close(F, torch.tensor([0.04, 1.0, 0.0]), atol=1e-6, rtol=0)
    # Principled's F0 = 0.08 * specular (Specular IOR Level with IOR 1.5)
    eta = pt.specular_eta(torch.tensor([0.5, 1.0, 4.0]))
    torch.testing.assert_close(pt.fresnel_dielectric(torch.ones(3), eta), torch.tensor([0.04, 0.08, 0.32]), atol=1e-6, rtol=0)


def test_albedo_table_against_monte_carlo():
    E, Eavg = pt.ggx_albedo_table()
    d, dw = _hemisphere_grid(600)
    for i, j in ((31, 31), (15, 6), (8, 20)):
        r, mu = i / 31, j / 31
        v = torch.tensor([math.sqrt(1 - mu * mu), 0.0, mu], dtype=torch.float64)
        h = (d + v) / (d + v).norm(dim=1, keepdim=True)
        a2 = torch.tensor(r**4, dtype=torch.float64)
        e = (pt.ggx_single(a2, h[:, 2], torch.tensor(mu, dtype=torch.float64), d[:, 2]) * dw).sum().item()
        assert E[i, j] == pytest.approx(e, abs=5e-3), (i, j)
    assert np.all(E <= 1.0 + 1e-6) and np.all(Eavg <= 1.0 + 1e-6) and Eavg[0] == 1.0


@pytest.mark.parametrize("kind", ["metal", "dielectric"])
def test_white_furnace_no_gain(kind):
    """Irradiance-weighted integral over all light directions (the albedo seen from v):
    a white metal with multiple scattering reflects 1; a white dielectric with its diffuse
    base reflects at most 1 (Lambert base 1 minus the layer, plus the layer)."""
    d, dw = _hemisphere_grid(400, sphere=True)  # every direction: the tilted normals' hemispheres too
    d = d.float()
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.8, 0.6]])
    for r in (0.4, 0.6, 0.9):  # lobes wide enough for a 400 x 400 grid
        if kind == "metal":
            p = _params(3, base_color=1.0, metallic=1.0, roughness=r)
        else:
            p = _params(3, base_color=1.0, specular=1.0, roughness=r)
        I = px.shade(normals, d, p, sheen_model="none")
        albedo = (I.double() * dw).sum(1) / math.pi  # pixel = π f cos
        assert torch.all(albedo <= 1.01), (r, albedo)
        if kind == "metal":
            assert torch.all(albedo >= 0.97), (r, albedo)


def test_microfiber_sheen_reflects_its_albedo_and_covers_the_base():
    """The sheen lobe (an LTC: a clamped cosine under a linear map that keeps the horizon)
    integrates to its fitted albedo R at every view angle; R grows toward grazing views
    (~0.02 facing, ~0.5 at 80 deg, roughness 0.5); the layers below are dimmed by 1 - R
    for a white sheen of weight 1 (Cycles' layering)."""
    d, dw = _hemisphere_grid(400, sphere=True)
    albedos = []
    for deg in (0, 30, 60, 80):
        t = math.radians(deg)
        n = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64)
        lobe, R = pt.microfiber_sheen(n, d[None])
        assert (lobe * dw).sum().item() / math.pi == pytest.approx(R.item(), rel=1e-3)
        albedos.append(R.item())
    assert 0.01 < albedos[0] < 0.04 and 0.4 < albedos[-1] < 0.6 and albedos == sorted(albedos)
    n = torch.tensor([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6], [0.0, -0.9, 0.43589]])
    L = torch.from_numpy(uniform_lights(80)).float()
    white = _params(3, sheen=1.0, sheen_tint=0.0)
    lobe, R = pt.microfiber_sheen(n, L[None])
    torch.testing.assert_close(px.shade(n, L, white),
                               (1 - R) * px.shade(n, L, white, sheen_model="none") + lobe * (n @ L.T > 0),
                               rtol=1e-5, atol=1e-6)
    # a tinted sheen dims the base by its strongest channel
    tinted = _params(3, sheen=1.0, sheen_tint=1.0, base_color=torch.tensor([0.2, 0.8, 0.4]))
    below = px.shade(n, L, tinted) - (torch.tensor([0.2, 0.8, 0.4]).mean() * lobe) * (n @ L.T > 0)
    torch.testing.assert_close(below, (1 - 0.8 * R) * px.shade(n, L, tinted, sheen_model="none"),
                               rtol=1e-5, atol=1e-6)


def test_multiscatter_raises_rough_metal_only():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    L = torch.from_numpy(uniform_lights(50)).float()
    p = _params(1, base_color=0.9, metallic=1.0, roughness=0.9)
    ms = px.shade(n, L, p, multiscatter=True)
    ss = px.shade(n, L, p, multiscatter=False)
    assert torch.all(ms >= ss) and (ms.sum() / ss.sum()) > 1.2
    p = _params(1, base_color=0.9, metallic=1.0, roughness=0.05)
    torch.testing.assert_close(px.shade(n, L, p), px.shade(n, L, p, multiscatter=False), rtol=1e-3, atol=1e-6)


# --------------------------------------------------------------------------- sampling


def test_normals_are_cosine_weighted():
    g = torch.Generator().manual_seed(0)
    n = px.sample_normals(200_000, generator=g, grazing_fraction=0.0)
    torch.testing.assert_close(n.norm(dim=1), torch.ones(len(n)))
    assert n[:, 2].min() > 0
    # density ∝ n_z: E[n_z] = 2/3, P(n_z < 0.5) = 1/4
    assert n[:, 2].double().mean().item() == pytest.approx(2 / 3, abs=3e-3)
    assert (n[:, 2] < 0.5).double().mean().item() == pytest.approx(0.25, abs=3e-3)
    ng = px.sample_normals(100_000, generator=g, grazing_fraction=0.5)
    assert (ng[:, 2] <= 0.3).double().mean().item() == pytest.approx(0.5 + 0.5 * 0.09, abs=1e-2)


def test_materials_follow_the_ranges():
    g = torch.Generator().manual_seed(0)
    ranges = MaterialRanges.from_dict({"specular": {"specular": [2.0, 3.0]}})
    p, cat = px.sample_materials(4000, ranges=ranges, categories=("diffuse", "specular", "metallic"), generator=g)
    met, spec, dif = cat == 2, cat == 1, cat == 0
    assert torch.all(p["metallic"][met] == 1) and torch.all(p["metallic"][~met] == 0)
    assert p["roughness"][met].min() >= 0.3 and p["roughness"][met].max() <= 0.7
    assert p["specular"][spec].min() >= 2.0 and p["specular"][spec].max() <= 3.0
    assert p["roughness"][spec].min() >= 0.05  # the near-mirror exclusion (specular > 1)
    assert p["specular"][dif].max() <= 1.0
    assert abs(int(met.sum()) - 4000 / 3) < 150


def test_light_subsets_follow_extract_rules():
    g = torch.Generator().manual_seed(0)
    L = torch.from_numpy(hemisphere_lights(1300, 3.0, seed=0)).float()
    mask = px.light_subsets(L, 500, generator=g)
    k = mask.sum(1)
    assert k.min() >= 50 and k.max() <= 1300
    # every chosen light lies inside the pixel's cone, which holds at least 50 lights
    zmin = torch.where(mask, L[:, 2][None].expand_as(mask), torch.full(mask.shape, 2.0)).amin(1)
    assert torch.all((L[:, 2][None] >= zmin[:, None]).sum(1) >= 50)
    mask_s = px.light_subsets(L, 2000, generator=g, sparse_fraction=0.5, sparse_min_lights=6)
    ks = mask_s.sum(1)
    assert ks.min() == 6 and (ks < 50).double().mean().item() == pytest.approx(0.5, abs=0.05)


# --------------------------------------------------------------------------- the generator


def test_generate_shapes_scale_and_seed():
    maps, normals = px.generate(16, generator=torch.Generator().manual_seed(3), n_lights=300)
    assert maps.shape == (16, 1, 32, 32) and maps.dtype == torch.float32 and normals.shape == (16, 3)
    torch.testing.assert_close(maps.amax((1, 2, 3)), torch.ones(16))
    maps2, normals2 = px.generate(16, generator=torch.Generator().manual_seed(3), n_lights=300)
    assert torch.equal(maps, maps2) and torch.equal(normals, normals2)
    maps3, _ = px.generate(16, generator=torch.Generator().manual_seed(4), n_lights=300)
    assert not torch.equal(maps, maps3)


def test_generate_lambertian_maps_match_numpy_pipeline():
    """With only a Lambertian category, no effects: the maps equal numpy's
    observation_maps of albedo · max(0, n·l) under the drawn subsets."""
    ranges = MaterialRanges.from_dict({"diffuse": {"specular": 0.0, "sheen": 0.0}})
    L = hemisphere_lights(400, 3.0, seed=2)
    maps, normals, det = px.generate(32, generator=torch.Generator().manual_seed(0), lights=L, ranges=ranges,
                                     categories=("diffuse",), return_details=True)
    Lf = torch.from_numpy(L).float()
    Lf = Lf / Lf.norm(dim=1, keepdim=True)
    I = (det["params"]["base_color"].mean(1, keepdim=True) * (normals @ Lf.T).clamp(min=0)).numpy()
    ref = observation_maps(I, Lf.numpy(), 32, light_mask=det["mask"].numpy())
    np.testing.assert_allclose(maps[:, 0].numpy(), ref, atol=2e-5)


def test_effects_off_change_nothing_and_shadows_only_lower():
    kw = dict(n_lights=300, return_details=True)
    base = px.generate(64, generator=torch.Generator().manual_seed(5), **kw)
    zero = px.generate(64, generator=torch.Generator().manual_seed(5), effects=px.Effects(0, 0, 0, 0, 0), **kw)
    assert torch.equal(base[0], zero[0])
    for name in ("cast_shadow", "interreflection", "ambient", "intensity_error", "noise"):
        on = px.generate(64, generator=torch.Generator().manual_seed(5), effects=px.Effects(**{name: 0.5}), **kw)
        assert torch.equal(on[1], base[1]), name  # same normals: an effect changes no other draw
        assert torch.equal(on[2]["mask"], base[2]["mask"]), name
        assert not torch.equal(on[0], base[0]), name
    sh = px.generate(64, generator=torch.Generator().manual_seed(5), effects=px.Effects(cast_shadow=1.0), **kw)
    I0, I1 = base[2]["intensities"], sh[2]["intensities"]
    assert torch.all(I1 <= I0) and (I1 < I0).any()
    ir = px.generate(64, generator=torch.Generator().manual_seed(5), effects=px.Effects(interreflection=1.0), **kw)
    assert torch.all(ir[2]["intensities"] >= I0)


def test_effects_are_validated():
    from cnnps.infra.errors import ConfigError

    with pytest.raises(ConfigError):
        px.Effects(ambient=-0.1)
    with pytest.raises(ConfigError):
        px.shade(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, 1.0]]), _params(1), diffuse_model="oren")


def test_lights_given_as_a_tensor_match_lights_given_as_an_array():
    L = hemisphere_lights(200, 3.0, seed=2)
    a = px.generate(16, generator=torch.Generator().manual_seed(4), lights=L)
    b = px.generate(16, generator=torch.Generator().manual_seed(4), lights=torch.from_numpy(L))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_generator_draws_on_the_gpu_and_repeats():
    fx = px.Effects(cast_shadow=0.3, interreflection=0.3, ambient=0.05, intensity_error=0.05, noise=0.01)

    def make(seed):
        g = torch.Generator(device="cuda").manual_seed(seed)
        return px.generate(256, generator=g, device="cuda", effects=fx, sparse_fraction=0.2)

    a, b, c = make(1), make(1), make(2)
    assert a[0].is_cuda and torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[1], c[1])
    n = a[1].norm(dim=1)
    assert torch.allclose(n, torch.ones_like(n), atol=1e-5) and float(a[0].amax()) == 1.0
