"""The render stage: parameters, planning, caching, and a clear error without Blender
(the rendering library: tests/synth/test_capture_render.py, test_blender_renderer.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError

trimesh = pytest.importorskip("trimesh")

THREADS = 2
REPO = Path(__file__).resolve().parents[2]
NO_BLENDER = "the render stage needs Blender: pip install 'cnnps[render]' (bpy 5.0.1, Python 3.11)"


def _sphere(radius=0.9):
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def _load(out):
    from cnnps.io.capture import load_capture

    return load_capture(out)


def _one_sphere_scene(tmp_path: Path, category: str) -> Path:
    """A data dir with one sphere mesh view and its ``category`` material maps (16 px, 3 superpixels)."""
    from cnnps.stages import materials, meshes

    mesh_dir = tmp_path / "src"
    mesh_dir.mkdir()
    _sphere().export(mesh_dir / "ball.obj")
    data = tmp_path / "data"
    meshes.run(meshes.Params(mesh_dir=str(mesh_dir)), data)
    materials.run(materials.Params(size=16, superpixels=3, categories=(category,)), data)
    return data


@pytest.fixture(scope="module")
def materials_data(views_data_dir, tmp_path_factory) -> Path:
    """meshes (2 procedural views) + materials (16 x 16, one category): 2 scenes to render."""
    from cnnps.stages import materials

    data = tmp_path_factory.mktemp("render-stage") / "data"
    shutil.copytree(views_data_dir, data)
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",)), data)
    return data


# --------------------------------------------------------------------------- no bpy needed


def test_params_validation():
    from cnnps.stages.render import Params

    Params()
    for bad in (dict(size=0), dict(lights=2), dict(samples=0), dict(device="tpu"), dict(jitter_deg=-1),
                dict(light_intensity=0.0), dict(max_bounces=-1), dict(min_elevation_deg=90), dict(workers=-1),
                dict(threads=-1), dict(env_fraction=-0.1), dict(env_fraction=1.5), dict(env_max=-1),
                dict(env_max=2.0), dict(env_fraction="half")):
        with pytest.raises(ConfigError, match=r"^render\."):
            Params(**bad)
    # how scenes run is not part of the pictures (nor of their keys)
    assert Params(device="gpu", workers=3, threads=2, prune=False).picture_params() == Params().picture_params()
    assert Params().env_fraction == 0.0 and Params().env_max == 0.05  # the environment light is opt-in


def test_environment_strength_is_seeded_per_scene_and_off_by_default():
    from cnnps.stages.render import Params, environment_strength

    names = [f"view{i:04d}-specular" for i in range(2000)]
    assert all(environment_strength(Params(), n) == 0.0 for n in names)
    assert all(environment_strength(Params(env_fraction=1.0, env_max=0.0), n) == 0.0 for n in names)
    p = Params(env_fraction=0.3, env_max=0.05)
    s = np.array([environment_strength(p, n) for n in names])
    assert s.tolist() == [environment_strength(p, n) for n in names]  # deterministic
    assert np.mean(s > 0) == pytest.approx(0.3, abs=0.04) and s.max() <= 0.05
    assert np.mean(s[s > 0]) == pytest.approx(0.025, abs=0.004)  # U(0, env_max)
    # more scenes lit: the earlier ones keep theirs; a larger env_max scales the strengths
    s2 = np.array([environment_strength(Params(env_fraction=0.6, env_max=0.1), n) for n in names])
    assert np.all(s2[s > 0] > 0) and np.mean(s2 > 0) == pytest.approx(0.6, abs=0.04)
    np.testing.assert_allclose(s2[s > 0], 2 * s[s > 0], rtol=1e-5)
    # another seed, another draw
    s3 = np.array([environment_strength(Params(env_fraction=0.3, env_max=0.05, seed=1), n) for n in names])
    assert not np.array_equal(s3 > 0, s > 0)


def test_render_keys_without_environment_are_unchanged(materials_data):
    """Both new features off (the defaults): every scene's key is the one it had before they
    existed (the old formula, and a pinned value of it); on, only lit scenes' keys move."""
    from cnnps.infra.hashing import file_sha256, files_sha256, stable_hash
    from cnnps.pipeline import config
    from cnnps.stages import render
    from cnnps.synth.render.keys import VERSION, capture_key

    def key(params):
        return capture_key({"mesh": "m", "material": "t", "params": params.picture_params(), "v": VERSION})

    # the formula, pinned (values computed before): on settings of its own, and on params.yaml's
    assert key(render.Params(samples=64, lights=50, jitter_deg=3.0)) == (
        "1e8a2408e5be2b94b2023bb9458d7f2b3679fb20721f23ebd8b22a2db0ebcfde")
    yaml_params = config.build_params(config.load_config(REPO / "params.yaml"), "render", check_files=False)
    assert key(yaml_params) == "78774e3bc797737ed68be9fadef41094ea265734633a247643d1670acd30f06e"
    p = render.Params(size=16, samples=1, lights=3)
    jobs = render._scene_jobs(p, materials_data)
    assert len(jobs) == 2
    for j in jobs:
        sdir = Path(j["material_dir"])
        mat_sha = files_sha256([q for q in sdir.iterdir() if q.is_file() and q.suffix in (".npy", ".json", ".png")
                                and q.name != "preview.png"])
        old = stable_hash({"mesh": file_sha256(j["mesh_path"]), "material": mat_sha, "params": p.picture_params(), "v": VERSION})
        assert j["key"] == old and j["environment"] == 0.0
    lit = render._scene_jobs(render.Params(size=16, samples=1, lights=3, env_fraction=1.0), materials_data)
    for j, k in zip(jobs, lit):
        assert 0 < k["environment"] <= 0.05 and k["key"] != j["key"]
        assert k["environment"] == render.environment_strength(render.Params(env_fraction=1.0), k["scene_id"])


def test_stage_modules_and_cli_import_without_bpy():
    """The core install (no ``render`` extra): every stage module, the render command's
    help and config validation of the whole params.yaml work without bpy."""
    code = (
        "import sys; sys.modules['bpy'] = None\n"
        "import cnnps.stages.meshes, cnnps.stages.materials, cnnps.stages.render, cnnps.stages.extract\n"
        "import cnnps.stages.train, cnnps.stages.evaluate, cnnps.synth.capture_render, cnnps.pipeline.cli_render\n"
        "from cnnps.pipeline import config\n"
        "cfg = config.load_config(config.preset_path('demo'))\n"
        "config.load_all(cfg, check_files=False)\n"
        "assert sys.modules['bpy'] is None\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    # and, with bpy installed, none of them imports it
    code = "import sys, cnnps.stages.render, cnnps.stages.evaluate, cnnps.pipeline.cli_render; assert 'bpy' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


def test_stage_without_blender_is_one_clear_line_before_any_job(materials_data, tmp_path, monkeypatch):
    from cnnps.stages import render

    data = tmp_path / "data"
    shutil.copytree(materials_data, data)
    monkeypatch.setitem(sys.modules, "bpy", None)
    with pytest.raises(ConfigError) as exc:
        render.run(render.Params(size=16, samples=1, lights=3, workers=1), data)
    assert str(exc.value) == NO_BLENDER
    assert list((data / "render").iterdir()) == []  # no job started


def test_stage_prunes_only_its_own_stale_folders(materials_data, tmp_path, monkeypatch):
    """A render folder of a scene no longer in materials/ goes; a user's folder stays."""
    from cnnps.stages import render

    data = tmp_path / "data"
    shutil.copytree(materials_data, data)
    stale = data / "render" / "gone-specular"
    stale.mkdir(parents=True)
    (stale / ".pending.json").write_text("{}")
    user = data / "render" / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    monkeypatch.setitem(sys.modules, "bpy", None)  # pruning comes before rendering (which then fails)
    with pytest.raises(ConfigError, match="needs Blender"):
        render.run(render.Params(size=16, samples=1, lights=3, workers=1), data)
    assert not stale.exists() and (user / "notes.txt").read_text() == "keep"


# --------------------------------------------------------------------------- Cycles


@pytest.mark.blender
def test_stage_run_renders_scenes_skips_current_and_redoes_changed(tmp_path):
    """meshes -> materials -> render on one tiny scene; rerun skips; a new material re-renders."""
    from cnnps.stages import materials, render

    data = _one_sphere_scene(tmp_path, "specular")
    p = render.Params(size=16, samples=2, lights=4, jitter_deg=2, threads=THREADS, workers=1)
    res = render.run(p, data)
    assert res == {"scenes": 1, "skipped": 0, "rendered_images": 4}
    (scene,) = (data / "materials").iterdir()
    out = data / "render" / scene.name
    cap = _load(out)
    grey = cap.grey_images()
    assert grey.shape == (4, 16, 16) and np.all(grey >= 0) and grey[:, cap.mask].max() > 0.05
    meta = json.loads((out / "scene.json").read_text())
    assert meta["view_id"] and meta["category"] == "specular" and meta["pose"] is not None
    # Blender's mask and the materials stage's rasterised mask agree (same pixel centres)
    from cnnps.io.images import read_mask

    assert (read_mask(scene / "mask.png") != cap.mask).sum() <= 2
    from cnnps.infra.hashing import derive_seed
    from cnnps.synth.lights import hemisphere_lights

    np.testing.assert_allclose(cap.lights, hemisphere_lights(4, 2, seed=derive_seed(0, scene.name)), atol=1e-8)
    assert render.run(p, data) == {"scenes": 1, "skipped": 1, "rendered_images": 0}
    with pytest.MonkeyPatch.context() as mp:  # nothing to render: no Blender needed
        mp.setitem(sys.modules, "bpy", None)
        assert render.run(p, data) == {"scenes": 1, "skipped": 1, "rendered_images": 0}
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",), seed=5), data)
    assert render.run(p, data)["rendered_images"] == 4


@pytest.mark.blender
def test_stage_environment_light_and_narrow_scene(tmp_path):
    """A narrow scene rendered with the environment light on, then off: scene.json records
    the drawn strength, the lights files are the sun's, attached shadows are lit only when on."""
    from cnnps.io.capture import load_capture
    from cnnps.stages import render

    data = _one_sphere_scene(tmp_path, "narrow")
    (scene,) = (data / "materials").iterdir()
    assert scene.name.endswith("-narrow")
    on = render.Params(size=16, samples=2, lights=6, jitter_deg=2, threads=THREADS, workers=1, env_fraction=1.0)
    assert render.run(on, data)["rendered_images"] == 6
    out = data / "render" / scene.name
    meta = json.loads((out / "scene.json").read_text())
    env = render.environment_strength(on, scene.name)
    assert meta["environment_strength"] == env and 0 < env <= 0.05 and meta["category"] == "narrow"
    np.testing.assert_allclose(np.loadtxt(out / "light_intensities.txt"), 1.0)  # the sun's
    cap = load_capture(out)
    n = cap.normal_gt[cap.mask]
    shadow = (n @ cap.lights.T) < -0.05  # attached shadows, pixel x light
    assert shadow.sum() > 10
    I_on = cap.pixel_intensities()
    assert I_on[shadow].min() > 0
    assert render.run(on, data)["rendered_images"] == 0  # current: skipped
    off = render.Params(size=16, samples=2, lights=6, jitter_deg=2, threads=THREADS, workers=1)
    assert render.run(off, data)["rendered_images"] == 6  # another key: re-rendered
    meta = json.loads((out / "scene.json").read_text())
    assert meta["environment_strength"] == 0.0 and meta["key"] == render._scene_jobs(off, data)[0]["key"]
    I_off = load_capture(out).pixel_intensities()
    assert (I_off[shadow] == 0).all()
    # the ambient term of a dielectric over a Lambertian base: about (1 - F0) * albedo * env,
    # F0 <= 0.16 and albedo <= 1 here, plus the glossy lobe reflecting the white world (<= F0 * env)
    assert I_on[shadow].max() < 1.2 * env  # measured 0.84 (median 0.65)
