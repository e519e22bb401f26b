"""The Blender renderer (cnnps.synth.blender_renderer): physics on tiny Cycles scenes
(32 x 32, few samples, 2 threads), seeds, texture alignment, temp folders, devices."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cnnps.core.errors import CnnpsError

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
    from cnnps.synth.blender_renderer import cycles_seed

    assert cycles_seed(0) == 0 and cycles_seed(12345) == 12345 and cycles_seed(2**31 - 1) == 2**31 - 1
    assert cycles_seed(2**31) == 0 and cycles_seed(2**31 + 7) == 7
    for seed in (2**40 + 3, 2**64, -1):
        assert 0 <= cycles_seed(seed) < 2**31
    assert cycles_seed(2**40 + 3) != cycles_seed(2**40 + 4)


def test_killed_renderers_temp_folders_are_removed(tmp_path):
    """Blender's temp folder carries a lock: once its process is SIGKILLed, a later
    renderer removes it; a live one's folder is left alone."""
    code = ("import sys, time; from cnnps.synth.blender_renderer import _make_tmpdir; "
            "d, fd = _make_tmpdir(); print(d, flush=True); time.sleep(120)")
    env = {**os.environ, "TMPDIR": str(tmp_path), "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
    try:
        d = Path(proc.stdout.readline().strip())
        assert d.parent == tmp_path and d.name.startswith("cnnps-blender-") and d.is_dir()
        from cnnps.synth.blender_renderer import _remove_stale_tmpdirs

        old = time.time() - 3600
        os.utime(d, (old, old))
        assert _remove_stale_tmpdirs(tmp_path) == [] and d.is_dir()  # alive: its lock is held
    finally:
        proc.kill()
        proc.wait()
    assert _remove_stale_tmpdirs(tmp_path, min_age_s=7200) == [] and d.is_dir()  # too young
    assert _remove_stale_tmpdirs(tmp_path) == [d] and not d.exists()


# --------------------------------------------------------------------------- Cycles


@pytest.mark.blender
def test_cast_shadows_and_interreflections(tmp_path):
    from cnnps.synth.blender_renderer import BlenderRenderer

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
    from cnnps.synth.blender_renderer import BlenderRenderer

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
    from cnnps.synth.blender_renderer import BlenderRenderer

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
    from cnnps.synth.blender_renderer import BlenderRenderer, cycles_seed

    with BlenderRenderer(8, samples=1, threads=THREADS, seed=2**40 + 3) as r:
        assert r.scene.cycles.seed == cycles_seed(2**40 + 3) == 3


@pytest.mark.blender
def test_gpu_request_without_gpu_is_a_clear_error(tmp_path):
    pytest.importorskip("bpy")
    from cnnps.synth.blender_renderer import BlenderRenderer

    try:
        r = BlenderRenderer(8, samples=1, device="gpu")
    except CnnpsError as exc:
        assert "gpu" in str(exc).lower() and "--device cpu" in str(exc)
    else:  # a machine with a GPU: it must render
        r.load_scene(_sphere().vertices, _sphere().faces)
        assert r.render([0, 0, 1]).max() > 0.9
        r.close()
