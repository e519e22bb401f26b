"""The Blender renderer: one Cycles scene in this process, built once and rendered once
per light (:class:`BlenderRenderer`), the one class the rest of the code sees
(kubric-style)::

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

Each picture is written by Blender into a private temp folder, locked (flock) while the
renderer lives, so a later renderer removes the folders of SIGKILLed ones; persistent
data keeps the scene synced once, so a re-render moves a lamp only
(docs/performance.md#other-commands).
"""

from __future__ import annotations

import math
import os
import shutil
from typing import Any, Mapping

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.infra.locked_temp import make_locked_tmpdir
from cnnps.io.images import read_exr
from cnnps.synth.blender.scene_setup import (
    POINT_POWER,
    add_point_light,
    add_sun,
    check_camera,
    set_device,
    setup_camera,
    setup_output,
    setup_sampling,
    setup_world,
)
from cnnps.synth.blender.session import cycles_seed, import_bpy, quiet
from cnnps.synth.blender.shaders import LAMBERTIAN, depth_material, normal_material, surface_material
from cnnps.synth.render.scene import CAMERA_ORIGIN

TMP_PREFIX = "cnnps-blender-"  # the renderer's temp folders (cnnps.infra.locked_temp)


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
        self.camera = check_camera(camera)
        self._bpy = import_bpy()
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
        (:mod:`cnnps.synth.blender.scene_setup`)."""
        bpy = self._bpy
        with quiet():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self.view_layer = self.scene.view_layers[0]
        setup_output(self.scene, self.size, self.persistent, self.threads)
        setup_sampling(self.scene, self.samples, self.seed, self.max_bounces)
        found = set_device(bpy, self.scene, self.device)
        if found:
            self.gpu_devices = found
        setup_world(bpy, self.scene, self.environment)
        setup_camera(bpy, self.scene, self.camera)
        self.sun = add_sun(bpy, self.scene)
        self.obj = None

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
        obj.data.materials.append(surface_material(bpy, material or {"bsdf": LAMBERTIAN, "Color": 1.0}, self.size,
                                                    self._images))
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
        self.obj.data.materials.append(surface_material(bpy, material, self.size, self._images))
        for m in old:
            bpy.data.materials.remove(m)

    # ------------------------------------------------------------------ render
    def _render_file(self) -> np.ndarray:
        path = self._tmpdir / "render.exr"
        self.scene.render.filepath = str(path)
        with quiet():
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
            self.point = add_point_light(self._bpy, self.scene)
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
        rgba = self._render_override(normal_material(self._bpy))
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
        rgba = self._render_override(depth_material(self._bpy))
        depth = rgba[:, :, 2].astype(np.float32)
        depth[~(rgba[:, :, 3] > 0.5)] = np.nan
        return depth

    def close(self) -> None:
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if self.obj is not None:
            with quiet():
                self._bpy.ops.wm.read_factory_settings(use_empty=True)
            self.obj = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
