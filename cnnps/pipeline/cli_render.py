"""The `cnnps render` command: one synthetic capture folder rendered with Blender Cycles.

The library side is :func:`cnnps.render` (:func:`cnnps.synth.capture_render.render_capture`).
Every option is a field of :class:`cnnps.synth.render.settings.CaptureSettings`, spelled
as a flag (``jitter_deg`` -> ``--jitter-deg``), with the default of :func:`cnnps.render`'s
signature (which reads it from that class). Blender (bpy, the ``cnnps[render]`` extra) is
imported only when there are images to render, so `--help`, option checks and an already
complete folder work without it.
"""

from __future__ import annotations

from pathlib import Path

import typer

from cnnps.pipeline.app import app


def _default(name: str):
    """The default of :func:`cnnps.render`'s option ``name`` (the one place it lives)."""
    import inspect

    from cnnps.api.rendering import render as render_folder

    return inspect.signature(render_folder).parameters[name].default


@app.command("render")
def render(
    mesh: str = typer.Argument(..., metavar="MESH", help="Mesh file (OBJ, PLY, OFF, STL, glTF; centred and scaled into the unit sphere) or procedural:<kind>[:seed] (blob, bowl, assembly, bumpy, holed)."),
    out: Path = typer.Option(..., "--out", "-o", help="Capture folder to write (DiLiGenT layout + float32 EXR images, normal_gt.npy, scene.json). Rerunning resumes a partial folder. An existing folder must be empty or a cnnps render folder."),
    lights: int = typer.Option(_default("lights"), "--lights", metavar="N", help="Number of lights over the upper hemisphere (Fibonacci spiral): suns, or point lights with --light-distance."),
    size: int = typer.Option(_default("size"), "--size", metavar="PIXELS", help="Image width = height; the orthographic camera covers x, y in [-1, 1]."),
    samples: int = typer.Option(_default("samples"), "--samples", metavar="SPP", help="Cycles path samples per pixel."),
    material: str = typer.Option(_default("material"), "--material", help="lambertian | diffuse | specular | metallic | narrow."),
    superpixels: int = typer.Option(_default("superpixels"), "--superpixels", metavar="P", help="Material regions (non-lambertian materials)."),
    seed: int = typer.Option(_default("seed"), "--seed", metavar="S", help="Seed for lights, material and Cycles sampling."),
    device: str = typer.Option(_default("device"), "--device", help="cpu | gpu (Cycles OptiX/CUDA/HIP/oneAPI/Metal)."),
    jitter_deg: float = typer.Option(_default("jitter_deg"), "--jitter-deg", metavar="DEG", help="Random offset of each light direction from the spiral, degrees."),
    min_elevation_deg: float = typer.Option(_default("min_elevation_deg"), "--min-elevation-deg", metavar="DEG", help="Every light at least this far above the horizon, degrees."),
    light_intensity: float = typer.Option(_default("light_intensity"), "--light-intensity", metavar="I", help="Lamp intensity: a white patch facing a sun reads I (a point light: I / r^2)."),
    max_bounces: int = typer.Option(_default("max_bounces"), "--max-bounces", metavar="N", help="Cycles bounces (global illumination)."),
    threads: int = typer.Option(_default("threads"), "--threads", metavar="N", help="Cycles CPU threads (0 = all cores)."),
    fov_deg: float = typer.Option(_default("fov_deg"), "--fov-deg", metavar="DEG", help="A pinhole camera of this field of view at distance 5, 0 < DEG < 120 (writes intrinsics.txt and depth_gt.npy)."),
    light_distance: float = typer.Option(_default("light_distance"), "--light-distance", metavar="D", help="With --fov-deg: point lights D from the object's centre, 1 < D < 5 (the object fills the unit sphere); writes light_positions.txt."),
    environment: float = typer.Option(_default("environment"), "--environment", metavar="S", help="A dim uniform white world of S x the light intensity in every image (0 = black world)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Render MESH under N lights into a capture folder that `cnnps predict` reads."""
    from cnnps.api.rendering import render as render_folder

    path = render_folder(mesh, out, lights=lights, size=size, samples=samples, material=material,
                         superpixels=superpixels, seed=seed, device=device, jitter_deg=jitter_deg,
                         min_elevation_deg=min_elevation_deg, light_intensity=light_intensity,
                         max_bounces=max_bounces, threads=threads, fov_deg=fov_deg, light_distance=light_distance,
                         environment=environment, progress=progress)
    typer.echo(f"wrote {path}")
