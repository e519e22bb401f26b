"""Rendering one capture folder with Blender Cycles: the library of the render stage,
``cnnps render`` and the eval stage's test set.

:func:`render_into` renders a mesh and a material under given lights into a capture
folder (docs/ARCHITECTURE.md): ``000.exr ...`` (float32 linear RGB, names zero-padded to
the light count), ``filenames.txt``, ``light_directions.txt`` (unit, camera frame),
``light_intensities.txt``, ``mask.png``, ``normal_gt.npy`` and ``scene.json``.
:func:`render_capture` does it for one mesh (a Trimesh, a mesh file or
``procedural:<kind>[:seed]``) and a material kind, with its own content key.

Caching and resuming. A folder whose ``scene.json`` holds the current key and all its
images is skipped (:func:`is_complete`). Otherwise the folder appears (built under a
temporary name, then renamed) already holding ``.pending.json`` (the key) and the three
text files, so the light directions are fixed FIRST (and every run renders with the
directions read back from the file); each image is written atomically (temp name,
rename); ``scene.json`` is written LAST as the completion marker. A rerun after a kill
finds ``.pending.json`` with the same key, deletes the temporary files the kill left
(:func:`remove_temp_files`), and renders only the missing images with the same lights;
a different key empties the folder. Only folders of ours (``.pending.json`` or
``scene.json``: :func:`is_render_folder`) are ever emptied: an existing non-empty folder
without them is refused (InputError), an existing empty one is filled in place. The
images of a folder depend only on its key and seeds (Cycles is deterministic per seed),
so a retried or duplicated job resumes or rewrites the same pixels.

Checksums. ``scene.json`` records every other file of the folder (``files``: name ->
``{"bytes", "sha256"}``) and a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`, indent 2, leaving out the two timing fields
``render_seconds`` and ``images_rendered_last_run``, so it is the same for every run that
writes the same folder). :func:`is_complete` verifies them
(a truncated, NaN-filled or byte-flipped image, or a ``scene.json`` edited by hand, makes
the folder incomplete), and :func:`render_into` then redoes exactly the damaged part:
damaged images (or the mask and normals) are deleted and re-rendered with the same
lights and seeds, so the folder ends with the bytes it had; damaged light files or an
untrustworthy ``scene.json`` re-render the whole capture. Files of a killed run (no
record yet) are checked by decoding (readable, finite) before they are kept.
:func:`folder_problems` tells a reader (the extract stage) what does not match. The key
does not depend on these entries, and a ``scene.json`` written before them (no
``files``, no ``checksum``) is still complete as it was (only existence is checked).

Mask and ground-truth normals come from Blender itself (one extra 1-sample render): the
mask is the alpha of the camera rays through the pixel centres and ``normal_gt`` is the
smooth shading normal at those hits, i.e. exactly the normal the BSDFs were lit with
(agreeing with the shading by construction; for meshes of the meshes stage it matches the
analytic/rasterised normal up to Blender's vertex-normal interpolation). Material maps
are extended outward by nearest neighbour (:func:`extend_maps`), so a silhouette pixel
that Blender covers but the materials' rasteriser did not still gets its neighbour's
material.

Lighting: one sun lamp per image (direction and intensity as written) and, optionally,
a dim uniform white environment (``environment``: strength relative to the sun's
irradiance, the same in every image of the capture, recorded in ``scene.json`` as
``environment_strength``; 0 = black world, the paper's set-up). The environment is the
ambient light a real capture has in its attached shadows; it is not in the lights files,
so every image then holds the sun's term *plus* the ambient term.

Blender (bpy) is needed only to render: :mod:`cnnps.synth.blender_renderer`, the one
module that imports it, is imported when a folder actually has images to render, and
without bpy that is one clear :class:`cnnps.infra.errors.ConfigError`
(:func:`cnnps.synth.blender_renderer.require_blender`). A complete folder is recognised
without Blender.
"""

from __future__ import annotations

import glob
import json
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from cnnps.infra.atomic import atomic_path, publish_mode, write_text
from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.hashing import (
    add_json_checksum,
    bytes_sha256,
    check_file_record,
    derive_seed,
    file_record,
    file_sha256,
    json_checksum_ok,
    stable_hash,
)
from cnnps.infra.progress import progress_bar
from cnnps.infra.stage_folders import read_json

VERSION = 1  # bump when what is written for the same inputs changes (part of every render key)
# what a capture is covered with: white Lambertian, or a materials-stage category on superpixels
Material = Literal["lambertian", "diffuse", "specular", "metallic", "narrow"]
MATERIAL_KINDS = get_args(Material)
# the settings that change the pictures (part of the content key); not device or threads
PICTURE_FIELDS = ("size", "samples", "lights", "jitter_deg", "min_elevation_deg", "light_intensity", "max_bounces", "seed")
SCENE_INDENT = 2  # scene.json is json.dumps(..., indent=2) + "\n": its checksum hashes that form
SCENE_TIMINGS = ("render_seconds", "images_rendered_last_run")  # not in its checksum: they vary between runs
LIGHT_FILES = ("filenames.txt", "light_directions.txt", "light_intensities.txt")
GEOMETRY_FILES = ("mask.png", "normal_gt.npy")


@dataclass(frozen=True)
class RenderSettings:
    """How captures are rendered (the render stage's ``Params`` extend it); validated."""

    size: int = 128  # image width = height (pixels); the camera covers x, y in [-1, 1]
    samples: int = 64  # Cycles path samples per pixel
    lights: int = 50  # lights per scene
    jitter_deg: float = 3.0  # random offset of each direction from the Fibonacci spiral
    min_elevation_deg: float = 5.0  # lights stay this far above the horizon
    light_intensity: float = 1.0  # sun irradiance: a white Lambertian patch facing it reads this
    max_bounces: int = 8  # Cycles max bounces (all kinds): global illumination
    device: str = "cpu"  # cpu | gpu
    seed: int = 0
    threads: int = 0  # Cycles threads per scene (0 = all cores; the stage: the executor's threads_per_job)

    def __post_init__(self):
        def bad(msg):
            raise ConfigError(f"render.{msg}")

        for name in ("size", "samples", "lights"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                bad(f"{name} must be a positive integer, got {v!r}")
        if self.lights < 3:
            bad(f"lights must be >= 3 (photometric stereo needs three), got {self.lights}")
        if self.size > 8192:
            bad(f"size must be <= 8192, got {self.size}")
        if not 0.0 <= self.jitter_deg <= 90.0:
            bad(f"jitter_deg must be in [0, 90], got {self.jitter_deg}")
        if not 0.0 <= self.min_elevation_deg < 90.0:
            bad(f"min_elevation_deg must be in [0, 90), got {self.min_elevation_deg}")
        if not (self.light_intensity > 0 and np.isfinite(self.light_intensity)):
            bad(f"light_intensity must be > 0, got {self.light_intensity}")
        if not isinstance(self.max_bounces, int) or self.max_bounces < 0:
            bad(f"max_bounces must be an integer >= 0, got {self.max_bounces!r}")
        if self.device not in ("cpu", "gpu"):
            bad(f"device must be 'cpu' or 'gpu', got {self.device!r}")
        if self.threads < 0:
            bad(f"threads must be >= 0, got {self.threads}")

    def picture_params(self) -> dict:
        """The settings that change the rendered pictures (part of the content key)."""
        return {k: getattr(self, k) for k in PICTURE_FIELDS}


def capture_key(inputs: dict, environment: float = 0.0) -> str:
    """Content key of a capture: ``stable_hash(inputs)``, with ``environment`` added to
    the hashed dict only when it is non-zero, so captures without an environment light
    keep the keys they had before the option existed."""
    if environment:
        inputs = {**inputs, "environment": float(environment)}
    return stable_hash(inputs)


def image_names(n: int) -> list[str]:
    """``000.exr`` ... for ``n`` lights (zero-padded to at least three digits)."""
    width = max(3, len(str(n - 1)))
    return [f"{i:0{width}d}.exr" for i in range(n)]


def extend_maps(maps: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, np.ndarray]:
    """Fill every map outside ``mask`` with its nearest mask pixel's value."""
    from scipy.ndimage import distance_transform_edt

    if not mask.any() or mask.all():
        return maps
    _, (ri, ci) = distance_transform_edt(~mask, return_indices=True)
    return {k: (v[ri, ci] if np.ndim(v) >= 2 else v) for k, v in maps.items()}


def lambertian_material(albedo=1.0) -> dict:
    """Renderer material: a Lambertian (Diffuse BSDF, roughness 0) of ``albedo`` (scalar, RGB or map)."""
    return {"bsdf": "lambertian", "Color": albedo}


def principled_material(params: dict[str, np.ndarray]) -> dict:
    """Renderer material (Blender Principled inputs) from paper parameter maps, through
    :func:`cnnps.synth.bsdf.to_blender_inputs`: RGBA colours become RGB, maps that hold one
    value everywhere become constants (no texture)."""
    from cnnps.synth.bsdf import to_blender_inputs

    out: dict[str, Any] = {"bsdf": "principled"}
    for name, value in to_blender_inputs(params).items():
        arr = np.asarray(value, dtype=np.float32)
        if arr.ndim >= 1 and arr.shape[-1] == 4 and (arr.ndim == 1 or arr.ndim == 3):
            arr = arr[..., :3]  # RGBA -> RGB (alpha 1)
        if arr.ndim >= 2:
            flat = arr.reshape(arr.shape[0] * arr.shape[1], -1)
            if np.all(flat == flat[0]):
                arr = flat[0] if flat.shape[1] > 1 else flat[0, 0]
        out[name] = arr
    return out


def _write_lights(out: Path, L: np.ndarray, intensity: float, names: list[str]) -> None:
    write_text(out / "light_directions.txt", "".join(f"{x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in L))
    write_text(out / "light_intensities.txt", "".join(f"{intensity:.9g} {intensity:.9g} {intensity:.9g}\n" for _ in L))
    write_text(out / "filenames.txt", "".join(n + "\n" for n in names))


def is_complete(out: Path, key: str, verify: bool = True) -> bool:
    """Whether ``out`` is a finished capture of ``key``: its ``scene.json`` holds the key
    and every image it lists exists (no Blender needed to tell) and, with ``verify``, the
    folder matches the checksums ``scene.json`` records (:func:`folder_problems`: one
    read of every file)."""
    meta = read_json(out / "scene.json")
    if not meta or meta.get("key") != key:
        return False
    names = meta.get("filenames") or []
    if not (bool(names) and all((out / n).is_file() for n in names) and (out / "normal_gt.npy").is_file()):
        return False
    return not verify or not folder_problems(out, meta)


def folder_problems(out: Path, meta: dict | None = None) -> list[tuple[Path, str]]:
    """``(file, problem)`` for every file of the finished capture ``out`` that does not
    match what its ``scene.json`` (``meta``: read when None) records: the record's own
    checksum first (a ``scene.json`` edited by hand cannot vouch for anything, so it is
    the only problem then), then each file's size and SHA-256. Empty when all match, or
    when ``scene.json`` predates checksums (nothing to check against)."""
    out = Path(out)
    if meta is None:
        meta = read_json(out / "scene.json") or {}
    ok = json_checksum_ok(meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    if ok is False:
        return [(out / "scene.json", "edited by hand or damaged: its content does not match its checksum")]
    problems = []
    for name, record in (meta.get("files") or {}).items():
        problem = check_file_record(out / name, record)
        if problem is not None:
            problems.append((out / name, problem))
    return problems


def decode_problem(path: Path) -> str | None:
    """Why a file of a capture folder without a checksum record cannot be kept (not
    readable by its decoder, or NaN / infinite values), or None when it reads as a whole."""
    from cnnps.io.images import read_image_raw

    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
            if not np.issubdtype(arr.dtype, np.number) or arr.ndim != 3 or not np.isfinite(arr).all():
                return "not a finite H x W x 3 normal map"
        else:
            arr = read_image_raw(path)
            if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
                return "holds NaN or infinite pixels"
    except InputError as exc:
        return exc.problem
    except Exception as exc:  # noqa: BLE001 - any decoder failure: the file is damaged
        return f"unreadable ({type(exc).__name__})"
    return None


def _drop_damaged(out: Path, names: list[str], records: dict) -> list[str]:
    """Delete the images, mask and normals of ``out`` that do not match their record
    (``records``: name -> {"bytes", "sha256"}) or, without one, do not decode as whole
    finite files; they are rendered again. Returns the names deleted."""
    dropped = []
    for name in list(names) + list(GEOMETRY_FILES):
        path = out / name
        if not path.is_file():
            continue
        record = records.get(name)
        problem = check_file_record(path, record) if record else decode_problem(path)
        if problem is not None:
            path.unlink()
            dropped.append(name)
    if any(n in dropped for n in GEOMETRY_FILES):  # written together: redo both
        for n in GEOMETRY_FILES:
            (out / n).unlink(missing_ok=True)
    return dropped


def render_into(
    out: Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    material: dict | Any,
    *,
    key: str,
    lights: np.ndarray,
    intensity: float,
    size: int,
    samples: int,
    seed: int,
    max_bounces: int = 8,
    device: str = "cpu",
    threads: int = 0,
    meta: dict | None = None,
    progress: bool = True,
    desc: str = "render",
    environment: float = 0.0,
) -> dict:
    """Render one capture folder, resuming a partial one with the same ``key``.

    ``material``: a renderer material dict (see :mod:`cnnps.synth.blender_renderer`), or a
    callable ``mask -> material dict`` called with Blender's mask (for maps drawn on it).
    ``environment``: strength s of a dim uniform white world relative to the sun's
    irradiance (0 = black world, as the paper): an unoccluded white Lambertian patch reads
    ``s * intensity`` from it, in *every* image (the ambient term a real capture has);
    the light directions and intensities written stay the sun's. Put a non-zero ``s`` in
    ``key`` (the callers do); it is recorded in scene.json (``environment_strength``).
    Returns ``{"rendered": number of images rendered now, "skipped": bool}``.

    Steps: skip a complete folder (or take back the version a killed re-render set
    aside); :func:`_prepare_folder` (resume or start afresh); :func:`_geometry_and_material`
    (mask, normals, a material drawn on the mask); :func:`_render_missing_images`;
    :func:`_scene_record` and :func:`_write_scene_json` (the completion marker). A failure
    puts the previous complete version back.
    """
    if not (np.isfinite(environment) and environment >= 0):
        raise ConfigError(f"render environment strength must be a finite number >= 0, got {environment!r}")
    out = Path(out)
    if is_complete(out, key):
        return {"rendered": 0, "skipped": True}
    if _take_back_previous(out, key):  # a killed re-render left the version this key asks for
        return {"rendered": 0, "skipped": True}
    _check_not_foreign(out)  # before Blender starts
    _forget_inherited_blender_paths()
    from cnnps.synth.blender_renderer import BlenderRenderer, require_blender

    require_blender()  # one clear line without bpy, before the folder is touched

    prev = previous_path(out)
    try:
        t0 = time.perf_counter()
        # the renderer first: a bad device fails before the folder is touched
        with BlenderRenderer(size, samples, device=device, threads=threads, seed=seed, max_bounces=max_bounces,
                             environment=float(environment) * float(intensity)) as r:
            names = image_names(len(lights))
            lights = _prepare_folder(out, key, lights, intensity, names)
            r.load_scene(vertices, faces, material if isinstance(material, dict) else lambertian_material())
            _geometry_and_material(r, out, material)
            rendered = _render_missing_images(r, out, names, lights, intensity, progress=progress, desc=desc)
            gpus = getattr(r, "gpu_devices", None)
        scene = _scene_record(
            out, meta, key=key, names=names, size=size, samples=samples, max_bounces=max_bounces,
            intensity=intensity, seed=seed, device=device, threads=threads, gpus=gpus, environment=environment,
            t0=t0, rendered=rendered,
        )
        _write_scene_json(out, scene)
    except BaseException:
        _restore_previous(out, prev)  # a failed re-render leaves the last complete version
        raise
    if prev.is_dir():  # the new version is complete: the previous one goes
        shutil.rmtree(prev)
    return {"rendered": rendered, "skipped": False}


def _prepare_folder(out: Path, key: str, lights: np.ndarray, intensity: float, names: list[str]) -> np.ndarray:
    """Make ``out`` ready for the images still missing; the light directions to render with.

    A folder of this ``key`` (unfinished, or finished with damaged files) whose light files
    are intact is resumed with the directions it holds (:func:`_reopen`); any other is
    started afresh with ``lights``, a finished capture of another key set aside until the
    new one is complete."""
    records = _resume_records(out, key)
    written = None if records is None else _written_lights(out, lights)
    if written is None:
        _set_aside(out)
        return _start_folder(out, key, lights, intensity, names)
    _reopen(out, key, names, records)
    return written


def _resume_records(out: Path, key: str) -> dict | None:
    """The file records ``out`` is resumed with (``{}`` when its ``scene.json`` has none or
    cannot be trusted), or None when it cannot be resumed: a finished folder only when its
    ``scene.json`` is the one we wrote for ``key`` and its light files are intact, an
    unfinished one when its ``.pending.json`` holds ``key``."""
    pending = read_json(out / ".pending.json") or {}
    done_meta = read_json(out / "scene.json") or {}
    done_ok = (done_meta.get("key") == key
               and json_checksum_ok(done_meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS) is not False)
    records = (done_meta.get("files") or {}) if done_ok else {}
    resume = (pending.get("key") == key or done_ok) and (out / "light_directions.txt").is_file()
    if resume and any(check_file_record(out / n, records[n]) for n in LIGHT_FILES if n in records):
        resume = False
    return records if resume else None


def _written_lights(out: Path, lights: np.ndarray) -> np.ndarray | None:
    """The directions ``out/light_directions.txt`` holds (those of the interrupted run), or
    None when they do not read as an array shaped like ``lights``."""
    try:
        L = np.loadtxt(out / "light_directions.txt", ndmin=2)
    except ValueError:
        L = np.zeros((0, 3))
    return L if L.shape == np.shape(lights) else None


def _reopen(out: Path, key: str, names: list[str], records: dict) -> None:
    """Resume ``out``: unfinished again, without the files a killed run half-wrote and
    without its damaged (or unverifiable and unreadable) files, which are rendered again."""
    if (out / "scene.json").is_file():
        # not complete any more: a killed resume must find .pending.json, not nothing
        write_text(out / ".pending.json", json.dumps({"key": key}) + "\n")
        (out / "scene.json").unlink()
    remove_temp_files(out)  # half-written files of the killed run
    _drop_damaged(out, names, records)  # damaged (or unverifiable and unreadable) files


def _geometry_and_material(r, out: Path, material: dict | Any) -> None:
    """Blender's mask and normals (one extra render) when the folder lacks them or the
    material is drawn on the mask: written if missing, an empty mask refused
    (InputError), and a callable ``material`` set from the mask."""
    from cnnps.io.images import write_png

    have_geometry = (out / "mask.png").is_file() and (out / "normal_gt.npy").is_file()
    if not have_geometry or callable(material):
        mask, normal = r.render_geometry()
        if not mask.any():
            raise InputError(out, "the mesh covers no pixel of the image (empty mask)")
        if callable(material):
            r.set_material(material(mask))
        if not have_geometry:
            with atomic_path(out / "normal_gt.npy") as tmp:
                np.save(tmp, normal)
            write_png(out / "mask.png", mask.astype(np.uint8) * 255)


def _render_missing_images(r, out: Path, names: list[str], lights: np.ndarray, intensity: float, *,
                           progress: bool, desc: str) -> int:
    """Render every image of ``names`` not in ``out`` yet, each written atomically; how many."""
    from cnnps.io.images import write_exr

    todo = [i for i, n in enumerate(names) if not (out / n).is_file()]
    rendered = 0
    for i in progress_bar(todo, desc=desc, unit="light", leave=False, disable=not progress or not todo):
        write_exr(out / names[i], r.render(lights[i], intensity))
        rendered += 1
    return rendered


def _scene_record(out: Path, meta: dict | None, *, key: str, names: list[str], size: int, samples: int,
                  max_bounces: int, intensity: float, seed: int, device: str, threads: int, gpus,
                  environment: float, t0: float, rendered: int) -> dict:
    """The contents of ``scene.json`` (``meta`` first), without its checksum: the settings,
    the renderer, the timings and the size and SHA-256 of every other file."""
    from cnnps.synth.blender_renderer import blender_version

    scene = dict(meta or {})
    scene.update(
        {
            "key": key,
            "filenames": names,
            "n_lights": len(names),
            "size": size,
            "samples": samples,
            "max_bounces": max_bounces,
            "light_intensity": intensity,
            "seed": seed,
            "device": device,
            "threads": threads,  # Cycles threads (0 = Blender's default: all cores)
            "gpu_devices": gpus,
            "blender_version": blender_version(),
            "renderer": "Cycles: orthographic camera, sun lamps (angle 0), "
            + ("black world" if environment == 0 else "uniform white world (environment_strength x the sun's irradiance)")
            + ", Gaussian 0.01 px filter, no denoising, no clamping",
            # relative to the sun's irradiance; 0 = none. In every image; lights files stay the sun's
            "environment_strength": float(environment),
            "mask_normal_source": "Blender camera rays through pixel centres: alpha and smooth shading normal",
            "render_seconds": round(time.perf_counter() - t0, 3),
            "images_rendered_last_run": rendered,
            "version": VERSION,
            # size and SHA-256 of every other file: what is_complete and the extract stage verify
            "files": {n: file_record(out / n) for n in list(LIGHT_FILES) + list(GEOMETRY_FILES) + names},
        }
    )
    return scene


def _write_scene_json(out: Path, scene: dict) -> None:
    """``scene.json`` with its checksum, written last: the folder is complete."""
    scene = add_json_checksum(scene, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    write_text(out / "scene.json", json.dumps(scene, indent=SCENE_INDENT) + "\n")
    (out / ".pending.json").unlink(missing_ok=True)

def _forget_inherited_blender_paths() -> None:
    """Drop Blender's script folders from ``sys.path`` in a process that has not imported bpy.

    ``import bpy`` adds ``.../site-packages/bpy/<version>/scripts/modules`` (and others)
    to ``sys.path``; that folder holds the *Python half* of bpy, also named ``bpy``. A
    worker spawned by a process that had imported bpy (the local executor's pool after an
    in-process render) inherits that ``sys.path``, and its ``import bpy`` then finds the
    Python half first and fails with "No module named '_bpy'". bpy adds the folders back
    when it is imported.
    """
    import os
    import sys

    if "bpy" in sys.modules:
        return
    marker = f"{os.sep}bpy{os.sep}"
    sys.path[:] = [p for p in sys.path if not (marker in p and f"{os.sep}scripts" in p)]


# the temporary names of cnnps.infra.atomic: ``.{stem}.XXXXXXXX.tmp{suffix}`` (atomic_path) and
# ``.{name}.XXXXXXXX.tmp`` (atomic_dir, and _start_folder's build folder)
_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def remove_temp_files(folder: Path) -> list[Path]:
    """Delete the hidden temporary files (and folders) that atomic writes left in ``folder``
    when their process was killed. Call it only while no other job writes there."""
    removed = []
    for p in Path(folder).iterdir():
        if _TEMP_NAME.match(p.name):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def is_render_folder(path: Path) -> bool:
    """Whether ``path`` is a capture folder :func:`render_into` wrote (finished or not)."""
    return path.is_dir() and ((path / ".pending.json").is_file() or (path / "scene.json").is_file())


def _check_not_foreign(out: Path) -> None:
    """Refuse an existing ``out`` that holds something not of ours (never delete it)."""
    if out.exists() and not is_render_folder(out) and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out.absolute(), "exists and is not a cnnps render folder; choose a new or empty folder")


def previous_path(out: Path) -> Path:
    """Where a finished capture waits while ``out`` is rendered again for another key:
    the hidden sibling ``.<name>.previous`` (readers of a render folder skip hidden names)."""
    return out.parent / f".{out.name}.previous"


def _set_aside(out: Path) -> None:
    """Move a finished capture (``scene.json``) at ``out`` to :func:`previous_path`, so a
    re-render for another key that fails (a full disk) can put it back."""
    if not (out / "scene.json").is_file():
        return
    prev = previous_path(out)
    if prev.exists():
        shutil.rmtree(prev)
    out.rename(prev)


def _restore_previous(out: Path, prev: Path) -> None:
    """After a failed re-render: the set-aside version back at ``out``, the partial one gone."""
    if not prev.is_dir():
        return
    if out.exists():
        shutil.rmtree(out, ignore_errors=True)
    prev.rename(out)


def _take_back_previous(out: Path, key: str) -> bool:
    """A set-aside version that is complete for ``key`` (a re-render for another key was
    killed, then the parameters went back) replaces ``out``; True when it did."""
    prev = previous_path(out)
    if not (prev.is_dir() and is_complete(prev, key)):
        return False
    if out.exists():
        shutil.rmtree(out)
    prev.rename(out)
    return True


def _start_folder(out: Path, key: str, lights: np.ndarray, intensity: float, names: list[str]) -> np.ndarray:
    """Make ``out`` hold ``.pending.json`` (the key) and the light files, so a folder with
    this key always has its lights. Returns the light directions to render, as read back
    from ``light_directions.txt`` (a resumed run reads the same numbers).

    Only a folder of ours (``.pending.json`` or ``scene.json``) is emptied; any other
    non-empty ``out`` is refused (InputError). A new folder is built under a temporary
    name and renamed into place; if a duplicate of this job created it meanwhile (same
    key), its lights are used. An existing empty folder (or one of ours, emptied) is
    filled in place: marker without a key first, so a kill leaves it recognisably ours.
    """
    import tempfile

    if is_render_folder(out):  # another key, or killed while being set up
        write_text(out / ".pending.json", json.dumps({"key": None}) + "\n")
        for p in out.iterdir():
            if p.name == ".pending.json":
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
    else:
        _check_not_foreign(out)

    if out.is_dir():  # empty (but for our key-less marker)
        write_text(out / ".pending.json", json.dumps({"key": None}) + "\n")
        _write_lights(out, lights, intensity, names)
        write_text(out / ".pending.json", json.dumps({"key": key}) + "\n")
        return np.loadtxt(out / "light_directions.txt", ndmin=2)

    out.parent.mkdir(parents=True, exist_ok=True)
    build = re.compile(rf"^\.{re.escape(out.name)}\.[A-Za-z0-9_]{{8}}\.tmp$")
    for p in out.parent.glob(f".{glob.escape(out.name)}.*.tmp"):  # build folders of killed runs
        if p.is_dir() and build.match(p.name):
            shutil.rmtree(p, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        write_text(tmp / ".pending.json", json.dumps({"key": key}) + "\n")
        _write_lights(tmp, lights, intensity, names)
        publish_mode(tmp, is_dir=True)  # mkdtemp made it private (0700)
        tmp.rename(out)
    except OSError:  # out appeared meanwhile (a duplicate job): resume what it started
        pending = read_json(out / ".pending.json") or read_json(out / "scene.json") or {}
        if pending.get("key") != key or not (out / "light_directions.txt").is_file():
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return np.loadtxt(out / "light_directions.txt", ndmin=2)


def load_mesh_arg(mesh) -> tuple[Any, dict]:
    """A trimesh from a Trimesh, a file path or ``procedural:<kind>[:seed]``."""
    import trimesh

    if isinstance(mesh, trimesh.Trimesh):
        return mesh, {"mesh": "in-memory"}
    text = str(mesh)
    if text.startswith("procedural:"):
        from cnnps.synth.procedural import make_shape

        parts = text.split(":")
        kind = parts[1] if len(parts) > 1 else ""
        try:
            shape_seed = int(parts[2]) if len(parts) > 2 else 0
        except ValueError:
            raise ConfigError(f"procedural mesh seed must be an integer: {text!r}") from None
        return make_shape(kind, shape_seed), {"mesh": text}
    from cnnps.synth.meshes import load_mesh

    path = Path(text)
    return load_mesh(path), {"mesh": str(path), "mesh_sha256": file_sha256(path) if path.is_file() else None}


def capture_material(material: str, superpixels: int, seed: int):
    """The renderer material of a capture: the white Lambertian dict for ``lambertian``,
    else a callable ``mask -> material dict`` drawing the category on ``superpixels``
    superpixels of the mask with ``seed``; a ConfigError for an unknown category."""
    if material not in MATERIAL_KINDS:
        raise ConfigError(f"material must be one of {', '.join(MATERIAL_KINDS)}, got {material!r}")
    if superpixels < 1:
        raise ConfigError(f"superpixels must be >= 1, got {superpixels}")
    if material == "lambertian":
        return lambertian_material()

    def mat(mask: np.ndarray) -> dict:
        from cnnps.synth.material_maps import sample_material_maps

        maps = sample_material_maps(mask, material, superpixels, derive_seed(int(seed), "material"))
        return principled_material(extend_maps(dict(maps.params), mask))

    return mat


def capture_lights(p: RenderSettings) -> np.ndarray:
    """(lights, 3) unit directions of a capture's lights: the hemisphere spiral with
    ``p.jitter_deg`` of jitter, seeded by ``p.seed``."""
    from cnnps.synth.lights import hemisphere_lights

    return hemisphere_lights(p.lights, p.jitter_deg, seed=derive_seed(int(p.seed), "lights"),
                             min_elevation_deg=p.min_elevation_deg)


def render_capture(
    mesh,
    out_dir: str | Path,
    lights: int = 40,
    size: int = 64,
    samples: int = 16,
    material: str = "lambertian",
    superpixels: int = 20,
    seed: int = 0,
    device: str = "cpu",
    jitter_deg: float = 0.0,
    light_intensity: float = 1.0,
    max_bounces: int = 8,
    threads: int = 0,
    progress: bool = True,
    environment: float = 0.0,
) -> Path:
    """Render one capture folder of ``mesh`` (a Trimesh in the camera frame, a mesh file,
    normalised into the unit sphere, or ``procedural:<kind>[:seed]``) and return its path.

    material: ``lambertian`` (white Lambertian, albedo 1: pixel = max(0, n.l) plus
    interreflections) or a category of the materials stage (``diffuse``, ``specular``,
    ``metallic``, ``narrow``) drawn on ``superpixels`` superpixels of the mask with ``seed``.
    ``environment``: a dim uniform white world, strength relative to the sun's irradiance
    (:func:`render_into`; 0 = black world, and then the key is the same as before it existed).
    """
    mat = capture_material(material, superpixels, seed)
    if not (np.isfinite(environment) and environment >= 0):
        raise ConfigError(f"environment must be a finite number >= 0, got {environment!r}")
    p = RenderSettings(
        size=size, samples=samples, lights=lights, jitter_deg=jitter_deg, light_intensity=light_intensity,
        max_bounces=max_bounces, device=device, seed=seed, threads=threads,
    )  # validation
    tm, info = load_mesh_arg(mesh)
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces, dtype=np.int64)
    mesh_hash = bytes_sha256(vertices.astype(np.float32).tobytes(), faces.astype(np.int64).tobytes())
    L = capture_lights(p)

    key = capture_key({"mesh": mesh_hash, "material": [material, superpixels], "params": p.picture_params(), "v": VERSION},
                      environment)
    out = Path(out_dir)
    meta = {"mesh_sha256": mesh_hash, "material": material, "superpixels": superpixels, **info}
    render_into(
        out, vertices, faces, mat, key=key, lights=L, intensity=p.light_intensity, size=p.size,
        samples=p.samples, seed=seed, max_bounces=p.max_bounces, device=p.device, threads=p.threads,
        meta=meta, progress=progress, desc=out.name, environment=environment,
    )
    return out
