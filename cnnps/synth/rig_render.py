"""Captures of real rigs rendered with Blender Cycles: a pinhole camera and, optionally,
point lights near the object (what ``cnnps render --fov F [--light-distance D]`` writes).

The object (a mesh in the unit sphere at the origin) is seen by the renderer's pinhole
camera at :data:`cnnps.synth.blender_renderer.CAMERA_ORIGIN` (0, 0, 5) looking down -z,
with a field of view ``fov_deg`` across the square image. The lights take the directions
of the orthographic captures (:func:`cnnps.synth.lights.hemisphere_lights`, same seed
rule) and are either suns from those directions or, with ``light_distance`` d, point
lights at d times those directions from the object's centre (radiant intensity
``light_intensity``: a white Lambertian patch facing one at distance r reads I / r^2).
d must be below 5, so that every light is in front of the camera.

The folder (written at once: a temporary folder renamed at the end; an existing folder
is refused, nothing is resumed):

- ``000.exr`` ... float32 linear RGB, ``filenames.txt``, ``light_intensities.txt``;
- ``light_directions.txt`` (suns) or ``light_positions.txt`` (point lights, capture
  frame: origin at the camera's optical centre, i.e. world - (0, 0, 5));
- ``intrinsics.txt``: the camera's K (OpenCV convention);
- ``mask.png``, ``normal_gt.npy`` (capture frame), ``depth_gt.npy`` (H x W float32
  depth along the optical axis, NaN outside the mask);
- ``scene.json``: the settings.

``cnnps predict`` reads it like any capture: the intrinsics turn each pixel's lights
into its view frame, the positions start the rounds of near-light prediction, and
``normal_gt.npy`` scores it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cnnps.infra.errors import ConfigError, InputError


def light_positions(directions: np.ndarray, distance: float) -> np.ndarray:
    """(m, 3) capture-frame positions of point lights at ``distance`` along ``directions``
    (m, 3) unit from the object's centre (world origin)."""
    from cnnps.synth.blender_renderer import CAMERA_ORIGIN

    return np.asarray(directions, dtype=np.float64) * float(distance) - np.asarray(CAMERA_ORIGIN)


def render_rig_capture(
    mesh,
    out_dir: str | Path,
    *,
    fov_deg: float,
    light_distance: float | None = None,
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
) -> Path:
    """Render ``mesh`` through a pinhole camera into ``out_dir`` (layout: module docstring)
    and return its path. Arguments as :func:`cnnps.synth.capture_render.render_capture`,
    plus ``fov_deg`` (the camera's field of view, in (0, 120)) and ``light_distance``
    (None: suns; else point lights that far from the object's centre, in (1, 5))."""
    from cnnps.infra.progress import progress_bar
    from cnnps.io.capture import Capture, write_capture
    from cnnps.synth.capture_render import (
        RenderSettings,
        capture_lights,
        capture_material,
        image_names,
        lambertian_material,
        load_mesh_arg,
    )

    if not (np.isfinite(fov_deg) and 0 < fov_deg < 120):
        raise ConfigError(f"fov must be in (0, 120) degrees, got {fov_deg!r}")
    if light_distance is not None and not (np.isfinite(light_distance) and 1.0 < light_distance < 5.0):
        raise ConfigError(f"light distance must be in (1, 5): outside the unit sphere of the object and in front "
                          f"of the camera at distance 5, got {light_distance!r}")
    mat = capture_material(material, superpixels, seed)
    p = RenderSettings(size=size, samples=samples, lights=lights, jitter_deg=jitter_deg,
                       light_intensity=light_intensity, max_bounces=max_bounces, device=device, seed=seed,
                       threads=threads)  # validation
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "exists and is not an empty folder (rig captures are not resumed): choose a new one")
    from cnnps.synth.blender_renderer import (
        CAMERA_ORIGIN,
        BlenderRenderer,
        require_blender,
    )

    require_blender()
    tm, info = load_mesh_arg(mesh)
    L = capture_lights(p)
    positions = None if light_distance is None else light_positions(L, light_distance)
    names = image_names(len(L))
    t0 = time.perf_counter()
    with BlenderRenderer(p.size, p.samples, device=p.device, threads=p.threads, seed=seed,
                         max_bounces=p.max_bounces, camera={"fov_deg": float(fov_deg)}) as r:
        r.load_scene(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64),
                     lambertian_material())
        mask, normal = r.render_geometry()
        if not mask.any():
            raise InputError(out, "the mesh covers no pixel of the image (empty mask)")
        depth = r.render_depth()
        if callable(mat):
            r.set_material(mat(mask))

        def images():
            for i in progress_bar(range(len(L)), desc=out.name, unit="light", leave=False, disable=not progress):
                yield (r.render(L[i], p.light_intensity) if positions is None
                       else r.render_point(positions[i] + np.asarray(CAMERA_ORIGIN), p.light_intensity))

        def scene() -> dict[str, Any]:
            return {
                **info, "camera": {"model": "perspective", "fov_deg": float(fov_deg), "position": list(CAMERA_ORIGIN)},
                "lights": ({"model": "sun"} if positions is None
                           else {"model": "point", "distance_from_object_centre": float(light_distance)}),
                "material": material, "superpixels": superpixels, **p.picture_params(), "device": device,
                "median_depth": float(np.nanmedian(depth)), "render_seconds": round(time.perf_counter() - t0, 3),
            }

        capture = Capture(filenames=names, lights=None if positions is not None else L, light_positions=positions,
                          intensities=np.full((len(L), 3), p.light_intensity), intrinsics=r.intrinsics(), mask=mask,
                          normal_gt=normal, depth_gt=depth)
        write_capture(out, capture, images(), scene=scene, overwrite=True)  # out: absent or empty (checked above)
    return out
