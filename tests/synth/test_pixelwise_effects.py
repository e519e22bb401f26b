"""Capture effects of the per-pixel maps (cnnps.synth.pixelwise): saturation, black level
and quantisation, mixing at depth discontinuities, coloured inter-reflection and the RGB
maps, checked against numpy references on Lambertian pixels; seeds; the default maps
against numbers recorded before these effects existed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.ps.obsmap import observation_maps
from cnnps.synth import pixel_effects as pfx
from cnnps.synth import pixelwise as px
from cnnps.synth.bsdf import MaterialRanges
from cnnps.synth.lights import hemisphere_lights

OLD = {"cast_shadow": 0.3, "interreflection": 0.3, "ambient": 0.05, "intensity_error": 0.05, "noise": 0.01}
NEW = {"saturation": 0.3, "quantisation": 0.5, "boundary_mix": 0.2}
LAMBERT = {"ranges": MaterialRanges.from_dict({"diffuse": {"specular": 0.0, "sheen": 0.0}}), "categories": ("diffuse",)}


def _lights(n=400, seed=2):
    L = hemisphere_lights(n, 3.0, seed=seed)
    Lf = torch.from_numpy(L).float()
    return L, (Lf / Lf.norm(dim=1, keepdim=True)).numpy().astype(np.float64)


def _lambert(base_color, normals, L):
    """(P, m) numpy float64 grey values of Lambertian pixels: mean(base_color) · max(0, n·l)."""
    cos = np.clip(np.asarray(normals, np.float64) @ L.T, 0.0, None)
    return np.asarray(base_color, np.float64).mean(1)[:, None] * cos


# --------------------------------------------------------------------------- the defaults


# Recorded from the module before saturation, quantisation and boundary_mix existed (seed
# 20240, batch 8, 300 lights, sparse share 0.2): per map the sum of its cells, the normals'
# z, and the generator's next uniform after the call.
GOLDEN = {
    "default": ([107.594755, 9.373046, 83.484651, 47.158145, 8.865713, 16.013587, 5.41216, 32.59993],
                0.20864397287368774),
    "old_on": ([97.934958, 10.421217, 85.698534, 41.256412, 8.936264, 32.991497, 6.985299, 30.733215],
               0.24192869663238525),
}
GOLDEN_NZ = [0.9482509, 0.8439965, 0.4194363, 0.4941175, 0.9365493, 0.5156252, 0.8345887, 0.9357828]


@pytest.mark.parametrize("name", ["default", "old_on"])
def test_maps_with_the_new_effects_at_zero_are_the_recorded_ones(name):
    fx = px.Effects() if name == "default" else px.Effects(**OLD)
    g = torch.Generator().manual_seed(20240)
    maps, normals = px.generate(8, generator=g, n_lights=300, sparse_fraction=0.2, effects=fx)
    sums, nxt = GOLDEN[name]
    # rtol 1e-4: each map is scaled by its brightest cell, often a specular peak x**k with k in the
    # hundreds, which multiplies float32's rounding of x by k; CPUs whose vector kernels round
    # differently (AVX2, AVX-512) move the whole map's sum by a few 1e-6 (seen: 2.4e-6 on an Intel
    # Xeon with AMX); a change of the generator moves it by percents (default against old_on: 2-50 %)
    np.testing.assert_allclose(maps.double().sum((1, 2, 3)).numpy(), sums, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(normals[:, 2].numpy(), GOLDEN_NZ, rtol=0, atol=1e-6)
    assert torch.rand(1, generator=g).item() == nxt  # no extra draw: the generator is where it was
    # explicit zeros are the defaults, bit for bit
    g2 = torch.Generator().manual_seed(20240)
    zero = px.Effects(**{**fx.__dict__, "saturation": 0.0, "quantisation": 0.0, "boundary_mix": 0.0})
    assert torch.equal(px.generate(8, generator=g2, n_lights=300, sparse_fraction=0.2, effects=zero)[0], maps)


def test_new_effects_are_validated_and_named_in_train():
    from cnnps.stages import train

    for name in NEW:
        with pytest.raises(ConfigError):
            px.Effects(**{name: 1.5})
    assert px.EFFECT_NAMES == tuple(px.Effects.__dataclass_fields__)
    train.Params(pixelwise={"effects": {k: 0.1 for k in px.EFFECT_NAMES}})
    with pytest.raises(ConfigError, match="boundary_mix"):
        train.Params(pixelwise={"effects": {"glare": 0.1}})


# --------------------------------------------------------------------------- seeds


def test_new_effects_repeat_per_seed_and_change_no_other_draw():
    kw = {"n_lights": 300, "return_details": True, "sparse_fraction": 0.2}
    fx = px.Effects(**OLD, **NEW)
    a = px.generate(64, generator=torch.Generator().manual_seed(7), effects=fx, **kw)
    b = px.generate(64, generator=torch.Generator().manual_seed(7), effects=fx, **kw)
    c = px.generate(64, generator=torch.Generator().manual_seed(8), effects=fx, **kw)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0])
    base = px.generate(64, generator=torch.Generator().manual_seed(7), effects=px.Effects(**OLD), **kw)
    for name in NEW:
        one = px.generate(64, generator=torch.Generator().manual_seed(7), effects=px.Effects(**OLD, **{name: 0.5}),
                          **kw)
        assert torch.equal(one[1], base[1]) and torch.equal(one[2]["mask"], base[2]["mask"]), name
        assert not torch.equal(one[0], base[0]), name
    # among the new effects too: the camera's draws and the second surfaces do not move
    s = px.generate(64, generator=torch.Generator().manual_seed(7), effects=px.Effects(**OLD, saturation=0.3), **kw)
    q = px.generate(64, generator=torch.Generator().manual_seed(7),
                    effects=px.Effects(**OLD, saturation=0.3, quantisation=0.5), **kw)
    assert torch.equal(s[2]["camera"]["saturated"], a[2]["camera"]["saturated"])
    keep = ~q[2]["camera"]["bits"].bool()  # the pixels quantisation left alone are as before it
    assert keep.any() and not keep.all()
    assert torch.equal(s[2]["camera"]["exposure"][keep], q[2]["camera"]["exposure"][keep])
    assert torch.equal(s[2]["intensities"][keep], q[2]["intensities"][keep])
    m = px.generate(64, generator=torch.Generator().manual_seed(7), effects=px.Effects(boundary_mix=0.2), **kw)
    assert torch.equal(m[2]["mix"]["normals"], a[2]["mix"]["normals"])
    assert torch.equal(m[2]["mix"]["mixed"], a[2]["mix"]["mixed"])


# --------------------------------------------------------------------------- saturation


def test_saturation_clips_at_the_drawn_exposure_on_lambertian_pixels():
    L, Ln = _lights()
    maps, normals, det = px.generate(96, generator=torch.Generator().manual_seed(0), lights=L,
                                     effects=px.Effects(saturation=1.0), return_details=True, **LAMBERT)
    cam, mask = det["camera"], det["mask"].numpy()
    assert cam["saturated"].all() and not cam["bits"].any() and not cam["black_level"].any()
    I_ref = _lambert(det["params"]["base_color"].numpy(), normals.numpy(), Ln)
    peak = np.where(mask, I_ref, 0.0).max(1)
    e = cam["exposure"].double().numpy()
    k = e * peak  # where the brightest chosen value landed, in units of the clip level
    lo, hi = pfx.SATURATION_RANGE
    assert k.min() >= lo * (1 - 1e-5) and k.max() <= hi * (1 + 1e-5) and np.ptp(np.log(k)) > 0.5 * np.log(hi / lo)
    got = det["intensities"].numpy()
    assert got.max() <= 1.0  # no value above the clip level reaches a map
    x = e[:, None] * I_ref
    clear = np.abs(x - 1.0) > 1e-4  # away from the clip level, where float rounding decides
    np.testing.assert_array_equal((got >= 1.0) & mask & clear, (x > 1.0) & mask & clear)
    frac_ref = ((x > 1.0) & mask).sum(1) / mask.sum(1)
    frac_got = ((got >= 1.0 - 1e-6) & mask).sum(1) / mask.sum(1)
    np.testing.assert_allclose(frac_got, frac_ref, atol=2.0 / mask.sum(1).min())
    assert frac_ref.mean() > 0.05
    ref = observation_maps(np.minimum(x, 1.0), Ln, 32, light_mask=mask)
    np.testing.assert_allclose(maps[:, 0].numpy(), ref, atol=3e-5)


# --------------------------------------------------------------------------- black level, quantisation


def test_quantisation_black_level_and_exposure_on_lambertian_pixels():
    L, Ln = _lights()
    maps, normals, det = px.generate(128, generator=torch.Generator().manual_seed(1), lights=L,
                                     effects=px.Effects(quantisation=1.0), return_details=True, **LAMBERT)
    cam, mask = det["camera"], det["mask"].numpy()
    bits = cam["bits"].numpy()
    assert set(np.unique(bits)) == {8, 16} and not cam["saturated"].any()
    assert 0.3 < (bits == 8).mean() < 0.7
    got = det["intensities"].double().numpy()
    for b, levels, tol in ((8, 255, 1e-4), (16, 65535, 1e-2)):
        v = got[bits == b] * levels
        assert np.abs(v - np.round(v)).max() < tol, b  # multiples of 1/255 or 1/65535
    black = cam["black_level"].double().numpy()
    assert np.abs(black).max() <= pfx.BLACK_LEVEL_MAX + 1e-7 and black.min() < 0 < black.max()
    I_ref = _lambert(det["params"]["base_color"].numpy(), normals.numpy(), Ln)
    e = cam["exposure"].double().numpy()
    k = e * np.where(mask, I_ref, 0.0).max(1)
    lo, hi = pfx.EXPOSURE_RANGE
    assert k.min() >= lo * (1 - 1e-5) and k.max() <= hi * (1 + 1e-5)
    levels = np.where(bits == 8, 255.0, 65535.0)[:, None]
    ref = np.round(np.clip(e[:, None] * I_ref + black[:, None], 0.0, 1.0) * levels) / levels
    off = np.abs(got - ref) * levels
    assert off[mask].max() <= 1.0 + 1e-3 and (off[mask] > 1e-3).mean() < 1e-3  # a level off only on a tie
    # a negative black level takes the darkest values to 0, a positive one lifts the unlit
    unlit = (I_ref == 0) & mask
    assert np.all(got[unlit & (black[:, None] < 0)] == 0)
    pos = unlit & (black[:, None] > 1.0 / 255)
    assert pos.any() and np.all(got[pos] > 0)
    ok = ~(off > 1e-3).any(1)  # pixels without a tie: their maps are the reference's
    np.testing.assert_allclose(maps[ok, 0].numpy(), observation_maps(ref[ok], Ln, 32, light_mask=mask[ok]), atol=3e-5)


def test_camera_response_contract():
    I = torch.tensor([[0.0, 0.5, 2.0, 4.0], [0.1, 0.2, 0.3, 0.4], [1.0, 1.0, 1.0, 1.0]])
    mask = torch.tensor([[True, True, True, False], [True] * 4, [True] * 4])
    u = torch.tensor([[0.0, 0.5, 0.9, 0.0, 0.5],  # saturated, k = 2: exposure 1 (peak 2)
                      [0.9, 0.0, 0.0, 0.0, 1.0],  # quantised 8 bit, k = 1/64, black + max
                      [0.9, 0.0, 0.9, 0.0, 0.5]])  # untouched
    out, cam = px.camera_response(I, mask, u, saturation=0.5, quantisation=0.5)
    assert cam["saturated"].tolist() == [True, False, False] and cam["bits"].tolist() == [0, 8, 0]
    torch.testing.assert_close(cam["exposure"], torch.tensor([1.0, (1 / 64) / 0.4, 1.0]))
    torch.testing.assert_close(out[0], torch.tensor([0.0, 0.5, 1.0, 1.0]))  # clipped at 1, the unchosen too
    exp1 = np.round((np.array([0.1, 0.2, 0.3, 0.4]) * (1 / 64) / 0.4 + 2 / 255) * 255) / 255
    np.testing.assert_allclose(out[1].numpy(), exp1, atol=1e-7)
    assert torch.equal(out[2], I[2])
    # per channel: the brightest value over lights and channels sets the exposure
    I3 = torch.rand(2, 5, 3, generator=torch.Generator().manual_seed(0)) * 3
    out3, cam3 = px.camera_response(I3, torch.ones(2, 5, dtype=torch.bool), torch.zeros(2, 5), saturation=1.0,
                                    quantisation=0.0)
    torch.testing.assert_close(cam3["exposure"], 1.0 / I3.reshape(2, -1).amax(1))
    assert float(out3.amax()) == 1.0 and out3.shape == I3.shape


# --------------------------------------------------------------------------- depth discontinuities


def test_boundary_mix_is_alpha_blend_of_two_lambertian_surfaces():
    L, Ln = _lights()
    fx = px.Effects(boundary_mix=0.5)
    maps, normals, det = px.generate(96, generator=torch.Generator().manual_seed(3), lights=L, effects=fx,
                                     return_details=True, **LAMBERT)
    mix = det["mix"]
    mixed, alpha = mix["mixed"].numpy(), mix["alpha"].double().numpy()
    assert 0.3 < mixed.mean() < 0.7
    lo, hi = pfx.MIX_ALPHA_RANGE
    assert np.all(alpha[~mixed] == 1) and alpha[mixed].min() >= lo and alpha[mixed].max() <= hi
    A = _lambert(det["params"]["base_color"].numpy(), normals.numpy(), Ln)
    B = _lambert(mix["params"]["base_color"].numpy(), mix["normals"].numpy(), Ln)
    ref = alpha[:, None] * A + (1 - alpha[:, None]) * B
    np.testing.assert_allclose(det["intensities"].numpy(), ref, atol=2e-6)
    assert np.abs(ref - A)[mixed].max() > 0.05  # the second surface shows
    # the target is the foreground's normal: the pixel's own draw, not the second surface's
    plain = px.generate(96, generator=torch.Generator().manual_seed(3), lights=L, return_details=True, **LAMBERT)
    assert torch.equal(plain[1], normals) and torch.equal(plain[2]["mask"], det["mask"])
    np.testing.assert_allclose(maps[:, 0].numpy(), observation_maps(ref, Ln, 32, light_mask=det["mask"].numpy()),
                               atol=3e-5)


def test_boundary_mix_blends_full_principled_shading():
    L, _ = _lights(300)
    _, normals, det = px.generate(64, generator=torch.Generator().manual_seed(4), lights=L,
                                  effects=px.Effects(boundary_mix=1.0), return_details=True)
    mix, Lt = det["mix"], det["lights"]
    a = mix["alpha"][:, None]
    ref = a * px.shade(normals, Lt, det["params"]) + (1 - a) * px.shade(mix["normals"], Lt, mix["params"])
    torch.testing.assert_close(det["intensities"], ref, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- coloured inter-reflection, RGB maps


def test_interreflection_is_coloured_per_channel_and_grey_is_its_mean():
    L, Ln = _lights()
    fx = px.Effects(interreflection=1.0)
    out = {}
    for rgb in (False, True):
        out[rgb] = px.generate(64, generator=torch.Generator().manual_seed(5), lights=L, effects=fx, rgb=rgb,
                               return_details=True, **LAMBERT)
    _, normals, det = out[True]
    ir = det["interreflection"]
    r, n2, rho_n = ir["strength"].double().numpy(), ir["normal"].double().numpy(), ir["colour"].double().numpy()
    base = det["params"]["base_color"].double().numpy()
    assert r.max() <= 1.0 and np.allclose(np.linalg.norm(n2, axis=1), 1, atol=1e-5)
    assert np.all((n2 * normals.numpy()).sum(1) >= -1e-5)  # the neighbour faces the pixel's hemisphere
    np.testing.assert_allclose(ir["reflectance"].numpy(), base, atol=1e-7)  # dielectric: its diffuse colour
    cos = np.clip(normals.double().numpy() @ Ln.T, 0, None)
    lit2 = np.clip(n2 @ Ln.T, 0, None)
    ref_rgb = base[:, None, :] * cos[..., None] + (r[:, None] * lit2)[..., None] * (base * rho_n)[:, None, :]
    np.testing.assert_allclose(det["intensities"].numpy(), ref_rgb, atol=2e-6)
    ref_grey = ref_rgb.mean(-1)
    np.testing.assert_allclose(out[False][2]["intensities"].numpy(), ref_grey, atol=2e-6)
    # the colour matters to the grey value: not mean(ρ_pixel) · mean(ρ_n)
    colourless = base.mean(1)[:, None] * cos + (r * base.mean(1) * rho_n.mean(1))[:, None] * lit2
    assert np.abs(colourless - ref_grey).max() > 1e-2
    # in RGB maps the bounced light's colour shows: channel ratios vary over the lights
    ratio = ref_rgb[..., 0] / np.maximum(ref_rgb[..., 1], 1e-9)
    lit = (cos > 0.1) & (lit2 > 0.1) & (r[:, None] > 0.5)
    assert np.nanmax(np.where(lit, ratio, np.nan) / np.nanmin(np.where(lit, ratio, np.inf), 1, keepdims=True)) > 1.1


def test_rgb_maps_against_numpy():
    L, Ln = _lights()
    maps, normals, det = px.generate(32, generator=torch.Generator().manual_seed(6), lights=L, rgb=True,
                                     return_details=True, **LAMBERT)
    assert maps.shape == (32, 4, 32, 32)
    base, mask = det["params"]["base_color"].double().numpy(), det["mask"].numpy()
    I = base[:, None, :] * np.clip(normals.double().numpy() @ Ln.T, 0, None)[..., None]  # (P, m, 3)
    np.testing.assert_allclose(maps[:, 0].numpy(), observation_maps(I.mean(-1), Ln, 32, light_mask=mask), atol=3e-5)
    per = np.stack([observation_maps(I[..., c], Ln, 32, light_mask=mask) for c in range(3)], 1)  # each scaled to 1
    # joint scaling: channel c = its own map times (its peak cell / the largest peak cell over channels)
    cells = np.stack([_cell_means(I[..., c], Ln, mask) for c in range(3)], 1)  # (P, 3, w*w)
    scale = cells.max(2) / cells.max((1, 2))[:, None]
    np.testing.assert_allclose(maps[:, 1:].numpy(), per * scale[..., None, None], atol=3e-5)
    assert np.allclose(maps[:, 1:].numpy().max((1, 2, 3)), 1.0, atol=1e-6)
    grey = px.generate(32, generator=torch.Generator().manual_seed(6), lights=L, **LAMBERT)[0]
    torch.testing.assert_close(maps[:, :1], grey, rtol=0, atol=1e-5)


def _cell_means(I, L, mask, w=32):
    """(P, w*w) numpy: per cell the mean value over the chosen lights (0 where none)."""
    col = np.clip((w * (L[:, 0] + 1) / 2).astype(int), 0, w - 1)
    row = np.clip((w * (L[:, 1] + 1) / 2).astype(int), 0, w - 1)
    cell = row * w + col
    out = np.zeros((len(I), w * w))
    cnt = np.zeros((len(I), w * w))
    for j in range(L.shape[0]):
        out[:, cell[j]] += np.where(mask[:, j], np.clip(I[:, j], 0, None), 0)
        cnt[:, cell[j]] += mask[:, j]
    return out / np.maximum(cnt, 1)


def test_rgb_with_every_effect_keeps_the_contract():
    fx = px.Effects(**OLD, **NEW)
    maps, _, det = px.generate(64, generator=torch.Generator().manual_seed(9), n_lights=300, effects=fx, rgb=True,
                               return_details=True)
    assert maps.shape == (64, 4, 32, 32) and det["intensities"].shape == (64, 300, 3)
    assert torch.isfinite(maps).all() and float(maps.amin()) >= 0 and float(maps.amax()) == 1.0
    I, cam = det["intensities"], det["camera"]
    assert float(I[cam["saturated"] | cam["bits"].bool()].amax()) <= 1.0
    v = I[cam["bits"] == 8] * 255  # per channel quantised
    assert (v - v.round()).abs().max() < 1e-4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_new_effects_on_cuda_repeat():
    fx = px.Effects(**OLD, **NEW)

    def make(seed, rgb=False):
        g = torch.Generator(device="cuda").manual_seed(seed)
        return px.generate(256, generator=g, device="cuda", effects=fx, sparse_fraction=0.2, rgb=rgb)

    a, b = make(1), make(1)
    assert a[0].is_cuda and torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert torch.isfinite(a[0]).all() and float(a[0].amax()) == 1.0
    c = make(1, rgb=True)
    assert c[0].shape == (256, 4, 32, 32) and torch.isfinite(c[0]).all()
    # a CPU generator gives the same draws on a CUDA device
    cpu = px.generate(64, generator=torch.Generator().manual_seed(2), effects=fx, return_details=True)
    gpu = px.generate(64, generator=torch.Generator().manual_seed(2), effects=fx, device="cuda", return_details=True)
    assert torch.equal(cpu[1], gpu[1].cpu()) and torch.equal(cpu[2]["camera"]["bits"], gpu[2]["camera"]["bits"].cpu())
    assert torch.equal(cpu[2]["mix"]["mixed"], gpu[2]["mix"]["mixed"].cpu())
    torch.testing.assert_close(cpu[2]["camera"]["exposure"], gpu[2]["camera"]["exposure"].cpu(), rtol=1e-3, atol=0)


# --------------------------------------------------------------------------- shares and grazing falloff


def test_shares_at_one_and_no_falloff_are_the_defaults_bit_for_bit():
    kw = {"n_lights": 300, "sparse_fraction": 0.2}
    g1, g2 = torch.Generator().manual_seed(20240), torch.Generator().manual_seed(20240)
    a = px.generate(8, generator=g1, effects=px.Effects(**OLD), **kw)
    b = px.generate(8, generator=g2, effects=px.Effects(**OLD, interreflection_share=1.0, ambient_share=1.0,
                                                         grazing_falloff=0.0), **kw)
    assert torch.equal(a[0], b[0]) and torch.rand(1, generator=g1).item() == torch.rand(1, generator=g2).item()
    with pytest.raises(ConfigError, match="ambient_share"):
        px.Effects(ambient_share=1.5)


@pytest.mark.parametrize("name", ["interreflection", "ambient"])
def test_a_share_applies_its_effect_to_that_share_of_the_pixels(name):
    kw = {"n_lights": 300, "return_details": True}
    other = {k: 0.0 for k in OLD if k != name}
    off = px.generate(2000, generator=torch.Generator().manual_seed(3), effects=px.Effects(**other), **kw)
    none = px.generate(2000, generator=torch.Generator().manual_seed(3),
                       effects=px.Effects(**other, **{name: 0.3, f"{name}_share": 0.0}), **kw)
    torch.testing.assert_close(none[2]["intensities"], off[2]["intensities"], rtol=0, atol=0)
    part = px.generate(2000, generator=torch.Generator().manual_seed(3),
                       effects=px.Effects(**other, **{name: 0.3, f"{name}_share": 0.3}), **kw)
    full = px.generate(2000, generator=torch.Generator().manual_seed(3), effects=px.Effects(**other, **{name: 0.3}),
                       **kw)
    changed = (part[2]["intensities"] != off[2]["intensities"]).any(1)
    assert abs(changed.double().mean().item() - 0.3) < 0.05  # binomial sd 0.01
    # where the share applies, the pixel is what the effect alone makes of it
    torch.testing.assert_close(part[2]["intensities"][changed], full[2]["intensities"][changed], rtol=0, atol=0)
    assert torch.equal(part[1], off[1]) and torch.equal(part[2]["mask"], off[2]["mask"])


def test_grazing_falloff_darkens_lambertian_pixels_by_burleys_light_factor():
    L, Ln = _lights()
    maps, normals, det = px.generate(400, generator=torch.Generator().manual_seed(1), lights=L,
                                     effects=px.Effects(grazing_falloff=0.5), return_details=True, **LAMBERT)
    fd90 = det["falloff_fd90"].double().numpy()
    some = fd90 < 1.0
    assert abs(some.mean() - 0.5) < 0.1  # binomial sd 0.025
    lo, hi = pfx.FD90_RANGE
    assert fd90[some].min() >= lo and fd90[some].max() <= hi and np.ptp(fd90[some]) > 0.5 * (hi - lo)
    cos = np.clip(normals.double().numpy() @ Ln.T, 0.0, None)
    ref = _lambert(det["params"]["base_color"].numpy(), normals.numpy(), Ln) * (1 + (fd90[:, None] - 1) * (1 - cos) ** 5)
    got = det["intensities"].double().numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6)
    # a grazing light (n.l = 0.1) on a pixel at fd90 = 0.5 reads 1 - 0.5 * 0.9^5 = 0.705 of Lambert's
    n = torch.tensor([[0.0, 0.0, 1.0]])
    lights = torch.tensor([[np.sqrt(1 - 0.01), 0.0, 0.1], [0.0, 0.0, 1.0]], dtype=torch.float32)
    prm = {"base_color": torch.ones(1, 3), "metallic": torch.zeros(1), "specular": torch.zeros(1),
           "roughness": torch.full((1,), 0.5), "sheen": torch.zeros(1), "sheen_tint": torch.zeros(1)}
    lam = px.shade(n, lights, prm)
    dark = px.shade(n, lights, prm, fd90=torch.tensor([0.5]))
    np.testing.assert_allclose((dark / lam).numpy()[0], [1.0 - 0.5 * 0.9 ** 5, 1.0], rtol=1e-5)
    with pytest.raises(ConfigError, match="lambert"):
        px.shade(n, lights, prm, diffuse_model="burley", fd90=torch.tensor([0.5]))
