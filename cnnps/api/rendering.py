"""Render one synthetic capture folder with Blender Cycles: what :func:`cnnps.render` runs.

Its keyword arguments are the fields of :class:`cnnps.synth.render.settings.CaptureSettings`
with that class's defaults (read from it, so the two cannot drift apart); ``cnnps render``
takes its option defaults from this signature, and the render stage's ``Params`` extend
the same :class:`cnnps.synth.render.settings.RenderSettings`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from cnnps.infra.options import Count, Range, check_arguments
from cnnps.synth.render.settings import CaptureSettings, Material

RenderDevice = Literal["cpu", "gpu"]
_DEFAULTS = CaptureSettings()


def render(
    mesh,
    out_dir,
    *,
    lights: Count = _DEFAULTS.lights,
    size: Count = _DEFAULTS.size,
    samples: Count = _DEFAULTS.samples,
    material: Material = _DEFAULTS.material,
    superpixels: Count = _DEFAULTS.superpixels,
    seed: int = _DEFAULTS.seed,
    device: RenderDevice = _DEFAULTS.device,
    jitter_deg: float = _DEFAULTS.jitter_deg,
    min_elevation_deg: float = _DEFAULTS.min_elevation_deg,
    light_intensity: float = _DEFAULTS.light_intensity,
    max_bounces: int = _DEFAULTS.max_bounces,
    threads: Annotated[int, Range(ge=0)] = _DEFAULTS.threads,
    fov_deg: float | None = _DEFAULTS.fov_deg,
    light_distance: float | None = _DEFAULTS.light_distance,
    environment: float = _DEFAULTS.environment,
    progress: bool = False,
) -> Path:
    """Render ``mesh`` under ``lights`` lights into a capture folder and return its path.

    Arguments (defaults: :class:`cnnps.synth.render.settings.CaptureSettings`):
        mesh: a mesh file (OBJ, PLY, OFF, STL, glTF; centred and scaled into the unit
            sphere), a ``trimesh.Trimesh`` in the camera frame, or
            ``"procedural:<kind>[:seed]"`` (blob, bowl, assembly, bumpy, holed).
        out_dir: the capture folder to write (DiLiGenT layout + float32 EXR images,
            normal_gt.npy, scene.json); a partial or damaged folder is resumed, whatever
            the camera and lights.
        lights: 40 lights over the upper hemisphere (Fibonacci spiral), ``jitter_deg``
            (0) degrees of random offset each, at least ``min_elevation_deg`` (5) above
            the horizon, of intensity ``light_intensity`` (1: a white patch facing a sun
            reads 1).
        size: 128, image width = height in pixels; the orthographic camera covers x, y
            in [-1, 1].
        samples: 32 Cycles path samples per pixel; max_bounces: 8 global-illumination bounces.
        material: "lambertian" (white, albedo 1) or a materials-stage category drawn on
            ``superpixels`` (100) regions with ``seed`` (0).
        device: "cpu" or "gpu" (Cycles OptiX/CUDA/HIP/oneAPI/Metal); threads: Cycles CPU
            threads (0 = all cores).
        fov_deg: a pinhole camera of this field of view (degrees, in (0, 120)) at distance
            5 instead of the orthographic one; the folder then has ``intrinsics.txt`` and
            ``depth_gt.npy``.
        light_distance: with ``fov_deg``: point lights this far from the object's centre
            (in (1, 5); the object fills the unit sphere), written as ``light_positions.txt``.
        environment: a dim uniform white world of this strength relative to the lights in
            every image (0 = black world).

    Needs Blender (``pip install 'cnnps[render]'``, Python 3.11); without it a
    :class:`cnnps.infra.errors.ConfigError` says so before anything is written.

    Example (needs bpy; about 10 s on 2 cores)::

        >>> import cnnps                                                  # doctest: +SKIP
        >>> folder = cnnps.render("procedural:blob", "blob", lights=20, size=64)  # doctest: +SKIP
        >>> rig = cnnps.render("procedural:blob", "rig", fov_deg=40.0, light_distance=3.0)  # doctest: +SKIP
        >>> cap = cnnps.load_capture(folder)                              # doctest: +SKIP
    """
    from cnnps.synth.capture_render import render_capture

    options = dict(lights=lights, size=size, samples=samples, material=material, superpixels=superpixels, seed=seed,
                   device=device, jitter_deg=jitter_deg, min_elevation_deg=min_elevation_deg,
                   light_intensity=light_intensity, max_bounces=max_bounces, threads=threads, fov_deg=fov_deg,
                   light_distance=light_distance, environment=environment)
    check_arguments(render, options)
    return render_capture(mesh, out_dir, CaptureSettings(**options), progress=progress)
