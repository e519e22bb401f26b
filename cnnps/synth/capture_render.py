"""The one Cycles capture renderer: a scene description and render settings in, a capture
folder out, resumable. What the render stage, ``cnnps render`` / :func:`cnnps.render`,
the eval stage's test set (and its rig twins) and the calibration sets render with.

The interface (kubric-style: scene + settings -> renderer -> folder)::

    scene = Scene(vertices, faces, lambertian_material(), lights=L)          # L (m, 3) unit
    render_into("cap", scene, RenderSettings(size=64, samples=8), key="k")   # -> {"rendered": m, ...}
    # a rig: pinhole camera of 40 degrees, point lights 3 object radii from its centre
    render_into("rig", Scene(vertices, faces, material, L, fov_deg=40.0, light_distance=3.0), settings, key="k2")

:class:`Scene` says what is seen (mesh, material, light directions, camera, light model,
ambient world); :class:`RenderSettings` how it is rendered (the names and defaults every
front end shares: ``cnnps.render``'s keyword arguments, ``cnnps render``'s options and the
render stage's ``render:`` section); :func:`render_into` writes the folder through
:mod:`cnnps.io.capture`. :func:`render_capture` does it all for one mesh (a Trimesh, a
mesh file or ``procedural:<kind>[:seed]``) and a :class:`CaptureSettings` (the settings
plus material, camera and lights), with its own content key.

The folder (docs/ARCHITECTURE.md): ``000.exr ...`` (float32 linear RGB, names zero-padded
to the light count), ``filenames.txt``, ``light_intensities.txt``, ``mask.png``,
``normal_gt.npy`` and ``scene.json``, and

- orthographic camera (``fov_deg`` None: it covers x, y in [-1, 1]): nothing more; suns:
  ``light_directions.txt`` (unit, camera frame);
- pinhole camera (``fov_deg`` F, at :data:`cnnps.synth.blender_renderer.CAMERA_ORIGIN`
  (0, 0, 5) looking down -z, F across the square image): ``intrinsics.txt`` (K, OpenCV)
  and ``depth_gt.npy`` (H x W depth along the optical axis, NaN outside the mask;
  ``scene.json`` records its median as ``median_depth``); with suns
  ``light_directions.txt``, with point lights (``light_distance`` d: at d times each
  direction from the object's centre, radiant intensity ``light_intensity``: a white
  Lambertian patch facing one at distance r reads I / r^2) ``light_positions.txt``
  (capture frame: origin at the camera's optical centre, i.e. world - (0, 0, 5)).

Caching and resuming (every camera and light model alike). A folder whose ``scene.json``
holds the current key and all its images is skipped (:func:`is_complete`). Otherwise the
folder appears (built under a temporary name, then renamed) already holding
``.pending.json`` (the key) and the light files (and the intrinsics), so the lights are
fixed FIRST (and every run renders with the directions or positions read back from the
file); each image is written atomically (temp name, rename); ``scene.json`` is written
LAST as the completion marker. A rerun after a kill finds ``.pending.json`` with the same
key, deletes the temporary files the kill left (:func:`remove_temp_files`), and renders
only the missing images with the same lights; a different key empties the folder. Only
folders of ours (``.pending.json`` or ``scene.json``: :func:`is_render_folder`) are ever
emptied: an existing non-empty folder without them is refused (InputError), an existing
empty one is filled in place. The images of a folder depend only on its key and seeds
(Cycles is deterministic per seed), so a retried or duplicated job resumes or rewrites
the same pixels.

Checksums. ``scene.json`` records every other file of the folder (``files``: name ->
``{"bytes", "sha256"}``) and a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`, indent 2, leaving out the two timing fields
``render_seconds`` and ``images_rendered_last_run``, so it is the same for every run that
writes the same folder). :func:`is_complete` verifies them
(a truncated, NaN-filled or byte-flipped image, or a ``scene.json`` edited by hand, makes
the folder incomplete), and :func:`render_into` then redoes exactly the damaged part:
damaged images (or the mask, normals and depth) are deleted and re-rendered with the same
lights and seeds, so the folder ends with the bytes it had; damaged light files (or
intrinsics) or an untrustworthy ``scene.json`` re-render the whole capture. Files of a
killed run (no record yet) are checked by decoding (readable, finite) before they are
kept. :func:`folder_problems` tells a reader (the extract stage) what does not match. The
key does not depend on these entries, and a ``scene.json`` without them (no ``files``, no
``checksum``) is complete when every file exists (only existence is checked).

Mask and ground truth come from Blender itself (one extra 1-sample render, two with the
pinhole camera): the mask is the alpha of the camera rays through the pixel centres,
``normal_gt`` is the smooth shading normal at those hits, i.e. exactly the normal the
BSDFs were lit with (agreeing with the shading by construction; for meshes of the meshes
stage it matches the analytic/rasterised normal up to Blender's vertex-normal
interpolation), and ``depth_gt`` the depth of those hits. Material maps are extended
outward by nearest neighbour (:func:`extend_maps`), so a silhouette pixel that Blender
covers but the materials' rasteriser did not still gets its neighbour's material.

Lighting: one lamp per image (direction or position and intensity as written) and,
optionally, a dim uniform white environment (``environment`` s: a white Lambertian patch
reads s x ``light_intensity`` from it, the same in every image of the capture, recorded
in ``scene.json`` as ``environment_strength``; 0 = black world, the paper's set-up). The
environment is the ambient light a real capture has in its attached shadows; it is not in
the lights files, so every image then holds the lamp's term *plus* the ambient term.

Content keys (:func:`capture_key`): a pinhole camera, point lights and an environment
each enter the hashed inputs only when used, so an orthographic capture under suns in a
black world is keyed by its inputs alone.

Blender (bpy) is needed only to render: :mod:`cnnps.synth.blender_renderer`, the one
module that imports it, is imported when a folder actually has images to render, and
without bpy that is one clear :class:`cnnps.infra.errors.ConfigError`
(:func:`cnnps.synth.blender_renderer.require_blender`). A complete folder is recognised
without Blender.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from cnnps.infra.atomic import publish_mode, write_text
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
from cnnps.io.capture import (
    DEPTH_GT_FILE,
    FILENAMES_FILE,
    INTRINSICS_FILE,
    LIGHT_DIRECTIONS_FILE,
    LIGHT_INTENSITIES_FILE,
    LIGHT_POSITIONS_FILE,
    MASK_FILE,
    NORMAL_GT_FILE,
    SCENE_FILE,
    SCENE_INDENT,
    Capture,
    read_light_directions,
    write_capture_files,
    write_depth_gt,
    write_image,
    write_mask,
    write_normal_gt,
    write_scene,
)
from cnnps.io.capture.files import read_depth_gt, read_light_positions
from cnnps.synth.bsdf import CategoryRanges, MaterialRanges

VERSION = 1  # bump when what is written for the same inputs changes (part of every render key)
# what a capture is covered with: white Lambertian, or a materials-stage category on superpixels
Material = Literal["lambertian", "diffuse", "specular", "metallic", "narrow"]
MATERIAL_KINDS = get_args(Material)
# the settings that change the pictures (part of the content key); not device or threads
PICTURE_FIELDS = ("size", "samples", "lights", "jitter_deg", "min_elevation_deg", "light_intensity", "max_bounces", "seed")
# scene.json is written by cnnps.io.capture.write_scene (indent SCENE_INDENT): its checksum hashes that form
SCENE_TIMINGS = ("render_seconds", "images_rendered_last_run")  # not in its checksum: they vary between runs
LIGHT_FILES = (FILENAMES_FILE, LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE)  # suns (Scene.light_files)
GEOMETRY_FILES = (MASK_FILE, NORMAL_GT_FILE)  # orthographic camera (Scene.geometry_files)
PENDING_FILE = ".pending.json"  # the key of a folder being rendered; SCENE_FILE replaces it at the end
RENDER_MARKERS = (SCENE_FILE, PENDING_FILE)  # a folder holding one is a render folder (ours to empty)
MAX_FOV_DEG = 120.0  # a pinhole camera's field of view is in (0, MAX_FOV_DEG)
# point lights: outside the object's unit sphere and in front of the camera at distance 5 (open interval)
LIGHT_DISTANCE_RANGE = (1.0, 5.0)


def _bad(msg: str):
    raise ConfigError(f"render.{msg}")


def _is_count(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_finite(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and bool(np.isfinite(v))


@dataclass(frozen=True)
class RenderSettings:
    """How captures are rendered; validated (a ConfigError naming ``render.<field>``).

    The one set of names and defaults of every front end: :func:`cnnps.render`'s keyword
    arguments and ``cnnps render``'s options (through :class:`CaptureSettings`, which adds
    the scene's material, camera and lights) and the render stage's ``render:`` section
    (its ``Params`` extend this class; params.yaml and the presets set their own values).

    size: image width = height in pixels. samples: Cycles path samples per pixel.
    lights: lights per capture, over the upper hemisphere (Fibonacci spiral,
    :func:`capture_lights`); jitter_deg: random offset of each direction from the spiral;
    min_elevation_deg: every light at least this far above the horizon.
    light_intensity: the lamps' intensity (sun: irradiance, a white Lambertian patch facing
    it reads this; point light: radiant intensity, it reads this / r^2).
    max_bounces: Cycles bounces of every kind (global illumination). device: "cpu" or
    "gpu". seed: the seed lights, materials and Cycles' sampling are drawn from.
    threads: Cycles CPU threads (0 = all cores; the render stage: the executor's share).

    :func:`render_into` reads size, samples, light_intensity, max_bounces, device, seed
    (the Cycles seed) and threads; lights, jitter_deg and min_elevation_deg say how a front
    end draws a scene's directions. Example: ``RenderSettings(size=64, samples=8)``.
    """

    size: int = 128
    samples: int = 32
    lights: int = 40
    jitter_deg: float = 0.0
    min_elevation_deg: float = 5.0
    light_intensity: float = 1.0
    max_bounces: int = 8
    device: str = "cpu"  # cpu | gpu
    seed: int = 0
    threads: int = 0

    def __post_init__(self):
        for name in ("size", "samples", "lights"):
            v = getattr(self, name)
            if not _is_count(v) or v < 1:
                _bad(f"{name} must be a positive integer, got {v!r}")
        if self.lights < 3:
            _bad(f"lights must be >= 3 (photometric stereo needs three), got {self.lights}")
        if self.size > 8192:
            _bad(f"size must be <= 8192, got {self.size}")
        if not 0.0 <= self.jitter_deg <= 90.0:
            _bad(f"jitter_deg must be in [0, 90], got {self.jitter_deg}")
        if not 0.0 <= self.min_elevation_deg < 90.0:
            _bad(f"min_elevation_deg must be in [0, 90), got {self.min_elevation_deg}")
        if not (self.light_intensity > 0 and np.isfinite(self.light_intensity)):
            _bad(f"light_intensity must be > 0, got {self.light_intensity}")
        if not isinstance(self.max_bounces, int) or self.max_bounces < 0:
            _bad(f"max_bounces must be an integer >= 0, got {self.max_bounces!r}")
        if self.device not in ("cpu", "gpu"):
            _bad(f"device must be 'cpu' or 'gpu', got {self.device!r}")
        if self.threads < 0:
            _bad(f"threads must be >= 0, got {self.threads}")

    def picture_params(self) -> dict:
        """The settings that change the rendered pictures (part of the content key)."""
        return {k: getattr(self, k) for k in PICTURE_FIELDS}


def check_camera_and_lights(fov_deg: float | None, light_distance: float | None, environment: float = 0.0) -> None:
    """A ConfigError unless ``fov_deg`` is None (orthographic) or in (0, 120) degrees,
    ``light_distance`` None (suns) or in (1, 5) with a ``fov_deg`` (point lights are placed
    relative to the pinhole camera), and ``environment`` a finite number >= 0."""
    if fov_deg is not None and not (_is_finite(fov_deg) and 0.0 < fov_deg < MAX_FOV_DEG):
        _bad(f"fov_deg must be in (0, {MAX_FOV_DEG:g}) degrees, got {fov_deg!r}")
    if light_distance is not None:
        if fov_deg is None:
            _bad("light_distance (point lights) needs fov_deg: point lights are placed relative to a pinhole camera")
        lo, hi = LIGHT_DISTANCE_RANGE
        if not (_is_finite(light_distance) and lo < light_distance < hi):
            _bad(f"light_distance must be in ({lo:g}, {hi:g}): outside the unit sphere of the object and in front "
                 f"of the camera at distance 5, got {light_distance!r}")
    if not (_is_finite(environment) and environment >= 0):
        _bad(f"environment must be a finite number >= 0, got {environment!r}")


@dataclass(frozen=True)
class CaptureSettings(RenderSettings):
    """One capture of one mesh (:func:`render_capture`): :class:`RenderSettings` plus what
    the scene is made of. :func:`cnnps.render`'s keyword arguments and ``cnnps render``'s
    options are exactly these fields, with these defaults (``--jitter-deg`` for
    ``jitter_deg``, ...).

    material: ``lambertian`` (white, albedo 1) or a materials-stage category (``diffuse``,
    ``specular``, ``metallic``, ``narrow``) drawn on ``superpixels`` superpixels of the
    mask with ``seed``. fov_deg: None = the orthographic camera; else a pinhole camera with
    this field of view across the image, in (0, 120). light_distance: None = suns; else
    point lights this far from the object's centre (the object fills the unit sphere), in
    (1, 5), with a fov_deg. environment: a dim uniform white world, s x light_intensity
    (0 = black).

    Example: ``CaptureSettings(lights=16, size=40, fov_deg=40.0, light_distance=2.7)``.
    """

    material: str = "lambertian"
    superpixels: int = 100
    fov_deg: float | None = None
    light_distance: float | None = None
    environment: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.material not in MATERIAL_KINDS:
            _bad(f"material must be one of {', '.join(MATERIAL_KINDS)}, got {self.material!r}")
        if not _is_count(self.superpixels) or self.superpixels < 1:
            _bad(f"superpixels must be a positive integer, got {self.superpixels!r}")
        check_camera_and_lights(self.fov_deg, self.light_distance, self.environment)


@dataclass(frozen=True, eq=False)
class Scene:
    """What one capture shows: the renderer's scene description, in the world frame of
    :mod:`cnnps.synth.blender_renderer` (x right, y up, z toward the camera; the object
    in the unit sphere at the origin, the camera at (0, 0, 5) looking down -z).

    vertices (V, 3), faces (F, 3): a smooth-shaded triangle mesh.
    material: a renderer material dict (:func:`lambertian_material`,
        :func:`principled_material`), or a callable ``mask (S, S) bool -> material dict``
        called with Blender's mask (maps drawn on the silhouette).
    lights: (m, 3) unit directions from the object's centre toward the m lights.
    fov_deg: None = the orthographic camera (x, y in [-1, 1]); F = a pinhole camera with
        F degrees across the image, in (0, 120).
    light_distance: None = one sun per image from ``lights[i]``; d = one point light at
        d * ``lights[i]`` (needs ``fov_deg``; d in (1, 5)).
    environment: s >= 0, a uniform white world in every image (s x the light intensity).

    Example: ``Scene(mesh.vertices, mesh.faces, lambertian_material(), L, fov_deg=40.0)``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: Any
    lights: np.ndarray
    fov_deg: float | None = None
    light_distance: float | None = None
    environment: float = 0.0

    def __post_init__(self):
        L = np.asarray(self.lights, dtype=np.float64)
        if L.ndim != 2 or L.shape[1] != 3 or len(L) < 1 or not np.isfinite(L).all():
            raise ConfigError(f"render scene lights must be finite (m, 3) directions, got shape {L.shape}")
        object.__setattr__(self, "lights", L)
        check_camera_and_lights(self.fov_deg, self.light_distance, self.environment)

    @property
    def pinhole(self) -> bool:
        """Whether the camera is the pinhole one (the folder then has intrinsics and depth)."""
        return self.fov_deg is not None

    @property
    def point_lights(self) -> bool:
        """Whether the lights are point lights (``light_positions.txt``) rather than suns."""
        return self.light_distance is not None

    def light_files(self) -> tuple[str, ...]:
        """The files fixed before the first image: names, directions (suns) or positions
        (point lights), intensities, and the pinhole camera's intrinsics."""
        lights = LIGHT_POSITIONS_FILE if self.point_lights else LIGHT_DIRECTIONS_FILE
        return (FILENAMES_FILE, lights, LIGHT_INTENSITIES_FILE) + ((INTRINSICS_FILE,) if self.pinhole else ())

    def geometry_files(self) -> tuple[str, ...]:
        """The ground truth Blender renders once: mask, normals and (pinhole) depth."""
        return GEOMETRY_FILES + ((DEPTH_GT_FILE,) if self.pinhole else ())

    def light_positions(self) -> np.ndarray | None:
        """(m, 3) capture-frame positions of the point lights (origin at the camera's
        optical centre: world - CAMERA_ORIGIN), or None for suns."""
        if not self.point_lights:
            return None
        from cnnps.synth.blender_renderer import CAMERA_ORIGIN

        return self.lights * float(self.light_distance) - np.asarray(CAMERA_ORIGIN)


def capture_key(inputs: dict, environment: float = 0.0, *, fov_deg: float | None = None,
                light_distance: float | None = None) -> str:
    """Content key of a capture: ``stable_hash(inputs)``, with ``environment`` (when
    non-zero), ``fov_deg`` and ``light_distance`` (when set) added to the hashed dict:
    an orthographic capture under suns in a black world is ``stable_hash(inputs)``."""
    extra: dict[str, float] = {}
    if environment:
        extra["environment"] = float(environment)
    if fov_deg is not None:
        extra["fov_deg"] = float(fov_deg)
    if light_distance is not None:
        extra["light_distance"] = float(light_distance)
    return stable_hash({**inputs, **extra} if extra else inputs)


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


def is_complete(out: Path, key: str, verify: bool = True) -> bool:
    """Whether ``out`` is a finished capture of ``key``: its ``scene.json`` holds the key
    and every image it lists exists (no Blender needed to tell) and, with ``verify``, the
    folder matches the checksums ``scene.json`` records (:func:`folder_problems`: one
    read of every file)."""
    meta = read_json(out / SCENE_FILE)
    if not meta or meta.get("key") != key:
        return False
    names = meta.get("filenames") or []
    if not (bool(names) and all((out / n).is_file() for n in names) and (out / NORMAL_GT_FILE).is_file()):
        return False
    return not verify or not folder_problems(out, meta)


def finished(out: Path, key: str) -> bool:
    """:func:`is_complete`, and a finished folder's leftover ``.pending.json`` removed (a
    kill between writing ``scene.json`` and removing the marker leaves both)."""
    if not is_complete(out, key):
        return False
    (out / PENDING_FILE).unlink(missing_ok=True)
    return True


def folder_problems(out: Path, meta: dict | None = None) -> list[tuple[Path, str]]:
    """``(file, problem)`` for every file of the finished capture ``out`` that does not
    match what its ``scene.json`` (``meta``: read when None) records: the record's own
    checksum first (a ``scene.json`` edited by hand cannot vouch for anything, so it is
    the only problem then), then each file's size and SHA-256. Empty when all match, or
    when ``scene.json`` predates checksums (nothing to check against)."""
    out = Path(out)
    if meta is None:
        meta = read_json(out / SCENE_FILE) or {}
    ok = json_checksum_ok(meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    if ok is False:
        return [(out / SCENE_FILE, "edited by hand or damaged: its content does not match its checksum")]
    problems = []
    for name, record in (meta.get("files") or {}).items():
        problem = check_file_record(out / name, record)
        if problem is not None:
            problems.append((out / name, problem))
    return problems


def decode_problem(path: Path) -> str | None:
    """Why a file of a capture folder without a checksum record cannot be kept (not
    readable by its decoder, or NaN / infinite values; the depth map may hold NaN off the
    object), or None when it reads as a whole."""
    from cnnps.io.images import read_image_raw

    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
            if path.name == DEPTH_GT_FILE:
                if not np.issubdtype(arr.dtype, np.number) or arr.ndim != 2 or np.isinf(arr).any():
                    return "not an H x W depth map (finite, or NaN off the object)"
            elif not np.issubdtype(arr.dtype, np.number) or arr.ndim != 3 or not np.isfinite(arr).all():
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


def _drop_damaged(out: Path, names: list[str], records: dict, geometry: tuple[str, ...] = GEOMETRY_FILES) -> list[str]:
    """Delete the images and ``geometry`` files (mask, normals, depth) of ``out`` that do
    not match their record (``records``: name -> {"bytes", "sha256"}) or, without one, do
    not decode as whole finite files; they are rendered again. Returns the names deleted."""
    dropped = []
    for name in list(names) + list(geometry):
        path = out / name
        if not path.is_file():
            continue
        record = records.get(name)
        problem = check_file_record(path, record) if record else decode_problem(path)
        if problem is not None:
            path.unlink()
            dropped.append(name)
    if any(n in dropped for n in geometry):  # written together: redo them all
        for n in geometry:
            (out / n).unlink(missing_ok=True)
    return dropped


def render_into(
    out: str | Path,
    scene: Scene,
    settings: RenderSettings,
    *,
    key: str,
    meta: dict | None = None,
    progress: bool = True,
    desc: str = "render",
) -> dict:
    """Render ``scene`` with ``settings`` into the capture folder ``out`` (layout: module
    docstring), resuming a partial one with the same ``key``.

    scene: what is seen (:class:`Scene`: mesh, material, lights, camera, light model,
        environment). settings: how (:class:`RenderSettings`; read here: size, samples,
        light_intensity, max_bounces, device, seed = the Cycles seed, threads).
    key: the folder's content key; it must change with anything that changes the
        pictures (:func:`capture_key`). meta: extra entries for ``scene.json``.
    Returns ``{"rendered": number of images rendered now, "skipped": bool}``.

    Steps: skip a complete folder (or take back the version a killed re-render set
    aside); :func:`_prepare_folder` (resume or start afresh); :func:`_geometry_and_material`
    (mask, normals, depth, a material drawn on the mask); :func:`_render_missing_images`;
    :func:`_scene_record` and :func:`_write_scene_json` (the completion marker). A failure
    puts the previous complete version back.

    Example: ``render_into("cap", Scene(v, f, lambertian_material(), L), RenderSettings(size=32), key="k")``.
    """
    out = Path(out)
    if finished(out, key):
        return {"rendered": 0, "skipped": True}
    if _take_back_previous(out, key):  # a killed re-render left the version this key asks for
        return {"rendered": 0, "skipped": True}
    _check_not_foreign(out)  # before Blender starts
    _forget_inherited_blender_paths()
    from cnnps.synth.blender_renderer import BlenderRenderer, require_blender

    require_blender()  # one clear line without bpy, before the folder is touched

    prev = previous_path(out)
    s = settings
    try:
        t0 = time.perf_counter()
        camera = {"fov_deg": float(scene.fov_deg)} if scene.pinhole else None
        # the renderer first: a bad device fails before the folder is touched
        with BlenderRenderer(s.size, s.samples, device=s.device, threads=s.threads, seed=s.seed,
                             max_bounces=s.max_bounces, camera=camera,
                             environment=float(scene.environment) * float(s.light_intensity)) as r:
            names = image_names(len(scene.lights))
            lights = _prepare_folder(out, key, scene, _light_record(scene, names, s.light_intensity, r))
            material = scene.material if isinstance(scene.material, dict) else lambertian_material()
            r.load_scene(scene.vertices, scene.faces, material)
            _geometry_and_material(r, out, scene)
            rendered = _render_missing_images(r, out, names, lights, scene, s.light_intensity,
                                              progress=progress, desc=desc)
            gpus = getattr(r, "gpu_devices", None)
        record = _scene_record(out, meta, key=key, names=names, scene=scene, settings=s, gpus=gpus, t0=t0,
                               rendered=rendered)
        _write_scene_json(out, record)
    except BaseException:
        _restore_previous(out, prev)  # a failed re-render leaves the last complete version
        raise
    if prev.is_dir():  # the new version is complete: the previous one goes
        shutil.rmtree(prev)
    return {"rendered": rendered, "skipped": False}


def _light_record(scene: Scene, names: list[str], intensity: float, renderer) -> Capture:
    """The files fixed before the first image, as a :class:`cnnps.io.capture.Capture`
    without images: names, directions or positions, intensities, intrinsics."""
    m = len(scene.lights)
    return Capture(filenames=names, lights=None if scene.point_lights else scene.lights,
                   light_positions=scene.light_positions(), intensities=np.full((m, 3), float(intensity)),
                   intrinsics=renderer.intrinsics() if scene.pinhole else None)


def _prepare_folder(out: Path, key: str, scene: Scene, record: Capture) -> np.ndarray:
    """Make ``out`` ready for the images still missing; the lights to render with
    (directions, or capture-frame positions of point lights).

    A folder of this ``key`` (unfinished, or finished with damaged files) whose light files
    are intact is resumed with the lights it holds (:func:`_reopen`); any other is started
    afresh with ``record`` (:func:`_start_folder`), a finished capture of another key set
    aside until the new one is complete."""
    records = _resume_records(out, key, scene)
    written = None if records is None else _written_lights(out, len(scene.lights), scene.point_lights)
    if written is None:
        _set_aside(out)
        return _start_folder(out, key, record)
    _reopen(out, key, record.filenames, records, scene.geometry_files())
    return written


def _resume_records(out: Path, key: str, scene: Scene) -> dict | None:
    """The file records ``out`` is resumed with (``{}`` when its ``scene.json`` has none or
    cannot be trusted), or None when it cannot be resumed: a finished folder only when its
    ``scene.json`` is the one we wrote for ``key`` and its light files are intact, an
    unfinished one when its ``.pending.json`` holds ``key``."""
    pending = read_json(out / PENDING_FILE) or {}
    done_meta = read_json(out / SCENE_FILE) or {}
    done_ok = (done_meta.get("key") == key
               and json_checksum_ok(done_meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS) is not False)
    records = (done_meta.get("files") or {}) if done_ok else {}
    light_files = scene.light_files()
    resume = (pending.get("key") == key or done_ok) and all((out / n).is_file() for n in light_files)
    if resume and any(check_file_record(out / n, records[n]) for n in light_files if n in records):
        resume = False
    return records if resume else None


def _written_lights(out: Path, m: int, point_lights: bool) -> np.ndarray | None:
    """The (m, 3) lights ``out`` holds (those of the interrupted run: the directions, or the
    positions of point lights), or None when they do not read as m lights."""
    try:
        if point_lights:
            L = read_light_positions(out, m, [])
        else:
            L = read_light_directions(out, unit=False)
    except InputError:
        return None
    return L if L is not None and L.shape == (m, 3) else None


def _reopen(out: Path, key: str, names: list[str], records: dict, geometry: tuple[str, ...]) -> None:
    """Resume ``out``: unfinished again, without the files a killed run half-wrote and
    without its damaged (or unverifiable and unreadable) files, which are rendered again."""
    if (out / SCENE_FILE).is_file():
        # not complete any more: a killed resume must find .pending.json, not nothing
        write_text(out / PENDING_FILE, json.dumps({"key": key}) + "\n")
        (out / SCENE_FILE).unlink()
    remove_temp_files(out)  # half-written files of the killed run
    _drop_damaged(out, names, records, geometry)  # damaged (or unverifiable and unreadable) files


def _geometry_and_material(r, out: Path, scene: Scene) -> None:
    """Blender's mask, normals and (pinhole) depth (one extra render each) when the folder
    lacks them or the material is drawn on the mask: written if missing, an empty mask
    refused (InputError), and a callable material set from the mask."""
    have_geometry = all((out / n).is_file() for n in scene.geometry_files())
    material = scene.material
    if have_geometry and not callable(material):
        return
    mask, normal = r.render_geometry()
    if not mask.any():
        raise InputError(out, "the mesh covers no pixel of the image (empty mask)")
    if callable(material):
        r.set_material(material(mask))
    if not have_geometry:
        if scene.pinhole:
            write_depth_gt(out, r.render_depth())
        write_normal_gt(out, normal)
        write_mask(out, mask)


def _render_missing_images(r, out: Path, names: list[str], lights: np.ndarray, scene: Scene, intensity: float, *,
                           progress: bool, desc: str) -> int:
    """Render every image of ``names`` not in ``out`` yet, each written atomically; how
    many. ``lights``: directions (suns) or capture-frame positions (point lights)."""
    from cnnps.synth.blender_renderer import CAMERA_ORIGIN

    todo = [i for i, n in enumerate(names) if not (out / n).is_file()]
    rendered = 0
    for i in progress_bar(todo, desc=desc, unit="light", leave=False, disable=not progress or not todo):
        if scene.point_lights:
            image = r.render_point(lights[i] + np.asarray(CAMERA_ORIGIN), intensity)
        else:
            image = r.render(lights[i], intensity)
        write_image(out / names[i], image)
        rendered += 1
    return rendered


def _renderer_text(scene: Scene) -> str:
    """``scene.json``'s one-line description of the renderer's set-up."""
    camera = f"pinhole camera ({scene.fov_deg:g} deg across)" if scene.pinhole else "orthographic camera"
    lamps = "point lamps (radius 0)" if scene.point_lights else "sun lamps (angle 0)"
    world = ("black world" if scene.environment == 0
             else "uniform white world (environment_strength x the light intensity)")
    return f"Cycles: {camera}, {lamps}, {world}, Gaussian 0.01 px filter, no denoising, no clamping"


def _scene_record(out: Path, meta: dict | None, *, key: str, names: list[str], scene: Scene, settings: RenderSettings,
                  gpus, t0: float, rendered: int) -> dict:
    """The contents of ``scene.json`` (``meta`` first), without its checksum: the settings,
    the camera and lights, the renderer, the timings and the size and SHA-256 of every
    other file."""
    from cnnps.synth.blender_renderer import CAMERA_ORIGIN, blender_version

    s = settings
    record = dict(meta or {})
    record.update(
        {
            "key": key,
            "filenames": names,
            "n_lights": len(names),
            "size": s.size,
            "samples": s.samples,
            "max_bounces": s.max_bounces,
            "light_intensity": s.light_intensity,
            "seed": s.seed,
            "device": s.device,
            "threads": s.threads,  # Cycles threads (0 = Blender's default: all cores)
            "gpu_devices": gpus,
            "blender_version": blender_version(),
            "renderer": _renderer_text(scene),
            "camera": ({"model": "pinhole", "fov_deg": float(scene.fov_deg), "position": list(CAMERA_ORIGIN)}
                       if scene.pinhole else {"model": "orthographic", "position": list(CAMERA_ORIGIN)}),
            "light_model": ({"model": "point", "distance_from_object_centre": float(scene.light_distance)}
                            if scene.point_lights else {"model": "sun"}),
            # relative to the light intensity; 0 = none. In every image; the lights files stay the lamps'
            "environment_strength": float(scene.environment),
            "mask_normal_source": "Blender camera rays through pixel centres: alpha and smooth shading normal",
            "render_seconds": round(time.perf_counter() - t0, 3),
            "images_rendered_last_run": rendered,
            "version": VERSION,
            # size and SHA-256 of every other file: what is_complete and the extract stage verify
            "files": {n: file_record(out / n) for n in scene.light_files() + scene.geometry_files() + tuple(names)},
        }
    )
    if scene.pinhole:  # the scale a point-light prediction starts from (the eval stage's rig_distance: known)
        record["median_depth"] = float(np.nanmedian(read_depth_gt(out, (s.size, s.size))))
    return record


def _write_scene_json(out: Path, scene: dict) -> None:
    """``scene.json`` with its checksum, written last: the folder is complete."""
    scene = add_json_checksum(scene, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    write_scene(out, scene)
    (out / PENDING_FILE).unlink(missing_ok=True)


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
    return path.is_dir() and any((path / n).is_file() for n in RENDER_MARKERS)


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
    if not (out / SCENE_FILE).is_file():
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
    (out / PENDING_FILE).unlink(missing_ok=True)
    return True


def _start_folder(out: Path, key: str, record: Capture) -> np.ndarray:
    """Make ``out`` hold ``.pending.json`` (the key) and the light files of ``record``
    (names, directions or positions, intensities, intrinsics: :func:`cnnps.io.capture.write_capture_files`),
    so a folder with this key always has its lights. Returns the lights to render, as read
    back from the directions or positions file (a resumed run reads the same numbers).

    Only a folder of ours (``.pending.json`` or ``scene.json``) is emptied; any other
    non-empty ``out`` is refused (InputError). A new folder is built under a temporary
    name and renamed into place; if a duplicate of this job created it meanwhile (same
    key), its lights are used. An existing empty folder (or one of ours, emptied) is
    filled in place: marker without a key first, so a kill leaves it recognisably ours.
    """
    import tempfile

    m, point_lights = len(record.filenames), record.light_positions is not None
    if is_render_folder(out):  # another key, or killed while being set up
        write_text(out / PENDING_FILE, json.dumps({"key": None}) + "\n")
        for p in out.iterdir():
            if p.name == PENDING_FILE:
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
    else:
        _check_not_foreign(out)

    if out.is_dir():  # empty (but for our key-less marker)
        write_text(out / PENDING_FILE, json.dumps({"key": None}) + "\n")
        write_capture_files(out, record)
        write_text(out / PENDING_FILE, json.dumps({"key": key}) + "\n")
        return _written_lights(out, m, point_lights)

    out.parent.mkdir(parents=True, exist_ok=True)
    build = re.compile(rf"^\.{re.escape(out.name)}\.[A-Za-z0-9_]{{8}}\.tmp$")
    for p in out.parent.glob(f".{glob.escape(out.name)}.*.tmp"):  # build folders of killed runs
        if p.is_dir() and build.match(p.name):
            shutil.rmtree(p, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        write_text(tmp / PENDING_FILE, json.dumps({"key": key}) + "\n")
        write_capture_files(tmp, record)
        publish_mode(tmp, is_dir=True)  # mkdtemp made it private (0700)
        tmp.rename(out)
    except OSError:  # out appeared meanwhile (a duplicate job): resume what it started
        pending = read_json(out / PENDING_FILE) or read_json(out / SCENE_FILE) or {}
        if pending.get("key") != key or _written_lights(out, m, point_lights) is None:
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _written_lights(out, m, point_lights)


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


def capture_material(material: str, superpixels: int, seed: int, ranges=None):
    """The renderer material of a capture: the white Lambertian dict for ``lambertian``,
    else a callable ``mask -> material dict`` drawing the category on ``superpixels``
    superpixels of the mask with ``seed`` from ``ranges`` (a
    :class:`cnnps.synth.bsdf.CategoryRanges` or :class:`~cnnps.synth.bsdf.MaterialRanges`;
    None = the category's default ranges); a ConfigError for an unknown category."""
    if material not in MATERIAL_KINDS:
        raise ConfigError(f"material must be one of {', '.join(MATERIAL_KINDS)}, got {material!r}")
    if superpixels < 1:
        raise ConfigError(f"superpixels must be >= 1, got {superpixels}")
    if material == "lambertian":
        return lambertian_material()

    def mat(mask: np.ndarray) -> dict:
        from cnnps.synth.material_maps import sample_material_maps

        maps = sample_material_maps(mask, material, superpixels, derive_seed(int(seed), "material"), ranges)
        return principled_material(extend_maps(dict(maps.params), mask))

    return mat


def changed_ranges(material: str, ranges) -> dict | None:
    """The ranges ``material`` is drawn from as plain data where they differ from its
    defaults, else None (lambertian, no ``ranges``, or the defaults): what a capture's
    key and ``scene.json`` add, so captures at the default ranges keep their keys."""
    if material == "lambertian" or ranges is None:
        return None
    cr = ranges if isinstance(ranges, CategoryRanges) else ranges.get(material)
    default = MaterialRanges().get(material)
    return None if cr == default else cr.to_dict()


def capture_lights(p: RenderSettings) -> np.ndarray:
    """(lights, 3) unit directions of a capture's lights: the hemisphere spiral with
    ``p.jitter_deg`` of jitter, seeded by ``p.seed``."""
    from cnnps.synth.lights import hemisphere_lights

    return hemisphere_lights(p.lights, p.jitter_deg, seed=derive_seed(int(p.seed), "lights"),
                             min_elevation_deg=p.min_elevation_deg)


def render_capture(mesh, out_dir: str | Path, settings: CaptureSettings | None = None, *, progress: bool = True,
                   ranges=None, **options) -> Path:
    """Render one capture folder of ``mesh`` and return its path: what :func:`cnnps.render`,
    ``cnnps render`` and the eval stage's test set (orthographic captures and rig twins) run.

    mesh: a Trimesh in the camera frame, a mesh file (normalised into the unit sphere) or
        ``procedural:<kind>[:seed]``.
    settings: a :class:`CaptureSettings` (default: its defaults); ``options``: fields of it
        to change (``lights=12, fov_deg=40.0``), validated before the mesh is loaded.
    ranges: the BSDF ranges a category material is drawn from (:func:`capture_material`;
        None = the category's defaults, as a materials-stage category's).

    The scene: the mesh, the material (:func:`capture_material`: white Lambertian, or a
    category drawn on superpixels of Blender's mask with ``derive_seed(seed, "material")``),
    the spiral's light directions (:func:`capture_lights`), the camera and the light model.
    Its key hashes the mesh, material, superpixels and :meth:`RenderSettings.picture_params`
    (plus ranges other than the category's defaults, :func:`changed_ranges`, and
    environment, fov_deg and light_distance when used: :func:`capture_key`), so a
    rerun skips a complete folder and resumes a partial one (:func:`render_into`).

    Example: ``render_capture("procedural:blob", "blob", lights=20, size=64, fov_deg=40.0)``.
    """
    p = settings if settings is not None else CaptureSettings()
    if options:
        p = dataclasses.replace(p, **options)  # validated again
    tm, info = load_mesh_arg(mesh)
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces, dtype=np.int64)
    mesh_hash = bytes_sha256(vertices.astype(np.float32).tobytes(), faces.astype(np.int64).tobytes())
    scene = Scene(vertices, faces, capture_material(p.material, p.superpixels, p.seed, ranges), capture_lights(p),
                  fov_deg=p.fov_deg, light_distance=p.light_distance, environment=p.environment)
    changed = changed_ranges(p.material, ranges)
    inputs = {"mesh": mesh_hash, "material": [p.material, p.superpixels], "params": p.picture_params(), "v": VERSION}
    key = capture_key({**inputs, "ranges": changed} if changed else inputs, p.environment, fov_deg=p.fov_deg,
                      light_distance=p.light_distance)
    out = Path(out_dir)
    meta = {"mesh_sha256": mesh_hash, "material": p.material, "superpixels": p.superpixels,
            **({"ranges": changed} if changed else {}), **info}
    render_into(out, scene, p, key=key, meta=meta, progress=progress, desc=out.name)
    return out
