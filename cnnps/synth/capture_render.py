"""The one Cycles capture renderer: a scene description and render settings in, a capture
folder out, resumable. What the render stage, ``cnnps render`` / :func:`cnnps.render`,
the eval stage's test set (and its rig twins) and the calibration sets render with.

The interface (kubric-style: scene + settings -> renderer -> folder)::

    scene = Scene(vertices, faces, lambertian_material(), lights=L)          # L (m, 3) unit
    render_into("cap", scene, RenderSettings(size=64, samples=8), key="k")   # -> {"rendered": m, ...}
    # a rig: pinhole camera of 40 degrees, point lights 3 object radii from its centre
    render_into("rig", Scene(vertices, faces, material, L, fov_deg=40.0, light_distance=3.0), settings, key="k2")

This module drives Blender (:mod:`cnnps.synth.blender`) through one folder;
what it renders from and into are the modules of :mod:`cnnps.synth.render`, none of
which needs Blender:

- :mod:`~cnnps.synth.render.settings`: :class:`RenderSettings` (how: the names and
  defaults every front end shares) and :class:`CaptureSettings` (plus material, camera
  and lights);
- :mod:`~cnnps.synth.render.scene`: :class:`Scene` (what is seen: mesh, material, light
  directions, camera, light model, ambient world) and the lights a capture draws;
- :mod:`~cnnps.synth.render.keys`: the content keys that name a folder;
- :mod:`~cnnps.synth.render.materials`, :mod:`~cnnps.synth.render.mesh_input`: renderer
  materials and the mesh a user names;
- :mod:`~cnnps.synth.render.resume`: the resume and checksum state machine (light files
  first, each image atomically, ``scene.json`` last; a killed or damaged folder re-renders
  only what is missing or damaged);
- :mod:`~cnnps.synth.render.rendered_folder`: reading a finished folder (complete? do its
  files match their checksums?), what the extract stage imports.

:func:`render_into` writes the folder through :mod:`cnnps.io.capture`;
:func:`render_capture` does it all for one mesh (a Trimesh, a mesh file or
``procedural:<kind>[:seed]``) and a :class:`CaptureSettings`, with its own content key.

The folder (docs/ARCHITECTURE.md): ``000.exr ...`` (float32 linear RGB, names zero-padded
to the light count), ``filenames.txt``, ``light_intensities.txt``, ``mask.png``,
``normal_gt.npy`` and ``scene.json``, and

- orthographic camera (``fov_deg`` None: it covers x, y in [-1, 1]): nothing more; suns:
  ``light_directions.txt`` (unit, camera frame);
- pinhole camera (``fov_deg`` F, at :data:`cnnps.synth.render.scene.CAMERA_ORIGIN`
  (0, 0, 5) looking down -z, F across the square image): ``intrinsics.txt`` (K, OpenCV)
  and ``depth_gt.npy`` (H x W depth along the optical axis, NaN outside the mask;
  ``scene.json`` records its median as ``median_depth``); with suns
  ``light_directions.txt``, with point lights (``light_distance`` d: at d times each
  direction from the object's centre, radiant intensity ``light_intensity``: a white
  Lambertian patch facing one at distance r reads I / r^2) ``light_positions.txt``
  (capture frame: origin at the camera's optical centre, i.e. world - (0, 0, 5)).

Mask and ground truth come from Blender itself (one extra 1-sample render, two with the
pinhole camera): the mask is the alpha of the camera rays through the pixel centres,
``normal_gt`` is the smooth shading normal at those hits, i.e. exactly the normal the
BSDFs were lit with (agreeing with the shading by construction; for meshes of the meshes
stage it matches the analytic/rasterised normal up to Blender's vertex-normal
interpolation), and ``depth_gt`` the depth of those hits.

Lighting: one lamp per image (direction or position and intensity as written) and,
optionally, a dim uniform white environment (``environment`` s: a white Lambertian patch
reads s x ``light_intensity`` from it, the same in every image of the capture, recorded
in ``scene.json`` as ``environment_strength``; 0 = black world, the paper's set-up). The
environment is the ambient light a real capture has in its attached shadows; it is not in
the lights files, so every image then holds the lamp's term *plus* the ambient term.

Blender (bpy) is needed only to render: :mod:`cnnps.synth.blender`, the one
module that imports it, is imported when a folder actually has images to render, and
without bpy that is one clear :class:`cnnps.infra.errors.ConfigError`
(:func:`cnnps.synth.blender.require_blender`). A complete folder is recognised
without Blender.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.infra.hashing import file_record
from cnnps.infra.progress import progress_bar
from cnnps.io.capture import Capture, write_depth_gt, write_image, write_mask, write_normal_gt
from cnnps.io.capture.files import read_depth_gt
from cnnps.synth.render.keys import VERSION, changed_ranges, mesh_capture_key, mesh_sha256
from cnnps.synth.render.materials import capture_material, lambertian_material
from cnnps.synth.render.mesh_input import load_mesh_arg
from cnnps.synth.render.resume import (
    check_not_foreign,
    finished,
    prepare_folder,
    previous_path,
    restore_previous,
    take_back_previous,
    write_scene_json,
)
from cnnps.synth.render.scene import Scene, capture_lights, image_names
from cnnps.synth.render.settings import CaptureSettings, RenderSettings


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
        pictures (:func:`cnnps.synth.render.keys.capture_key`). meta: extra entries for
        ``scene.json``.
    Returns ``{"rendered": number of images rendered now, "skipped": bool}``.

    Steps (the states: :mod:`cnnps.synth.render.resume`): skip a complete folder (or take
    back the version a killed re-render set aside); ``prepare_folder`` (resume or start
    afresh); :func:`_geometry_and_material` (mask, normals, depth, a material drawn on the
    mask); :func:`_render_missing_images`; :func:`_scene_record` and ``write_scene_json``
    (the completion marker). A failure puts the previous complete version back.

    Example: ``render_into("cap", Scene(v, f, lambertian_material(), L), RenderSettings(size=32), key="k")``.
    """
    out = Path(out)
    if finished(out, key):
        return {"rendered": 0, "skipped": True}
    if take_back_previous(out, key):  # a killed re-render left the version this key asks for
        return {"rendered": 0, "skipped": True}
    check_not_foreign(out)  # before Blender starts
    _forget_inherited_blender_paths()
    from cnnps.synth.blender import BlenderRenderer, require_blender

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
            lights = prepare_folder(out, key, scene, _light_record(scene, names, s.light_intensity, r))
            material = scene.material if isinstance(scene.material, dict) else lambertian_material()
            r.load_scene(scene.vertices, scene.faces, material)
            _geometry_and_material(r, out, scene)
            rendered = _render_missing_images(r, out, names, lights, scene, s.light_intensity,
                                              progress=progress, desc=desc)
            gpus = getattr(r, "gpu_devices", None)
        record = _scene_record(out, meta, key=key, names=names, scene=scene, settings=s, gpus=gpus, t0=t0,
                               rendered=rendered)
        write_scene_json(out, record)
    except BaseException:
        restore_previous(out, prev)  # a failed re-render leaves the last complete version
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
    from cnnps.synth.render.scene import CAMERA_ORIGIN

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
    from cnnps.synth.blender import blender_version
    from cnnps.synth.render.scene import CAMERA_ORIGIN

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


def render_capture(mesh, out_dir: str | Path, settings: CaptureSettings | None = None, *, progress: bool = True,
                   ranges=None, **options) -> Path:
    """Render one capture folder of ``mesh`` and return its path: what :func:`cnnps.render`,
    ``cnnps render`` and the eval stage's test set (orthographic captures and rig twins) run.

    mesh: a Trimesh in the camera frame, a mesh file (normalised into the unit sphere) or
        ``procedural:<kind>[:seed]``.
    settings: a :class:`CaptureSettings` (default: its defaults); ``options``: fields of it
        to change (``lights=12, fov_deg=40.0``), validated before the mesh is loaded.
    ranges: the BSDF ranges a category material is drawn from (None = the category's
        defaults, as a materials-stage category's).

    The scene: the mesh, the material (:func:`cnnps.synth.render.materials.capture_material`:
    white Lambertian, or a category drawn on superpixels of Blender's mask with
    ``derive_seed(seed, "material")``), the spiral's light directions
    (:func:`cnnps.synth.render.scene.capture_lights`), the camera and the light model. Its
    key (:func:`cnnps.synth.render.keys.mesh_capture_key`) hashes the mesh, material,
    superpixels and :meth:`RenderSettings.picture_params` (plus ranges other than the
    category's defaults, and environment, fov_deg and light_distance when used), so a
    rerun skips a complete folder and resumes a partial one (:func:`render_into`).

    Example: ``render_capture("procedural:blob", "blob", lights=20, size=64, fov_deg=40.0)``.
    """
    p = settings if settings is not None else CaptureSettings()
    if options:
        p = dataclasses.replace(p, **options)  # validated again
    tm, info = load_mesh_arg(mesh)
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces, dtype=np.int64)
    mesh_hash = mesh_sha256(vertices, faces)
    scene = Scene(vertices, faces, capture_material(p.material, p.superpixels, p.seed, ranges), capture_lights(p),
                  fov_deg=p.fov_deg, light_distance=p.light_distance, environment=p.environment)
    changed = changed_ranges(p.material, ranges)
    key = mesh_capture_key(mesh_hash, p, changed)
    out = Path(out_dir)
    meta = {"mesh_sha256": mesh_hash, "material": p.material, "superpixels": p.superpixels,
            **({"ranges": changed} if changed else {}), **info}
    render_into(out, scene, p, key=key, meta=meta, progress=progress, desc=out.name)
    return out
