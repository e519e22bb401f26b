"""Render one synthetic capture folder with Blender Cycles: what :func:`cnnps.render` runs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Count, Range, check_arguments
from cnnps.synth.capture_render import Material

RenderDevice = Literal["cpu", "gpu"]


def render(
    mesh,
    out_dir,
    *,
    lights: Count = 40,
    size: Count = 128,
    samples: Count = 32,
    material: Material = "lambertian",
    superpixels: Count = 100,
    seed: int = 0,
    device: RenderDevice = "cpu",
    jitter: float = 0.0,
    max_bounces: int = 8,
    threads: Annotated[int, Range(ge=0)] = 0,
    fov: float | None = None,
    light_distance: float | None = None,
    progress: bool = False,
) -> Path:
    """Render ``mesh`` under ``lights`` sun lights into a capture folder and return its path.

    Arguments:
        mesh: a mesh file (OBJ, PLY, OFF, STL, glTF; centred and scaled into the unit
            sphere), a ``trimesh.Trimesh`` in the camera frame, or
            ``"procedural:<kind>[:seed]"`` (blob, bowl, assembly, bumpy, holed).
        out_dir: the capture folder to write (DiLiGenT layout + float32 EXR images,
            normal_gt.npy, scene.json); a partial folder is resumed.
        lights: sun lights over the upper hemisphere (Fibonacci spiral), ``jitter``
            degrees of random offset each.
        size: image width = height in pixels; the orthographic camera covers x, y in [-1, 1].
        samples: Cycles path samples per pixel; max_bounces: global-illumination bounces.
        material: "lambertian" (white, albedo 1) or a materials-stage category drawn on
            ``superpixels`` regions with ``seed``.
        device: "cpu" or "gpu" (Cycles OptiX/CUDA/HIP/oneAPI/Metal); threads: Cycles CPU
            threads (0 = all cores).
        fov: a pinhole camera of this field of view (degrees) at distance 5 instead of
            the orthographic one; the folder then has ``intrinsics.txt`` and
            ``depth_gt.npy`` and is written at once, not resumed
            (:mod:`cnnps.synth.rig_render`).
        light_distance: with ``fov``: point lights this far from the object's centre (in
            (1, 5); the object fills the unit sphere), written as ``light_positions.txt``.

    Needs Blender (``pip install 'cnnps[render]'``, Python 3.11); without it a
    :class:`cnnps.infra.errors.ConfigError` says so before anything is written.

    Example (needs bpy; about 10 s on 2 cores)::

        >>> import cnnps                                                  # doctest: +SKIP
        >>> folder = cnnps.render("procedural:blob", "blob", lights=20, size=64)  # doctest: +SKIP
        >>> cap = cnnps.load_capture(folder)                              # doctest: +SKIP
    """
    from cnnps.synth.capture_render import render_capture

    check_arguments(render, {"lights": lights, "size": size, "samples": samples, "material": material,
                             "superpixels": superpixels, "device": device, "threads": threads})
    if light_distance is not None and fov is None:
        raise ConfigError("light_distance (point lights) needs fov: point lights are placed relative to a pinhole camera")
    if fov is not None:
        from cnnps.synth.rig_render import render_rig_capture

        return render_rig_capture(mesh, out_dir, fov_deg=fov, light_distance=light_distance, lights=lights, size=size,
                                  samples=samples, material=material, superpixels=superpixels, seed=seed,
                                  device=device, jitter_deg=jitter, max_bounces=max_bounces, threads=threads,
                                  progress=progress)
    return render_capture(mesh, out_dir, lights=lights, size=size, samples=samples, material=material,
                          superpixels=superpixels, seed=seed, device=device, jitter_deg=jitter,
                          max_bounces=max_bounces, threads=threads, progress=progress)
