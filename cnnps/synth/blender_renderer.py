"""The one module that imports ``bpy``: a small in-process Blender Cycles renderer.

The rest of the code sees :class:`BlenderRenderer` only (kubric-style)::

    r = BlenderRenderer(size=64, samples=16, device="cpu", threads=2, seed=0)  # environment=0.0
    r.load_scene(vertices, faces, material={"bsdf": "lambertian", "Color": 1.0})
    mask, normal = r.render_geometry()          # (S,S) bool, (S,S,3) float32
    img = r.render((0.3, 0.2, 0.93), 1.0)       # (S,S,3) float32 linear RGB
    r.close()

    # a pinhole camera and point lights (world = capture frame + CAMERA_ORIGIN)
    r = BlenderRenderer(size=64, samples=4, camera={"fov_deg": 40.0})
    K = r.intrinsics()                          # OpenCV 3x3
    depth = r.render_depth()                    # (S,S) float32, 5 - z; NaN off the object
    img = r.render_point((1.5, 1.0, 3.0), 1.0)  # one point light, radiant intensity 1

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

Materials: ``{"bsdf": "lambertian", "Color": albedo}`` is a Diffuse BSDF (roughness 0 =
pure Lambertian). Anything else is a Principled BSDF: every other key is the name of a
Principled input and its value a constant (scalar or RGB) or a per-pixel map (S, S) or
(S, S, 3) (image row 0 on top). Maps reach the shader as image-space textures
(Texture Coordinate ``Window`` -> Image Texture, Closest interpolation, non-colour data),
so each pixel renders with its own parameters. Scalar maps are packed three to an image.
Rays that bounce onto the object elsewhere read the map at the point's projection into
the image (an approximation only for self-occluded points).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
from typing import Any, Mapping

import numpy as np

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.infra.locked_temp import make_locked_tmpdir
from cnnps.io.images import read_exr
from cnnps.synth.render.scene import CAMERA_ORIGIN

LAMBERTIAN = "lambertian"
# the one line every command says when it must render and bpy is missing
BLENDER_MISSING = "the render stage needs Blender: pip install 'cnnps[render]' (bpy 5.0.1, Python 3.11)"
_GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")


CYCLES_SEED_RANGE = 2**31  # Cycles' seed property takes 0 .. 2^31 - 1
TMP_PREFIX = "cnnps-blender-"  # the renderer's temp folders (cnnps.infra.locked_temp)

# Blender point-light power (W) per unit of radiant intensity: a point light of power
# POINT_POWER * I makes a white Lambertian patch facing it at distance r read I / r^2
# (Cycles: radiant intensity P / (4 pi) per steradian, and the Lambertian 1 / pi).
POINT_POWER = 4.0 * math.pi**2


def _check_camera(camera: Mapping[str, Any] | None) -> dict[str, float] | None:
    """None (the orthographic camera) or ``{"fov_deg": F}`` with 0 < F < 180, checked."""
    if camera is None:
        return None
    if not isinstance(camera, Mapping) or set(camera) != {"fov_deg"}:
        raise ConfigError(f"render camera must be None or {{'fov_deg': F}}, got {camera!r}")
    fov = camera["fov_deg"]
    if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not (0.0 < fov < 180.0):
        raise ConfigError(f"render camera fov_deg must be a number in (0, 180), got {fov!r}")
    return {"fov_deg": float(fov)}


def cycles_seed(seed: int) -> int:
    """``seed`` folded into the range Cycles accepts (seeds already in range are unchanged)."""
    return int(seed) % CYCLES_SEED_RANGE


def blender_available() -> bool:
    """Whether bpy can be found (without importing it: the import takes a while and
    changes ``sys.path``)."""
    import importlib.util

    try:
        return importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        return False


def require_blender() -> None:
    """Raise :class:`ConfigError` (:data:`BLENDER_MISSING`) when bpy is not installed."""
    if not blender_available():
        raise ConfigError(BLENDER_MISSING)


def _import_bpy():
    """``import bpy``, failing as one clear line (an optional extra: ``cnnps[render]``)."""
    try:
        import bpy
    except ImportError as exc:
        raise ConfigError(f"{BLENDER_MISSING}; import bpy failed: {exc}" if blender_available() else BLENDER_MISSING) from exc
    return bpy


def blender_version() -> str:
    return _import_bpy().app.version_string


@contextlib.contextmanager
def _quiet():
    """Silence Blender's progress lines on stdout (C-level writes, so redirect fd 1)."""
    if os.environ.get("CNNPS_BLENDER_VERBOSE"):
        yield
        return
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


class BlenderRenderer:
    """One Blender scene in this process: build once, render once per light."""

    def __init__(
        self,
        size: int,
        samples: int = 16,
        device: str = "cpu",
        threads: int = 0,
        seed: int = 0,
        max_bounces: int = 8,
        persistent: bool = True,
        environment: float = 0.0,
        camera: Mapping[str, Any] | None = None,
    ):
        if size < 1:
            raise ConfigError(f"render size must be >= 1, got {size}")
        if samples < 1:
            raise ConfigError(f"render samples must be >= 1, got {samples}")
        if device not in ("cpu", "gpu"):
            raise ConfigError(f"render device must be 'cpu' or 'gpu', got {device!r}")
        if not (math.isfinite(environment) and environment >= 0):
            raise ConfigError(f"render environment must be a finite number >= 0, got {environment!r}")
        self.camera = _check_camera(camera)
        self._bpy = _import_bpy()
        self.size = int(size)
        self.samples = int(samples)
        self.device = device
        self.threads = int(threads)
        self.seed = cycles_seed(seed)
        self.max_bounces = int(max_bounces)
        self.persistent = bool(persistent)
        self.environment = float(environment)  # world radiance (0 = black world)
        self.renders = 0  # number of light renders done (for tests / benchmarks)
        self._tmpdir, self._lock_fd = make_locked_tmpdir(TMP_PREFIX)
        self._images: list[Any] = []
        self.obj = None
        self.point = None  # the point light, made by the first render_point
        try:
            self._setup()
        except BaseException:  # e.g. no GPU: leave no temp folder behind
            self.close()
            raise

    # ------------------------------------------------------------------ set-up
    def _setup(self) -> None:
        """Factory settings, then the film and sampling, the world, the camera and the sun
        (module docstring: the scene set-up)."""
        bpy = self._bpy
        with _quiet():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self.view_layer = self.scene.view_layers[0]
        self._setup_output()
        self._setup_sampling()
        self._set_device()
        self._setup_world()
        self._setup_camera()
        self._setup_sun()
        self.obj = None

    def _setup_output(self) -> None:
        """Resolution, transparent film (alpha = object coverage), float32 RGBA EXR files,
        the Standard view transform."""
        scene = self.scene
        r = scene.render
        r.engine = "CYCLES"
        r.resolution_x = r.resolution_y = self.size
        r.resolution_percentage = 100
        r.film_transparent = True  # alpha = object coverage
        r.use_persistent_data = self.persistent
        if self.threads > 0:
            r.threads_mode = "FIXED"
            r.threads = self.threads
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

    def _setup_sampling(self) -> None:
        """Unbiased path tracing: fixed samples and seed, a 0.01 px Gaussian filter, no
        denoiser, no clamping, ``max_bounces`` bounces of every kind, caustics on."""
        c = self.scene.cycles
        c.samples = self.samples
        c.use_adaptive_sampling = False
        c.use_denoising = False
        c.seed = self.seed
        c.use_animated_seed = False
        c.pixel_filter_type = "GAUSSIAN"
        c.filter_width = 0.01
        c.max_bounces = self.max_bounces
        c.diffuse_bounces = self.max_bounces
        c.glossy_bounces = self.max_bounces
        c.transmission_bounces = self.max_bounces
        c.transparent_max_bounces = self.max_bounces
        c.volume_bounces = 0
        c.sample_clamp_direct = 0.0
        c.sample_clamp_indirect = 0.0
        c.blur_glossy = 0.0
        c.caustics_reflective = True
        c.caustics_refractive = True

    def _setup_world(self) -> None:
        """A black world, or with ``environment`` E > 0 a uniform white one of radiance E."""
        world = self._bpy.data.worlds.new("black" if self.environment == 0 else "environment")
        if world.node_tree is None:  # Blender 5 makes the tree already (use_nodes is deprecated)
            world.use_nodes = True
        for bg in world.node_tree.nodes:  # the default tree emits grey light: switch it off
            if bg.type == "BACKGROUND":
                if self.environment == 0:
                    bg.inputs["Strength"].default_value = 0.0
                    bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
                else:  # a uniform white world of radiance `environment`
                    bg.inputs["Strength"].default_value = self.environment
                    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        world.color = (0.0, 0.0, 0.0)
        self.scene.world = world

    def _setup_camera(self) -> None:
        """The orthographic camera (``ortho_scale`` 2), or the pinhole one of ``camera``,
        at :data:`CAMERA_ORIGIN` looking down -z."""
        bpy = self._bpy
        cam_data = bpy.data.cameras.new("camera")
        if self.camera is None:
            cam_data.type = "ORTHO"
            cam_data.ortho_scale = 2.0
        else:  # pinhole: the field of view across the (square) image, principal point centred
            cam_data.type = "PERSP"
            cam_data.lens_unit = "FOV"
            cam_data.sensor_fit = "HORIZONTAL"
            cam_data.angle = math.radians(self.camera["fov_deg"])
            cam_data.shift_x = cam_data.shift_y = 0.0
        cam_data.clip_start = 0.1
        cam_data.clip_end = 20.0
        cam = bpy.data.objects.new("camera", cam_data)
        cam.location = CAMERA_ORIGIN
        cam.rotation_euler = (0.0, 0.0, 0.0)
        self.scene.collection.objects.link(cam)
        self.scene.camera = cam

    def _setup_sun(self) -> None:
        """The sun lamp: zero angle, turned by :meth:`render`."""
        sun_data = self._bpy.data.lights.new("sun", type="SUN")
        sun_data.angle = 0.0
        sun_data.energy = math.pi
        sun = self._bpy.data.objects.new("sun", sun_data)
        sun.rotation_mode = "QUATERNION"
        self.scene.collection.objects.link(sun)
        self.sun = sun

    def _set_device(self) -> None:
        c = self.scene.cycles
        if self.device == "cpu":
            c.device = "CPU"
            return
        prefs = self._bpy.context.preferences.addons["cycles"].preferences
        found: list[str] = []
        for backend in _GPU_BACKENDS:
            try:
                prefs.compute_device_type = backend
            except TypeError:  # backend not compiled into this build
                continue
            with _quiet():
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
                f"(tried {', '.join(_GPU_BACKENDS)}); use --device cpu"
            )
        self.gpu_devices = found
        c.device = "GPU"

    # ------------------------------------------------------------------ scene
    def load_scene(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        material: Mapping[str, Any] | None = None,
        vertex_normals: np.ndarray | None = None,
    ) -> None:
        """Replace the object: a smooth-shaded triangle mesh (camera frame) and its material.

        vertex_normals: optional (V, 3) normals to shade with (custom normals); by default
        Blender's own smooth vertex normals.
        """
        bpy = self._bpy
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"need (V,3) vertices and (F,3) triangles, got {vertices.shape}, {faces.shape}")
        if self.obj is not None:
            mesh = self.obj.data
            old = [m for m in mesh.materials if m is not None]
            bpy.data.objects.remove(self.obj)
            bpy.data.meshes.remove(mesh)
            for m in old:
                bpy.data.materials.remove(m)
        for img in self._images:
            bpy.data.images.remove(img)
        self._images = []

        mesh = bpy.data.meshes.new("object")
        mesh.vertices.add(len(vertices))
        mesh.vertices.foreach_set("co", vertices.ravel())
        mesh.loops.add(faces.size)
        mesh.loops.foreach_set("vertex_index", faces.ravel())
        mesh.polygons.add(len(faces))
        mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
        mesh.polygons.foreach_set("use_smooth", np.ones(len(faces), dtype=bool))
        mesh.update()
        if vertex_normals is not None:
            vn = np.asarray(vertex_normals, dtype=np.float64)
            vn = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
            mesh.normals_split_custom_set_from_vertices([tuple(n) for n in vn])
        obj = bpy.data.objects.new("object", mesh)
        self.scene.collection.objects.link(obj)
        obj.data.materials.append(self._material(material or {"bsdf": LAMBERTIAN, "Color": 1.0}))
        self.obj = obj

    def set_material(self, material: Mapping[str, Any]) -> None:
        """Replace the object's material (keeps the mesh)."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        bpy = self._bpy
        old = list(self.obj.data.materials)
        for img in self._images:
            bpy.data.images.remove(img)
        self._images = []
        self.obj.data.materials.clear()
        self.obj.data.materials.append(self._material(material))
        for m in old:
            bpy.data.materials.remove(m)

    def _image(self, name: str, rgb: np.ndarray):
        """An S x S float, non-colour image holding rgb (S, S, 3), row 0 on top."""
        S = self.size
        if rgb.shape[:2] != (S, S):
            raise ConfigError(f"material map {name!r} is {rgb.shape[1]}x{rgb.shape[0]}, render size is {S}x{S}")
        img = self._bpy.data.images.new(name, S, S, alpha=False, float_buffer=True, is_data=True)
        img.colorspace_settings.name = "Non-Color"
        rgba = np.ones((S, S, 4), dtype=np.float32)
        rgba[:, :, :3] = rgb[::-1]  # Blender images start at the bottom row
        img.pixels.foreach_set(rgba.ravel())
        img.pack()
        self._images.append(img)
        return img

    def _empty_material(self, name: str):
        """A new material and its node tree, emptied."""
        mat = self._bpy.data.materials.new(name)
        if mat.node_tree is None:  # Blender 5 makes the tree already (use_nodes is deprecated)
            mat.use_nodes = True
        mat.node_tree.nodes.clear()
        return mat, mat.node_tree

    def _material(self, spec: Mapping[str, Any]):
        spec = dict(spec)
        kind = spec.pop("bsdf", "principled")
        mat, nt = self._empty_material("material")
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        if kind == LAMBERTIAN:
            bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
            bsdf.inputs["Roughness"].default_value = 0.0
            spec.setdefault("Color", 1.0)
        elif kind == "principled":
            bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
            bsdf.inputs["Diffuse Roughness"].default_value = 0.0
        else:
            raise ConfigError(f"unknown material bsdf {kind!r} (use 'lambertian' or 'principled')")
        nt.links.new(bsdf.outputs[0], out.inputs["Surface"])

        coord = None
        scalar_maps: list[tuple[str, np.ndarray]] = []
        for name, value in spec.items():
            if name not in bsdf.inputs:
                raise ConfigError(f"material input {name!r} is not an input of {bsdf.bl_idname}")
            sock = bsdf.inputs[name]
            arr = np.asarray(value, dtype=np.float32)
            is_color = sock.type == "RGBA"
            if arr.ndim <= 1:  # constant
                if is_color:
                    rgb = np.broadcast_to(arr, (3,))
                    sock.default_value = (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)
                elif arr.ndim == 0:
                    sock.default_value = float(arr)
                else:
                    raise ConfigError(f"material input {name!r} takes one number, got {arr.shape}")
                continue
            if coord is None:
                coord = nt.nodes.new("ShaderNodeTexCoord")
            if arr.ndim == 3 and arr.shape[2] == 3:
                if not is_color:
                    raise ConfigError(f"material input {name!r} takes one number per pixel, got an RGB map")
                tex = self._texture(nt, coord, self._image(name, arr))
                nt.links.new(tex.outputs["Color"], sock)
            elif arr.ndim == 2:
                if is_color:
                    tex = self._texture(nt, coord, self._image(name, np.repeat(arr[:, :, None], 3, axis=2)))
                    nt.links.new(tex.outputs["Color"], sock)
                else:
                    scalar_maps.append((name, arr))
            else:
                raise ConfigError(f"material map {name!r} must be (S,S) or (S,S,3), got {arr.shape}")
        for i in range(0, len(scalar_maps), 3):  # pack three scalar maps per image
            group = scalar_maps[i : i + 3]
            rgb = np.zeros((self.size, self.size, 3), dtype=np.float32)
            for k, (_, arr) in enumerate(group):
                if arr.shape != (self.size, self.size):
                    raise ConfigError(f"material map {group[k][0]!r} is {arr.shape}, render size is {self.size}")
                rgb[:, :, k] = arr
            tex = self._texture(nt, coord, self._image("+".join(n for n, _ in group), rgb))
            sep = nt.nodes.new("ShaderNodeSeparateColor")
            sep.mode = "RGB"
            nt.links.new(tex.outputs["Color"], sep.inputs[0])
            for k, (name, _) in enumerate(group):
                nt.links.new(sep.outputs[k], bsdf.inputs[name])
        return mat

    @staticmethod
    def _texture(nt, coord, image):
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Closest"
        tex.extension = "EXTEND"
        nt.links.new(coord.outputs["Window"], tex.inputs["Vector"])
        return tex

    # ------------------------------------------------------------------ render
    def _render_file(self) -> np.ndarray:
        path = self._tmpdir / "render.exr"
        self.scene.render.filepath = str(path)
        with _quiet():
            self._bpy.ops.render.render(write_still=True)
        return read_exr(path, "RGBA")

    def render(self, light_direction, intensity: float = 1.0) -> np.ndarray:
        """(S, S, 3) float32 linear RGB under one sun from ``light_direction`` (camera frame)."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        from mathutils import Vector

        l = np.asarray(light_direction, dtype=np.float64)
        n = np.linalg.norm(l)
        if l.shape != (3,) or not n > 0:
            raise ValueError(f"light direction must be a non-zero 3-vector, got {light_direction!r}")
        if self.point is not None:  # only after a render_point: the sun alone
            self.point.hide_render = True
            self.sun.hide_render = False
        self.sun.rotation_quaternion = Vector((l / n).tolist()).to_track_quat("Z", "Y")
        self.sun.data.energy = math.pi * float(intensity)
        rgba = self._render_file()
        self.renders += 1
        return np.ascontiguousarray(rgba[:, :, :3])

    def render_point(self, position, intensity: float = 1.0) -> np.ndarray:
        """(S, S, 3) float32 linear RGB under one point light (radius 0) at ``position``
        (world frame: capture frame + :data:`CAMERA_ORIGIN`) of radiant intensity
        ``intensity``: a white Lambertian patch facing it at distance r reads intensity / r^2.
        The sun is hidden meanwhile (and this light during :meth:`render`)."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        p = np.asarray(position, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"light position must be a finite 3-vector, got {position!r}")
        if not (math.isfinite(intensity) and intensity >= 0):
            raise ValueError(f"light intensity must be a finite number >= 0, got {intensity!r}")
        if self.point is None:
            data = self._bpy.data.lights.new("point", type="POINT")
            data.shadow_soft_size = 0.0  # a true point: hard shadows, exact 1 / r^2
            data.use_soft_falloff = False
            self.point = self._bpy.data.objects.new("point", data)
            self.scene.collection.objects.link(self.point)
        self.sun.hide_render = True
        self.point.hide_render = False
        self.point.location = p.tolist()
        self.point.data.energy = POINT_POWER * float(intensity)
        rgba = self._render_file()
        self.renders += 1
        return np.ascontiguousarray(rgba[:, :, :3])

    def intrinsics(self) -> np.ndarray:
        """The OpenCV 3x3 K of the pinhole camera's images: fx = fy = (S/2) / tan(F/2),
        cx = cy = (S - 1)/2 (pixel (0, 0)'s centre is the origin, as in cnnps.ps.camera).
        ValueError for the orthographic camera (it has no K)."""
        if self.camera is None:
            raise ValueError("the orthographic camera has no intrinsic matrix")
        S = self.size
        f = (S / 2.0) / math.tan(math.radians(self.camera["fov_deg"]) / 2.0)
        c = (S - 1) / 2.0
        return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])

    @property
    def camera_origin(self) -> np.ndarray:
        """The optical centre in the world frame, (0, 0, 5): capture = world - camera_origin."""
        return np.array(CAMERA_ORIGIN)

    def _emission_material(self, name: str, link) -> Any:
        """A material emitting (strength 1) the colour ``link(nt, geometry_node)`` returns."""
        mat, nt = self._empty_material(name)
        geo = nt.nodes.new("ShaderNodeNewGeometry")
        emit = nt.nodes.new("ShaderNodeEmission")
        emit.inputs["Strength"].default_value = 1.0
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(link(nt, geo), emit.inputs["Color"])
        nt.links.new(emit.outputs[0], out.inputs["Surface"])
        return mat

    def _normal_material(self):
        """Emission of (N + 1) / 2 with N Blender's smooth shading normal (world = camera frame)."""

        def link(nt, geo):
            scale = nt.nodes.new("ShaderNodeVectorMath")
            scale.operation = "MULTIPLY_ADD"
            scale.inputs[1].default_value = (0.5, 0.5, 0.5)
            scale.inputs[2].default_value = (0.5, 0.5, 0.5)
            nt.links.new(geo.outputs["Normal"], scale.inputs[0])
            return scale.outputs["Vector"]

        return self._emission_material("normals", link)

    def _depth_material(self):
        """Emission of CAMERA_ORIGIN - P (P the hit point): its blue is the depth 5 - z."""

        def link(nt, geo):
            sub = nt.nodes.new("ShaderNodeVectorMath")
            sub.operation = "SUBTRACT"
            sub.inputs[0].default_value = CAMERA_ORIGIN
            nt.links.new(geo.outputs["Position"], sub.inputs[1])
            return sub.outputs["Vector"]

        return self._emission_material("depth", link)

    def _render_override(self, material) -> np.ndarray:
        """One 1-sample RGBA render with every surface shaded by ``material``, lights hidden."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        c = self.scene.cycles
        lights = [x for x in (self.sun, self.point) if x is not None]
        saved = c.samples, [x.hide_render for x in lights]
        c.samples = 1
        for x in lights:
            x.hide_render = True
        self.view_layer.material_override = material
        try:
            return self._render_file()
        finally:
            c.samples = saved[0]
            for x, hidden in zip(lights, saved[1]):
                x.hide_render = hidden
            self.view_layer.material_override = None
            self._bpy.data.materials.remove(material)

    def render_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Mask (S, S) bool and unit normals (S, S, 3) float32 (camera frame, 0 outside)
        at the pixel centres, from Blender's own camera-ray hits: alpha, and an emission
        override showing the smooth shading normal (the normal the BSDFs are lit with)."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        rgba = self._render_override(self._normal_material())
        mask = rgba[:, :, 3] > 0.5
        normal = rgba[:, :, :3] * 2.0 - 1.0
        norm = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 1e-6)
        normal[~mask] = 0.0
        return mask, normal.astype(np.float32)

    def render_depth(self) -> np.ndarray:
        """(S, S) float32 depth along the optical axis (5 - z of the point each pixel's
        centre ray hits; the same for both cameras), NaN outside the mask: an emission
        override showing CAMERA_ORIGIN - P, 1 sample through the pixel centres."""
        if self.obj is None:
            raise RuntimeError("load_scene first")
        rgba = self._render_override(self._depth_material())
        depth = rgba[:, :, 2].astype(np.float32)
        depth[~(rgba[:, :, 3] > 0.5)] = np.nan
        return depth

    def close(self) -> None:
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if self.obj is not None:
            with _quiet():
                self._bpy.ops.wm.read_factory_settings(use_empty=True)
            self.obj = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
