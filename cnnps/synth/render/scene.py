"""What one capture shows: :class:`Scene` (mesh, material, light directions, camera,
light model, ambient world), the files it fixes before the first image and the ones
Blender renders once, the image names, and the lights a capture's settings draw.

Example::

    scene = Scene(vertices, faces, lambertian_material(), capture_lights(RenderSettings(lights=20)))
    scene.light_files()   # ('filenames.txt', 'light_directions.txt', 'light_intensities.txt')
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import derive_seed
from cnnps.io.capture import (
    DEPTH_GT_FILE,
    FILENAMES_FILE,
    INTRINSICS_FILE,
    LIGHT_DIRECTIONS_FILE,
    LIGHT_INTENSITIES_FILE,
    LIGHT_POSITIONS_FILE,
    MASK_FILE,
    NORMAL_GT_FILE,
)
from cnnps.synth.render.settings import RenderSettings, check_camera_and_lights

# The camera's optical centre in the world frame (both cameras, :mod:`cnnps.synth.blender`):
# world point (x, y, z) is capture-frame point (x, y, z) - CAMERA_ORIGIN, and its depth along the
# optical axis is 5 - z.
CAMERA_ORIGIN = (0.0, 0.0, 5.0)
LIGHT_FILES = (FILENAMES_FILE, LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE)  # suns (Scene.light_files)
GEOMETRY_FILES = (MASK_FILE, NORMAL_GT_FILE)  # orthographic camera (Scene.geometry_files)


@dataclass(frozen=True, eq=False)
class Scene:
    """What one capture shows: the renderer's scene description, in the world frame of
    :mod:`cnnps.synth.blender` (x right, y up, z toward the camera; the object
    in the unit sphere at the origin, the camera at (0, 0, 5) looking down -z).

    vertices (V, 3), faces (F, 3): a smooth-shaded triangle mesh.
    material: a renderer material dict
        (:func:`cnnps.synth.render.materials.lambertian_material`,
        :func:`~cnnps.synth.render.materials.principled_material`), or a callable
        ``mask (S, S) bool -> material dict`` called with Blender's mask (maps drawn on
        the silhouette).
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

        return self.lights * float(self.light_distance) - np.asarray(CAMERA_ORIGIN)


def image_names(n: int) -> list[str]:
    """``000.exr`` ... for ``n`` lights (zero-padded to at least three digits)."""
    width = max(3, len(str(n - 1)))
    return [f"{i:0{width}d}.exr" for i in range(n)]


def capture_lights(p: RenderSettings) -> np.ndarray:
    """(lights, 3) unit directions of a capture's lights: the hemisphere spiral with
    ``p.jitter_deg`` of jitter, seeded by ``p.seed``."""
    from cnnps.synth.lights import hemisphere_lights

    return hemisphere_lights(p.lights, p.jitter_deg, seed=derive_seed(int(p.seed), "lights"),
                             min_elevation_deg=p.min_elevation_deg)
