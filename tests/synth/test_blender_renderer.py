"""The Blender renderer (cnnps.synth.blender): physics on tiny Cycles scenes
(32 x 32, few samples, 2 threads), seeds, texture alignment, temp folders, devices."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra.errors import CnnpsError
from tests.support.tiny_scenes import THREADS, S
from tests.support.tiny_scenes import sphere as _sphere

trimesh = pytest.importorskip("trimesh")

REPO = Path(__file__).resolve().parents[2]


def _two_spheres():
    a = trimesh.creation.icosphere(3, radius=0.45)
    a.apply_translation([-0.48, 0, 0])
    b = trimesh.creation.icosphere(3, radius=0.45)
    b.apply_translation([0.48, 0, 0])
    return trimesh.util.concatenate([a, b])


def _pixel_grid(size):
    c = (np.arange(size) + 0.5) * 2.0 / size - 1.0
    return np.meshgrid(c, -c)  # X right, Y up, row 0 on top


# --------------------------------------------------------------------------- no bpy needed


def test_cycles_seed_is_folded_into_range():
    from cnnps.synth.blender import cycles_seed

    assert cycles_seed(0) == 0 and cycles_seed(12345) == 12345 and cycles_seed(2**31 - 1) == 2**31 - 1
    assert cycles_seed(2**31) == 0 and cycles_seed(2**31 + 7) == 7
    for seed in (2**40 + 3, 2**64, -1):
        assert 0 <= cycles_seed(seed) < 2**31
    assert cycles_seed(2**40 + 3) != cycles_seed(2**40 + 4)


def test_killed_renderers_temp_folders_are_removed(tmp_path):
    """Blender's temp folder carries a lock: once its process is SIGKILLed, a later
    renderer removes it; a live one's folder is left alone."""
    code = ("import sys, time; from cnnps.infra.locked_temp import make_locked_tmpdir; "
            "d, fd = make_locked_tmpdir('cnnps-blender-'); print(d, flush=True); time.sleep(120)")
    env = {**os.environ, "TMPDIR": str(tmp_path), "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
    try:
        d = Path(proc.stdout.readline().strip())
        assert d.parent == tmp_path and d.name.startswith("cnnps-blender-") and d.is_dir()
        from cnnps.infra.locked_temp import remove_stale_tmpdirs

        old = time.time() - 3600
        os.utime(d, (old, old))
        assert remove_stale_tmpdirs("cnnps-blender-", tmp_path) == [] and d.is_dir()  # alive: its lock is held
    finally:
        proc.kill()
        proc.wait()
    assert remove_stale_tmpdirs("cnnps-blender-", tmp_path, min_age_s=7200) == [] and d.is_dir()  # too young
    assert remove_stale_tmpdirs("cnnps-blender-", tmp_path) == [d] and not d.exists()


# --------------------------------------------------------------------------- Cycles


@pytest.mark.blender
def test_cast_shadows_and_interreflections(tmp_path):
    from cnnps.synth.blender import BlenderRenderer

    mesh = _two_spheres()
    l = np.array([1.0, 0.0, 0.35])
    l /= np.linalg.norm(l)
    imgs = {}
    with BlenderRenderer(S, samples=8, threads=THREADS, seed=0, max_bounces=4) as r:
        r.load_scene(mesh.vertices, mesh.faces)
        mask, n = r.render_geometry()
        img = r.render(l)[..., 0]
        imgs["gi"] = r.render([0.0, 0.3, 1.0])[..., 0]
    ndl = n @ l
    # cast shadow: the right sphere hides the light from the left sphere's facing side
    shadowed = mask & (ndl > 0.3) & (img < 0.02)
    assert shadowed.sum() >= 5
    X, _ = _pixel_grid(S)
    assert np.all(X[shadowed] < 0)  # on the left sphere
    with BlenderRenderer(S, samples=8, threads=THREADS, seed=0, max_bounces=0) as r:
        r.load_scene(mesh.vertices, mesh.faces)
        imgs["direct"] = r.render([0.0, 0.3, 1.0])[..., 0]
    # global illumination: light bounced between the spheres adds to direct light only
    extra = imgs["gi"] - imgs["direct"]
    assert extra.sum() > 1.0 and extra.min() > -0.05
    gap = mask & (np.abs(X) < 0.25)  # facing sides of the two spheres near the gap
    assert extra[gap].mean() > 5 * max(extra[mask & (np.abs(X) > 0.7)].mean(), 1e-3)


@pytest.mark.blender
def test_same_seed_same_images_other_seed_other_noise():
    """Cycles on the CPU is bitwise deterministic for a seed (measured); the seed moves the noise."""
    from cnnps.synth.blender import BlenderRenderer

    mesh = _two_spheres()
    out = []
    for seed in (0, 0, 1):
        with BlenderRenderer(S, samples=4, threads=THREADS, seed=seed, max_bounces=4) as r:
            r.load_scene(mesh.vertices, mesh.faces)
            out.append(r.render([0.2, 0.3, 0.9]))
    np.testing.assert_array_equal(out[0], out[1])
    assert np.abs(out[0] - out[2]).max() > 1e-3


@pytest.mark.blender
def test_image_space_material_maps_line_up_with_pixels():
    """A per-pixel albedo map reaches exactly its pixel (Window coords, Closest, row 0 on top)."""
    from cnnps.synth.blender import BlenderRenderer

    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.2, 1.0, (S, S)).astype(np.float32)
    rgb = np.stack([albedo, albedo[::-1], albedo[:, ::-1]], axis=-1)  # asymmetric in all channels
    with BlenderRenderer(S, samples=2, threads=THREADS, seed=0, max_bounces=0) as r:
        r.load_scene(_sphere().vertices, _sphere().faces, {"bsdf": "lambertian", "Color": rgb})
        mask, n = r.render_geometry()
        img = r.render([0.0, 0.0, 1.0])
    ok = mask & (n[..., 2] > 0.2)
    np.testing.assert_allclose(img[ok], rgb[ok] * n[ok][:, 2:3], rtol=1e-2, atol=1e-4)  # measured 0.4 %
    # principled inputs, scalar maps packed three to an image: a metal, smooth on one half
    smooth_left = np.where(np.arange(S)[None, :] < S // 2, 0.3, 1.0).astype(np.float32) * np.ones((S, S), np.float32)
    peak = {}
    for name, rough in (("smooth_left", smooth_left), ("smooth_right", smooth_left[:, ::-1].copy())):
        with BlenderRenderer(S, samples=2, threads=THREADS, seed=0, max_bounces=0) as r:
            r.load_scene(_sphere().vertices, _sphere().faces,
                         {"Base Color": rgb, "Roughness": rough, "Metallic": np.ones((S, S), np.float32)})
            peak[name] = r.render([-0.6, 0.0, 0.8]).max()  # highlight (n = half vector) on the left half
    assert peak["smooth_left"] > 3 * peak["smooth_right"], peak


@pytest.mark.blender
def test_renderer_accepts_a_large_seed():
    pytest.importorskip("bpy")
    from cnnps.synth.blender import BlenderRenderer, cycles_seed

    with BlenderRenderer(8, samples=1, threads=THREADS, seed=2**40 + 3) as r:
        assert r.scene.cycles.seed == cycles_seed(2**40 + 3) == 3


@pytest.mark.blender
def test_gpu_request_without_gpu_is_a_clear_error(tmp_path):
    pytest.importorskip("bpy")
    from cnnps.synth.blender import BlenderRenderer

    try:
        r = BlenderRenderer(8, samples=1, device="gpu")
    except CnnpsError as exc:
        assert "gpu" in str(exc).lower() and "--device cpu" in str(exc)
    else:  # a machine with a GPU: it must render
        r.load_scene(_sphere().vertices, _sphere().faces)
        assert r.render([0, 0, 1]).max() > 0.9
        r.close()


@pytest.mark.blender
def test_narrow_lobe_highlight_is_peakier_than_a_rough_one():
    """The narrow category's ends (roughness 0.02 and 0.15) against a specular surface of
    roughness 0.5, 32 px, the sun aimed so that one pixel centre sees the mirror direction:
    the narrow highlight is that pixel (or two) and far brighter; the rough one is broad."""
    from cnnps.synth.blender import BlenderRenderer
    from cnnps.synth.bsdf import MaterialRanges
    from cnnps.synth.render.materials import principled_material

    lo, hi = MaterialRanges().narrow.roughness
    params = {"base_color": np.full(3, 0.5), "metallic": 0.0, "specular": 1.0, "sheen": 0.0, "sheen_tint": 0.0}
    stats = {}
    for rough in (lo, hi, 0.5):
        with BlenderRenderer(S, samples=4, threads=THREADS, seed=0, max_bounces=0) as r:
            r.load_scene(_sphere().vertices, _sphere().faces, principled_material({**params, "roughness": rough}))
            mask, n = r.render_geometry()
            # a pixel whose normal is 20-25 deg from the view axis; the sun at its mirror direction
            cand = np.argwhere(mask & (n[..., 2] > np.cos(np.radians(25))) & (n[..., 2] < np.cos(np.radians(20))))
            pix = tuple(cand[len(cand) // 2])
            v = np.array([0.0, 0.0, 1.0])
            l = 2 * (n[pix] @ v) * n[pix] - v
            img = r.render(l).mean(axis=-1)
        lit = mask & (n @ l > 0)
        peak = img[mask].max()
        stats[rough] = {"peak": peak, "above_half": int((img[mask] > peak / 2).sum()), "at": img[pix],
                        "median": float(np.median(img[lit])), "pixels": int(mask.sum())}
    for rough in (lo, hi):
        s = stats[rough]
        assert s["at"] == s["peak"], stats  # the highlight sits where the mirror direction says
        assert s["above_half"] <= 3, stats  # a point: at most a pixel and its neighbours (measured 1)
        assert s["peak"] > 10 * stats[0.5]["peak"] and s["peak"] > 20 * s["median"], stats  # measured 56x, 157x
    assert stats[0.5]["above_half"] > 0.1 * stats[0.5]["pixels"], stats  # a broad lobe (measured 25 %)


@pytest.mark.blender
def test_environment_light_reads_albedo_times_strength_in_attached_shadow():
    """A uniform white world of radiance E on a Lambertian sphere (convex: every point sees
    the whole sky above its tangent plane): irradiance pi*E, outgoing radiance albedo*E,
    added to the sun's albedo*max(0, n.l). Off: attached shadows read exactly 0."""
    from cnnps.synth.blender import BlenderRenderer

    albedo, E = 0.6, 0.05
    l = np.array([1.0, 0.0, 0.2])
    l /= np.linalg.norm(l)
    img = {}
    for env in (0.0, E):
        with BlenderRenderer(S, samples=4, threads=THREADS, seed=0, max_bounces=8, environment=env) as r:
            r.load_scene(_sphere().vertices, _sphere().faces, {"bsdf": "lambertian", "Color": albedo})
            mask, n = r.render_geometry()
            img[env] = r.render(l)[..., 0]
    ndl = n @ l
    shadow = mask & (ndl < -0.05)  # attached shadow: the sun cannot reach these points
    lit = mask & (ndl > 0.3)
    assert shadow.sum() > 150 and lit.sum() > 150
    assert (img[0.0][shadow] == 0).all()  # no environment: black, as the paper's renders
    # With a constant world, Cycles' cosine-weighted sample of a Lambertian returns albedo*E
    # exactly, so there is no Monte Carlo noise to allow for (measured: every pixel 1.0000 *
    # albedo*E at 1 spp). The only loss: a direction drawn about the smooth shading normal
    # that dips under the flat triangle hits the mesh and returns 0, costing that pixel 1/spp
    # (measured: mean 0.999, lowest pixel 0.75 at 4 spp). Bounds that hold whatever the seed:
    ratio = img[E][shadow] / (albedo * E)
    assert ratio.min() > 0 and ratio.max() < 1.001, (ratio.min(), ratio.max())
    assert abs(ratio.mean() - 1) < 0.02 and np.median(ratio) > 0.999, ratio.mean()
    # in the light the environment adds the same albedo*E to the sun's term
    added = (img[E][lit] - albedo * ndl[lit]) / (albedo * E)
    assert abs(np.median(added) - 1) < 0.02, np.median(added)
    np.testing.assert_allclose(img[0.0][lit], albedo * ndl[lit], rtol=0.01, atol=1e-4)
    with pytest.raises(CnnpsError, match="environment"):
        BlenderRenderer(8, samples=1, environment=-1.0)
