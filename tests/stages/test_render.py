"""Render stage: physics checks on tiny Cycles scenes (32 x 32, few samples, 2 threads)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cnnps.core.errors import CnnpsError, ConfigError

trimesh = pytest.importorskip("trimesh")

S = 32
THREADS = 2
REPO = Path(__file__).resolve().parents[2]


def _sphere(radius=0.9):
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def _two_spheres():
    a = trimesh.creation.icosphere(3, radius=0.45)
    a.apply_translation([-0.48, 0, 0])
    b = trimesh.creation.icosphere(3, radius=0.45)
    b.apply_translation([0.48, 0, 0])
    return trimesh.util.concatenate([a, b])


def _pixel_grid(size):
    c = (np.arange(size) + 0.5) * 2.0 / size - 1.0
    return np.meshgrid(c, -c)  # X right, Y up, row 0 on top


def _load(out):
    from cnnps.core.capture import load_capture

    return load_capture(out)


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    pytest.importorskip("bpy")
    from cnnps.stages.render import render_capture

    out = tmp_path_factory.mktemp("render") / "sphere"
    return render_capture(_sphere(), out, lights=40, size=S, samples=4, seed=0, threads=THREADS, progress=False)


# --------------------------------------------------------------------------- no bpy needed


def test_params_validation():
    from cnnps.stages.render import Params

    Params()
    for bad in (dict(size=0), dict(lights=2), dict(samples=0), dict(device="tpu"), dict(jitter_deg=-1),
                dict(light_intensity=0.0), dict(max_bounces=-1), dict(min_elevation_deg=90)):
        with pytest.raises(ConfigError):
            Params(**bad)


def test_render_module_does_not_import_bpy():
    code = "import sys, cnnps.stages.render, cnnps.pipeline.cli_render; assert 'bpy' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_extend_maps_fills_outside_with_nearest():
    from cnnps.stages.render import extend_maps

    mask = np.zeros((5, 5), bool)
    mask[1:3, 1:3] = True
    v = np.zeros((5, 5), np.float32)
    v[mask] = [1, 2, 3, 4]
    out = extend_maps({"a": v, "c": 0.5}, mask)["a"]
    assert out[0, 0] == 1 and out[0, 4] == 2 and out[4, 0] == 3 and out[4, 4] == 4
    np.testing.assert_array_equal(out[mask], v[mask])


# --------------------------------------------------------------------------- Cycles


@pytest.mark.blender
def test_capture_layout_and_geometry(sphere_capture):
    out = Path(sphere_capture)
    names = (out / "filenames.txt").read_text().split()
    assert names == [f"{i:03d}.exr" for i in range(40)]
    assert all((out / n).is_file() for n in names)
    assert not (out / ".pending.json").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left
    meta = json.loads((out / "scene.json").read_text())
    assert meta["blender_version"].startswith("5.") and meta["samples"] == 4 and meta["n_lights"] == 40
    cap = _load(out)
    X, Y = _pixel_grid(S)
    disc = X**2 + Y**2 < 0.9**2
    # mask = the silhouette sampled at pixel centres (icosphere: a pixel or two on the edge)
    assert (cap.mask != disc).sum() <= 4
    Z = np.sqrt(np.maximum(0.81 - X**2 - Y**2, 0))
    analytic = np.stack([X, Y, Z], -1) / 0.9
    both = cap.mask & disc & (Z > 0.1)
    cos = np.sum(cap.normal_gt[both] * analytic[both], axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 0.5
    np.testing.assert_array_equal(cap.normal_gt[~cap.mask], 0)
    np.testing.assert_allclose(np.linalg.norm(cap.normal_gt[cap.mask], axis=1), 1, atol=1e-5)
    assert np.all(cap.lights[:, 2] > 0)


@pytest.mark.blender
def test_lambertian_sphere_least_squares_recovers_normal_gt(sphere_capture):
    """Lambertian photometric stereo on the rendered images gives back normal_gt."""
    from cnnps.core.lambertian import least_squares

    cap = _load(sphere_capture)
    I = cap.pixel_intensities()
    lit = (I > 1e-4).sum(axis=1) >= 3
    assert lit.mean() > 0.95
    # each pixel uses only the lights that reach it (I > 0)
    n, albedo, valid = least_squares(I[lit], cap.lights, shadow_threshold=0.0, return_valid=True)
    gt = cap.normal_gt[cap.mask][lit]
    err = np.degrees(np.arccos(np.clip(np.sum(n * gt, axis=1), -1, 1)))
    assert valid.all()
    assert err.mean() < 1.0, err.mean()  # measured 0.003 deg
    np.testing.assert_allclose(np.median(albedo), 1.0, atol=0.01)  # sun strength pi: white patch reads 1
    # the renders are I = max(0, n.l) pixel for pixel (no clamping, no tone mapping)
    pred = np.maximum(gt @ cap.lights.T, 0)
    assert np.abs(I[lit] - pred).mean() < 0.005


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
def test_specular_and_metallic_highlights_brighter_than_diffuse(tmp_path):
    """The BSDF mapping checked by rendering: glossy categories peak higher than diffuse."""
    pytest.importorskip("cnnps.synth.bsdf")
    from cnnps.stages.render import render_capture

    peaks = {}
    for kind in ("diffuse", "specular", "metallic"):
        out = render_capture(_sphere(), tmp_path / kind, lights=12, size=S, samples=8, material=kind,
                             superpixels=4, seed=1, threads=THREADS, progress=False)
        cap = _load(out)
        I = cap.pixel_intensities()
        peaks[kind] = float(np.percentile(I.max(axis=1), 99))
        assert np.isfinite(I).all() and I.min() >= 0
    assert peaks["specular"] > 1.5 * peaks["diffuse"], peaks
    assert peaks["metallic"] > 1.5 * peaks["diffuse"], peaks


@pytest.mark.blender
def test_resume_renders_only_missing_images(sphere_capture, tmp_path):
    import shutil

    from cnnps.stages.render import render_capture

    out = tmp_path / "cap"
    shutil.copytree(sphere_capture, out)
    meta = json.loads((out / "scene.json").read_text())
    before = {n: (out / n).read_bytes() for n in ("light_directions.txt", "007.exr")}
    # a killed run: no scene.json, .pending.json holds the key, some images missing
    (out / "scene.json").unlink()
    (out / ".pending.json").write_text(json.dumps({"key": meta["key"]}))
    for n in ("003.exr", "007.exr", "039.exr"):
        (out / n).unlink()
    from cnnps.core.atomic import atomic_path

    write = atomic_path(out / "003.exr")  # killed in the middle of this atomic write (kept alive:
    leftover = write.__enter__()  # a collected one would clean up after itself)
    assert leftover.is_file() and leftover.name.startswith(".003.")
    render_capture(_sphere(), out, lights=40, size=S, samples=4, seed=0, threads=THREADS, progress=False)
    meta2 = json.loads((out / "scene.json").read_text())
    assert meta2["images_rendered_last_run"] == 3 and meta2["key"] == meta["key"]
    assert not leftover.exists() and not [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert (out / "light_directions.txt").read_bytes() == before["light_directions.txt"]
    from cnnps.core.images import read_image

    assert (out / "007.exr").read_bytes() != b""
    np.testing.assert_array_equal(read_image(out / "007.exr"), read_image(Path(sphere_capture) / "007.exr"))
    # complete and current: nothing to do
    render_capture(_sphere(), out, lights=40, size=S, samples=4, seed=0, threads=THREADS, progress=False)
    assert json.loads((out / "scene.json").read_text())["images_rendered_last_run"] == 3  # untouched
    # other parameters: the folder is redone from scratch
    render_capture(_sphere(), out, lights=5, size=S, samples=4, seed=0, threads=THREADS, progress=False)
    assert sorted(p.name for p in out.glob("*.exr")) == [f"{i:03d}.exr" for i in range(5)]


@pytest.mark.blender
def test_cli_killed_then_resumed(tmp_path):
    """SIGKILL in the middle of `cnnps render`, rerun: only the missing lights are rendered."""
    out = tmp_path / "cap"
    out.mkdir()  # an existing empty folder is filled in place
    cmd = [sys.executable, "-m", "cnnps", "render", "procedural:blob:2", "--out", str(out), "--lights", "60",
           "--size", "24", "--samples", "2", "--threads", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.time()  # generous: Blender starts slowly on a loaded machine
    while len(list(out.glob("[0-9]*.exr"))) < 5 and time.time() - t0 < 300 and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = sorted(p.name for p in out.glob("[0-9]*.exr"))
    assert 5 <= len(done) < 60, "render finished before it could be killed"
    assert not (out / "scene.json").exists() and (out / ".pending.json").exists()
    lights = (out / "light_directions.txt").read_text()
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "scene.json").read_text())
    assert meta["images_rendered_last_run"] == 60 - len(done)
    assert (out / "light_directions.txt").read_text() == lights
    assert len(list(out.glob("[0-9]*.exr"))) == 60
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.blender
def test_stage_run_renders_scenes_skips_current_and_redoes_changed(tmp_path):
    """meshes -> materials -> render on one tiny scene; rerun skips; a new material re-renders."""
    from cnnps.stages import materials, meshes, render

    mesh_dir = tmp_path / "src"
    mesh_dir.mkdir()
    _sphere().export(mesh_dir / "ball.obj")
    data = tmp_path / "data"
    meshes.run(meshes.Params(mesh_dir=str(mesh_dir)), data)
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",)), data)
    p = render.Params(size=16, samples=2, lights=4, jitter_deg=2, threads=THREADS, workers=1)
    res = render.run(p, data)
    assert res == {"scenes": 1, "skipped": 0, "rendered_images": 4}
    (scene,) = (data / "materials").iterdir()
    out = data / "render" / scene.name
    cap = _load(out)
    assert cap.images.shape == (4, 16, 16) and np.all(cap.images >= 0) and cap.images[:, cap.mask].max() > 0.05
    meta = json.loads((out / "scene.json").read_text())
    assert meta["view_id"] and meta["category"] == "specular" and meta["pose"] is not None
    # Blender's mask and the materials stage's rasterised mask agree (same pixel centres)
    from cnnps.core.images import read_mask

    assert (read_mask(scene / "mask.png") != cap.mask).sum() <= 2
    from cnnps.synth.lights import hemisphere_lights

    np.testing.assert_allclose(cap.lights, hemisphere_lights(4, 2, seed=render.derive_seed(0, scene.name)), atol=1e-8)
    assert render.run(p, data) == {"scenes": 1, "skipped": 1, "rendered_images": 0}
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",), seed=5), data)
    assert render.run(p, data)["rendered_images"] == 4


def test_cli_errors_are_one_line(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "cnnps", "render", *args], cwd=REPO,
                              capture_output=True, text=True)

    r = run(str(tmp_path / "missing.obj"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0
    assert "missing.obj" in r.stderr and "not found" in r.stderr
    r = run("procedural:bowl", "--out", str(tmp_path / "o"), "--material", "glass")
    assert r.returncode == 2 and "--material" in r.stderr
    assert not (tmp_path / "o").exists()


def test_cli_refuses_a_folder_that_is_not_a_render_folder(tmp_path):
    """--out naming a user's folder (e.g. ~/Documents or .) is refused, never emptied."""
    user = tmp_path / "Documents"
    user.mkdir()
    (user / "thesis.txt").write_text("precious")
    (user / "sub").mkdir()
    for out, cwd in ((str(user), REPO), (".", user)):
        r = subprocess.run([sys.executable, "-m", "cnnps", "render", "procedural:bowl", "--out", out,
                            "--lights", "3", "--size", "8", "--samples", "1"], cwd=cwd, capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip().count("\n") == 0 and "is not a cnnps render folder" in r.stderr
        assert str(user) in r.stderr
        assert sorted(p.name for p in user.iterdir()) == ["sub", "thesis.txt"]
        assert (user / "thesis.txt").read_text() == "precious"


def test_remove_temp_files_only_removes_atomic_temporaries(tmp_path):
    from cnnps.core.atomic import atomic_path
    from cnnps.stages.render import remove_temp_files

    keep = ["000.exr", ".pending.json", ".hidden_user_file", "light_directions.txt", ".x.tmp"]
    for n in keep:
        (tmp_path / n).write_text("x")
    # temporaries of writes that never finished (a SIGKILLed process)
    writes = [atomic_path(tmp_path / n) for n in ("001.exr", "normal_gt.npy", "scene.json")]  # kept alive:
    left = [w.__enter__() for w in writes]  # a collected write would clean up after itself
    assert all(p.is_file() and p.name.startswith(".") for p in left)
    removed = remove_temp_files(tmp_path)
    assert sorted(removed) == sorted(left)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(keep)


def test_cycles_seed_is_folded_into_range():
    from cnnps.synth.blender_renderer import cycles_seed

    assert cycles_seed(0) == 0 and cycles_seed(12345) == 12345 and cycles_seed(2**31 - 1) == 2**31 - 1
    assert cycles_seed(2**31) == 0 and cycles_seed(2**31 + 7) == 7
    for seed in (2**40 + 3, 2**64, -1):
        assert 0 <= cycles_seed(seed) < 2**31
    assert cycles_seed(2**40 + 3) != cycles_seed(2**40 + 4)


@pytest.mark.blender
def test_renderer_accepts_a_large_seed():
    pytest.importorskip("bpy")
    from cnnps.synth.blender_renderer import BlenderRenderer, cycles_seed

    with BlenderRenderer(8, samples=1, threads=THREADS, seed=2**40 + 3) as r:
        assert r.scene.cycles.seed == cycles_seed(2**40 + 3) == 3


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


def test_new_scene_folder_gets_the_umask_mode(tmp_path):
    """A scene folder is built under mkdtemp (private 0700); renamed into place it must be
    readable as the umask allows, like every other output."""
    import stat

    from cnnps.stages.render import _start_folder

    old = os.umask(0o022)
    try:
        _start_folder(tmp_path / "scene", "k", np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]), 1.0, ["0.exr", "1.exr"])
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "scene").st_mode) == 0o755
    assert (tmp_path / "scene" / "light_directions.txt").is_file()
