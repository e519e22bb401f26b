"""A new Cycles scene's set-up, one function a concern: the film and output files, the
sampling, the compute device, the world, the camera and the lamps.

Scene set-up:

- factory settings, empty scene; Cycles; black world (Background strength 0), or with
  ``environment`` E > 0 a uniform white world of radiance E (Background colour white,
  strength E: an unoccluded Lambertian surface of albedo a reads a·E from it, measured
  exactly at 1 spp, since a constant world and cosine sampling give every sample a·E);
- orthographic camera at (0, 0, 5) looking down -Z, ``ortho_scale`` 2: the image covers
  x, y in [-1, 1]; world x, y, z = image right, up, toward the camera; row 0 on top;
- or, with ``camera={"fov_deg": F}``, a pinhole camera at the same place and orientation
  (type PERSP, ``lens_unit`` FOV, ``sensor_fit`` HORIZONTAL, ``angle`` F, no shift): the
  field of view F spans the (square) image's width, and the OpenCV intrinsics are
  fx = fy = (S/2) / tan(F/2), cx = cy = (S - 1)/2 with (0, 0) the centre of the top-left
  pixel (:meth:`BlenderRenderer.intrinsics`; measured: depths of a tilted plane match rays
  K^-1 (u, v, 1) to 7e-8 relative, while K with cx, cy half a pixel off is 7e-3 out).
  Its capture frame (cnnps.ps.camera) is the world frame moved by :data:`CAMERA_ORIGIN`:
  world (x, y, z) is capture (x, y, z - 5);
- one sun lamp of zero angular size, strength ``pi * intensity`` (a white Lambertian patch
  facing it reads ``intensity``), turned with ``Vector(l).to_track_quat('Z', 'Y')``;
- point lights (:meth:`BlenderRenderer.render_point`, made on first use): one POINT lamp
  of radius (``shadow_soft_size``) 0, no soft falloff, power ``4 pi^2 * intensity`` W
  (:data:`POINT_POWER`): Cycles gives a point lamp of P W the radiant intensity P/(4 pi),
  and a white Lambertian patch facing it at distance r reads intensity / r^2 (measured on
  a tilted Lambertian plane: per-pixel ratio to max(0, n.l) / r^2 is 1.0000 in median
  and mean). The sun is hidden during point renders and the point lamp during sun
  renders, so a renderer that never calls render_point renders with its sun alone;
- Gaussian pixel filter of 0.01 px: every camera sample goes through the pixel centre, so
  pixel (r, c) sees the surface at x = -1 + (c + .5) 2/S, y = 1 - (r + .5) 2/S;
- no denoiser, no adaptive sampling, no sample clamping, no glossy filter, caustics on:
  unbiased path tracing with ``max_bounces`` bounces of every kind (global illumination:
  interreflections and cast shadows);
- Standard view transform; each picture is written as a float32 linear RGBA OpenEXR
  (one layer, alpha = object coverage) and read back with :func:`cnnps.io.images.read_exr`;
- mask and ground-truth normals: one more 1-sample render of the same camera rays with
  an emission override showing the smooth shading normal (:meth:`BlenderRenderer.render_geometry`),
  and its alpha; depth the same way (:meth:`BlenderRenderer.render_depth`), emitting
  CAMERA_ORIGIN - P for the hit point P, whose blue is the depth along the optical axis
  5 - z for either camera (not the distance along the ray); Cycles' own Z pass is not used
  (a single-layer EXR holds RGBA only);
- persistent data: the scene is synced once, each light only moves a lamp, so a
  re-render costs less than the first render (docs/performance.md#other-commands);
- the seed is folded into Cycles' range 0 .. 2^31 - 1 (:func:`cycles_seed`);
- Blender writes each picture into a private temp folder, locked (flock) while the
  renderer lives, so a later renderer removes the folders of SIGKILLed ones.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.synth.blender.session import quiet
from cnnps.synth.render.scene import CAMERA_ORIGIN

GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")  # tried in this order

# Blender point-light power (W) per unit of radiant intensity: a point light of power
# POINT_POWER * I makes a white Lambertian patch facing it at distance r read I / r^2
# (Cycles: radiant intensity P / (4 pi) per steradian, and the Lambertian 1 / pi).
POINT_POWER = 4.0 * math.pi**2


def check_camera(camera: Mapping[str, Any] | None) -> dict[str, float] | None:
    """None (the orthographic camera) or ``{"fov_deg": F}`` with 0 < F < 180, checked."""
    if camera is None:
        return None
    if not isinstance(camera, Mapping) or set(camera) != {"fov_deg"}:
        raise ConfigError(f"render camera must be None or {{'fov_deg': F}}, got {camera!r}")
    fov = camera["fov_deg"]
    if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not (0.0 < fov < 180.0):
        raise ConfigError(f"render camera fov_deg must be a number in (0, 180), got {fov!r}")
    return {"fov_deg": float(fov)}


def setup_output(scene, size: int, persistent: bool, threads: int) -> None:
    """Resolution, transparent film (alpha = object coverage), float32 RGBA EXR files,
    the Standard view transform."""
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = size
    r.resolution_percentage = 100
    r.film_transparent = True  # alpha = object coverage
    r.use_persistent_data = persistent
    if threads > 0:
        r.threads_mode = "FIXED"
        r.threads = threads
    r.image_settings.media_type = "IMAGE"
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_mode = "RGBA"
    r.image_settings.color_depth = "32"
    r.image_settings.exr_codec = "NONE"
    r.use_file_extension = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0

def setup_sampling(scene, samples: int, seed: int, max_bounces: int) -> None:
    """Unbiased path tracing: fixed samples and seed, a 0.01 px Gaussian filter, no
    denoiser, no clamping, ``max_bounces`` bounces of every kind, caustics on."""
    c = scene.cycles
    c.samples = samples
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = seed
    c.use_animated_seed = False
    c.pixel_filter_type = "GAUSSIAN"
    c.filter_width = 0.01
    c.max_bounces = max_bounces
    c.diffuse_bounces = max_bounces
    c.glossy_bounces = max_bounces
    c.transmission_bounces = max_bounces
    c.transparent_max_bounces = max_bounces
    c.volume_bounces = 0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.blur_glossy = 0.0
    c.caustics_reflective = True
    c.caustics_refractive = True

def setup_world(bpy, scene, environment: float) -> None:
    """A black world, or with ``environment`` E > 0 a uniform white one of radiance E."""
    world = bpy.data.worlds.new("black" if environment == 0 else "environment")
    if world.node_tree is None:  # Blender 5 makes the tree already (use_nodes is deprecated)
        world.use_nodes = True
    for bg in world.node_tree.nodes:  # the default tree emits grey light: switch it off
        if bg.type == "BACKGROUND":
            if environment == 0:
                bg.inputs["Strength"].default_value = 0.0
                bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            else:  # a uniform white world of radiance `environment`
                bg.inputs["Strength"].default_value = environment
                bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    world.color = (0.0, 0.0, 0.0)
    scene.world = world

def setup_camera(bpy, scene, camera: Mapping[str, Any] | None) -> None:
    """The orthographic camera (``ortho_scale`` 2), or the pinhole one of ``camera``,
    at :data:`CAMERA_ORIGIN` looking down -z."""
    cam_data = bpy.data.cameras.new("camera")
    if camera is None:
        cam_data.type = "ORTHO"
        cam_data.ortho_scale = 2.0
    else:  # pinhole: the field of view across the (square) image, principal point centred
        cam_data.type = "PERSP"
        cam_data.lens_unit = "FOV"
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.angle = math.radians(camera["fov_deg"])
        cam_data.shift_x = cam_data.shift_y = 0.0
    cam_data.clip_start = 0.1
    cam_data.clip_end = 20.0
    cam = bpy.data.objects.new("camera", cam_data)
    cam.location = CAMERA_ORIGIN
    cam.rotation_euler = (0.0, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam

def add_sun(bpy, scene):
    """The sun lamp (returned): zero angle, strength pi (intensity 1), turned by
    :meth:`cnnps.synth.blender.renderer.BlenderRenderer.render`."""
    sun_data = bpy.data.lights.new("sun", type="SUN")
    sun_data.angle = 0.0
    sun_data.energy = math.pi
    sun = bpy.data.objects.new("sun", sun_data)
    sun.rotation_mode = "QUATERNION"
    scene.collection.objects.link(sun)
    return sun

def set_device(bpy, scene, device: str) -> list[str]:
    """Cycles on the CPU, or on the first GPU backend of :data:`GPU_BACKENDS` with a device
    (CnnpsError when none has one). The GPUs used, as "name (backend)" (none on the CPU)."""
    c = scene.cycles
    if device == "cpu":
        c.device = "CPU"
        return []
    prefs = bpy.context.preferences.addons["cycles"].preferences
    found: list[str] = []
    for backend in GPU_BACKENDS:
        try:
            prefs.compute_device_type = backend
        except TypeError:  # backend not compiled into this build
            continue
        with quiet():
            prefs.refresh_devices()
        gpus = [d for d in prefs.devices if d.type == backend]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == backend
            found = [f"{d.name} ({backend})" for d in gpus]
            break
    if not found:
        raise CnnpsError(
            "render device 'gpu' asked for, but Blender Cycles finds no GPU "
            f"(tried {', '.join(GPU_BACKENDS)}); use --device cpu"
        )
    c.device = "GPU"
    return found



def add_point_light(bpy, scene):
    """A point lamp (returned) of radius 0 and no soft falloff: hard shadows, exact 1 / r^2;
    its power is :data:`POINT_POWER` times the radiant intensity."""
    data = bpy.data.lights.new("point", type="POINT")
    data.shadow_soft_size = 0.0  # a true point: hard shadows, exact 1 / r^2
    data.use_soft_falloff = False
    point = bpy.data.objects.new("point", data)
    scene.collection.objects.link(point)
    return point
