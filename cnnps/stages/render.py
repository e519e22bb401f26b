"""The ``render`` stage: every scene (mesh view x material) rendered under many suns.

For each ``data_dir/materials/<scene_id>/`` (written by the materials stage, naming its
mesh view in ``material.json``) this writes ``data_dir/render/<scene_id>/``, a capture
folder rendered by :func:`cnnps.synth.capture_render.render_into` (the one capture
renderer; its module docstring: layout, resuming a killed render, mask and ground truth
from Blender) with the orthographic camera and one sun per image. A scene's ``key`` hashes
the mesh file, the material files and the parameters that change the pictures (not the
device, workers or threads), plus the scene's environment strength when it has one; a
folder holding the current key and all its images is skipped. Render folders of scenes
no longer in ``materials/`` are removed (``prune``).

Environment light (``env_fraction``, ``env_max``; off by default, and then a scene's key and
images are those of a scene in a black world): a drawn share of the scenes is also lit
by a dim uniform white world (:func:`environment_strength`), so their attached shadows are
not black, as in a real capture. It adds its term to *every* image of the scene; the light
directions and intensities written are still the sun's, and ``scene.json`` records the
strength (``environment_strength``, relative to the sun's irradiance; 0 = none).

Scaling out. Scenes are independent jobs run by an executor (:mod:`cnnps.infra.executor`:
``local`` process pool, or ``ray`` on a cluster; params.yaml's ``executor`` section).
Each job builds a fresh Blender scene (factory settings) in whatever worker process runs
it, is told how many threads Cycles may use (``threads``, else the executor's
``threads_per_job``), asks Ray for one GPU when ``device: gpu``, and is idempotent: the
images of a scene depend only on its key and seeds, so a retried job (its worker died)
resumes the folder and a duplicated one rewrites the same pixels.

Damaged files. A scene whose folder no longer matches the checksums its ``scene.json``
records (a truncated, NaN-filled or byte-flipped image, a ``scene.json`` edited by hand)
is not complete: this stage renders again exactly what is damaged (the images, or the
whole scene when its light files or ``scene.json`` cannot be trusted;
:mod:`cnnps.synth.capture_render`). Damaged inputs of another stage (a mesh or a
material map that does not decode, holds NaN, or disagrees with its ``view.json``) stop
the stage with one line naming the file and the fix, before the scene's folder is touched.

Blender (bpy, the ``cnnps[render]`` extra) is needed only when a scene has images to
render; without it the stage stops with one line (with the local executor before any
job starts; on Ray the first job on a node without bpy fails with it). Only
:mod:`cnnps.synth.blender` imports bpy.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.executor import (
    ExecutorParams,
    LocalExecutor,
    runs_in_process,
    stage_executor,
)
from cnnps.infra.hashing import derive_seed, file_sha256, files_sha256
from cnnps.infra.stage_folders import prune_stale, read_json
from cnnps.io.capture import MASK_FILE
from cnnps.synth.capture_render import render_into
from cnnps.synth.render.keys import VERSION, capture_key
from cnnps.synth.render.materials import extend_maps, lambertian_material, principled_material
from cnnps.synth.render.rendered_folder import RENDER_MARKERS
from cnnps.synth.render.resume import finished
from cnnps.synth.render.scene import Scene
from cnnps.synth.render.settings import RenderSettings


@dataclass(frozen=True)
class Params(RenderSettings):
    """Parameters of the render stage (``render:`` in params.yaml): the render settings of
    :class:`cnnps.synth.render.settings.RenderSettings` (size, samples, lights, jitter_deg,
    min_elevation_deg, light_intensity, max_bounces, device, seed, threads: the names and
    defaults ``cnnps.render`` and ``cnnps render`` use too; params.yaml and the presets set
    the stage's own values) and how the scenes are run.

    ``executor``: params.yaml's shared ``executor`` section (None = in this process);
    ``workers`` overrides executor.workers when set (1 = in this process, 0 = one per
    core); ``threads`` (0) = the executor's threads_per_job (cores / parallel jobs);
    ``prune``: remove render folders of scenes no longer in materials/.

    Environment light (off by default): a share ``env_fraction`` of the scenes (drawn per
    scene, :func:`environment_strength`) is also lit by a dim uniform white world of
    strength U(0, ``env_max``) relative to the sun's irradiance (0.05: a white Lambertian
    patch out of the sun reads up to 5 % of what it reads facing the sun; DiLiGenT's BALL
    reads 3–6 % of a pixel's brightest value in its attached shadows).
    """

    executor: ExecutorParams | None = None
    workers: int | None = None
    prune: bool = True
    env_fraction: float = 0.0  # share of scenes with an environment light (0 = none: the paper's black world)
    env_max: float = 0.05  # their strength ~ U(0, env_max), relative to the sun's irradiance

    def __post_init__(self):
        super().__post_init__()
        if self.workers is not None and self.workers < 0:
            raise ConfigError(f"render.workers must be >= 0, got {self.workers}")
        for name in ("env_fraction", "env_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not 0.0 <= v <= 1.0:
                raise ConfigError(f"render.{name} must be a number in [0, 1], got {v!r}")


def environment_strength(params: Params, scene_id: str) -> float:
    """Strength of scene ``scene_id``'s environment light relative to the sun's irradiance
    (0.0 = none), drawn from ``derive_seed(seed, scene_id, "environment")``: whether the
    scene gets one (u1 < env_fraction) and how strong (u2 * env_max).

    Seeded by the scene (not by its content key) so that it is deterministic, does not
    move when the scene's material is redrawn, and raising env_fraction keeps the scenes
    that already had one (and their u2); a larger env_max scales their strengths.
    """
    if params.env_fraction <= 0 or params.env_max <= 0:
        return 0.0
    u = np.random.default_rng(derive_seed(int(params.seed), str(scene_id), "environment")).random(2)
    if u[0] >= params.env_fraction:
        return 0.0
    return float(f"{u[1] * params.env_max:.6g}")  # as written to scene.json and hashed into the key


def _scene_jobs(params: Params, data_dir: Path) -> list[dict]:
    mat_root = data_dir / "materials"
    if not mat_root.is_dir():
        raise InputError(mat_root, "no materials folder (run the materials stage first)")
    jobs = []
    for sdir in sorted(p for p in mat_root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        mjson = sdir / "material.json"
        meta = read_json(mjson)
        if meta is None:
            continue  # not (yet) a finished scene folder: the materials stage writes atomically
        view_id = meta.get("view_id")
        if not view_id:
            raise InputError(mjson, "names no 'view_id' (the mesh view this material belongs to)")
        view_dir = data_dir / "meshes" / view_id
        mesh_path = view_dir / "mesh.ply"
        if not mesh_path.is_file():
            raise InputError(mesh_path, f"mesh of scene {sdir.name} not found (run the meshes stage)")

        mesh_sha = file_sha256(mesh_path)
        mat_sha = files_sha256([p for p in sdir.iterdir() if p.is_file() and p.suffix in (".npy", ".json", ".png")
                                 and p.name != "preview.png"])
        view_meta = read_json(view_dir / "view.json") or {}
        env = environment_strength(params, sdir.name)
        # a scene without an environment light: no environment term in its key (capture_key)
        key = capture_key({"mesh": mesh_sha, "material": mat_sha, "params": params.picture_params(), "v": VERSION}, env)
        jobs.append(
            {
                "scene_id": sdir.name,
                "material_dir": str(sdir),
                "mesh_path": str(mesh_path),
                "out": str(data_dir / "render" / sdir.name),
                "key": key,
                "environment": env,
                "params": {k: v for k, v in asdict(params).items() if k != "executor"},
                "meta": {
                    "scene_id": sdir.name,
                    "view_id": view_id,
                    "category": meta.get("category"),
                    "mesh_sha256": mesh_sha,
                    "material_sha256": mat_sha,
                    "pose": view_meta.get("rotation"),
                    "view_key": view_meta.get("key"),
                    "material_key": meta.get("key"),
                },
            }
        )
    return jobs


def _load_map(p: Path) -> np.ndarray:
    """A material map (.npy) as float32; unreadable or non-finite -> InputError."""
    try:
        arr = np.load(p, allow_pickle=False).astype(np.float32)
    except Exception as exc:
        raise InputError(p, f"unreadable .npy file ({exc})") from exc
    if not np.isfinite(arr).all():
        raise InputError(p, "material map holds NaN or infinite values")
    return arr


def _material_from_dir(sdir: Path, meta: dict) -> dict:
    """Renderer material of a materials-stage folder (maps extended past their mask)."""
    from cnnps.io.images import read_mask

    mask = read_mask(sdir / MASK_FILE)
    if meta.get("category") == "lambertian" or meta.get("bsdf") == "lambertian":
        albedo = _load_map(sdir / "base_color.npy") if (sdir / "base_color.npy").is_file() else 1.0
        return lambertian_material(extend_maps({"a": albedo}, mask)["a"] if np.ndim(albedo) >= 2 else albedo)
    names = ("base_color", "metallic", "specular", "roughness", "sheen", "sheen_tint")
    maps = {}
    for n in names:
        p = sdir / f"{n}.npy"
        if not p.is_file():
            raise InputError(p, "material parameter map missing")
        maps[n] = _load_map(p)
        if maps[n].shape[:2] != mask.shape:
            raise InputError(p, f"map is {maps[n].shape}, mask is {mask.shape}")
    return principled_material(extend_maps(maps, mask))


def _check_material_files(sdir: Path) -> None:
    """Every file of a materials folder that enters the scene's key must decode as a whole
    (maps: finite numbers; images: readable; JSON: valid), so a damaged one stops the
    stage instead of changing the key and being rendered from."""
    from cnnps.io.images import read_image_raw

    for p in sorted(sdir.iterdir()):
        if not p.is_file() or p.name == "preview.png":
            continue
        if p.suffix == ".npy":
            _load_map(p)
        elif p.suffix == ".png":
            read_image_raw(p)
        elif p.suffix == ".json" and read_json(p) is None:
            raise InputError(p, "not valid JSON")


def _read_mesh(mesh_path: Path):
    """The view's mesh, checked against the vertex and face counts its ``view.json``
    records (when it does) and for finite vertices."""
    from cnnps.synth.meshes import read_view_mesh

    mesh = read_view_mesh(mesh_path.parent)
    view = read_json(mesh_path.parent / "view.json") or {}
    for what, n in (("vertices", len(mesh.vertices)), ("faces", len(mesh.faces))):
        want = view.get(f"n_{what}")
        if want is not None and int(want) != n:
            raise InputError(mesh_path, f"holds {n} {what}, its view.json records {want} (damaged)")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise InputError(mesh_path, "mesh has NaN or infinite vertices")
    return mesh


def _upstream_fix(stage: str, folder: Path) -> str:
    """The fix for a damaged input of another stage (which trusts its own keys, so the
    damaged folder must go first)."""
    return f"delete {folder} and rerun `cnnps run-stage {stage}` (then this stage)"


def render_scene_job(job: dict) -> dict:
    """Top-level (picklable) job: render one scene of the stage."""
    p = Params(**job["params"])
    sid = job["scene_id"]
    out = Path(job["out"])
    if finished(out, job["key"]):
        return {"scene_id": sid, "rendered": 0, "skipped": True}
    from cnnps.synth.lights import hemisphere_lights

    sdir = Path(job["material_dir"])
    mesh_path = Path(job["mesh_path"])
    # the inputs are read (and checked) before the scene's folder is touched
    try:
        mesh = _read_mesh(mesh_path)
    except InputError as exc:
        raise InputError(exc.path, f"{exc.problem}; {_upstream_fix('meshes', mesh_path.parent)}") from None
    try:
        _check_material_files(sdir)
        material = _material_from_dir(sdir, read_json(sdir / "material.json") or {})
    except InputError as exc:
        raise InputError(exc.path, f"{exc.problem}; {_upstream_fix('materials', sdir)}") from None
    if isinstance(material.get("Color"), np.ndarray) and material["Color"].shape[:2] != (p.size, p.size):
        raise InputError(sdir, f"material maps are {material['Color'].shape[:2]}, render size is {p.size}")
    scene_seed = derive_seed(int(p.seed), str(sid))  # the scene's lights and Cycles seed
    L = hemisphere_lights(p.lights, p.jitter_deg, seed=scene_seed, min_elevation_deg=p.min_elevation_deg)
    scene = Scene(np.asarray(mesh.vertices), np.asarray(mesh.faces), material, L,
                  environment=job.get("environment", 0.0))  # orthographic camera, suns
    settings = replace(p, seed=scene_seed, threads=job.get("threads", p.threads))
    res = render_into(out, scene, settings, key=job["key"], meta=job["meta"], desc=sid,
                      progress=job.get("progress", True))
    return {"scene_id": sid, **res}


def run(params: Params, data_dir: Path, executor=None) -> dict:
    """Render every scene of ``data_dir/materials`` into ``data_dir/render`` (skipping
    current ones, resuming partial ones). Returns counts.

    ``executor``: runs the per-scene jobs (:mod:`cnnps.infra.executor`); None = one made
    from ``params.executor`` / ``params.workers`` (default: in this process), closed at
    the end. Progress: scenes done / total (the executor's bar).
    """
    data_dir = Path(data_dir)
    jobs = _scene_jobs(params, data_dir)
    out_root = data_dir / "render"
    out_root.mkdir(parents=True, exist_ok=True)
    if params.prune:
        prune_stale(out_root, {j["scene_id"] for j in jobs}, RENDER_MARKERS)
    todo = [j for j in jobs if not finished(Path(j["out"]), j["key"])]
    results = []
    if todo:
        from cnnps.synth.blender import require_blender

        with stage_executor(params, executor) as ex:
            # one clear line here rather than one per job (Ray workers may have the bpy this process lacks)
            if isinstance(ex, LocalExecutor):
                require_blender()
            threads = params.threads or ex.threads_per_job(len(todo))
            progress = runs_in_process(ex, len(todo))  # per-light bars only in this process
            for j in todo:
                j["threads"] = threads
                j["progress"] = progress
            gpus = 1 if params.device == "gpu" else 0
            results = ex.map(render_scene_job, todo, desc="render", num_cpus=threads, num_gpus=gpus)
    return {
        "scenes": len(jobs),
        "skipped": len(jobs) - len(todo),
        "rendered_images": int(sum(r["rendered"] for r in results)),
    }
