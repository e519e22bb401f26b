"""The `cnnps render` command: one synthetic capture folder rendered with Blender Cycles.

The library side is :func:`cnnps.synth.capture_render.render_capture`; Blender (bpy, the
``cnnps[render]`` extra) is imported only when there are images to render, so `--help`,
option checks and an already complete folder work without it.
"""

from __future__ import annotations

from pathlib import Path

import typer

from cnnps.core.errors import ConfigError
from cnnps.pipeline.app import app


@app.command("render")
def render(
    mesh: str = typer.Argument(..., metavar="MESH", help="Mesh file (OBJ, PLY, OFF, STL, glTF; centred and scaled into the unit sphere) or procedural:<kind>[:seed] (blob, bowl, assembly, bumpy, holed)."),
    out: Path = typer.Option(..., "--out", "-o", help="Capture folder to write (DiLiGenT layout + float32 EXR images, normal_gt.npy, scene.json). Rerunning resumes a partial folder. An existing folder must be empty or a cnnps render folder."),
    lights: int = typer.Option(40, "--lights", metavar="N", help="Number of sun lights over the upper hemisphere (Fibonacci spiral)."),
    size: int = typer.Option(128, "--size", metavar="PIXELS", help="Image width = height; the camera covers x, y in [-1, 1]."),
    samples: int = typer.Option(32, "--samples", metavar="SPP", help="Cycles path samples per pixel."),
    material: str = typer.Option("lambertian", "--material", help="lambertian | diffuse | specular | metallic."),
    superpixels: int = typer.Option(100, "--superpixels", metavar="P", help="Material regions (non-lambertian materials)."),
    seed: int = typer.Option(0, "--seed", metavar="S", help="Seed for lights, material and Cycles sampling."),
    device: str = typer.Option("cpu", "--device", help="cpu | gpu (Cycles OptiX/CUDA/HIP/oneAPI/Metal)."),
    jitter: float = typer.Option(0.0, "--jitter", metavar="DEG", help="Random offset of each light direction from the spiral, degrees."),
    max_bounces: int = typer.Option(8, "--max-bounces", metavar="N", help="Cycles bounces (global illumination)."),
    threads: int = typer.Option(0, "--threads", metavar="N", help="Cycles CPU threads (0 = all cores)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Render MESH under N lights into a capture folder that `cnnps predict` reads."""
    from cnnps.synth.capture_render import MATERIAL_KINDS, render_capture

    if material not in MATERIAL_KINDS:
        raise ConfigError(f"--material must be one of {', '.join(MATERIAL_KINDS)}, got {material!r}")
    if device not in ("cpu", "gpu"):
        raise ConfigError(f"--device must be cpu or gpu, got {device!r}")
    if threads < 0:
        raise ConfigError(f"--threads must be >= 0, got {threads}")
    path = render_capture(
        mesh, out, lights=lights, size=size, samples=samples, material=material, superpixels=superpixels,
        seed=seed, device=device, jitter_deg=jitter, max_bounces=max_bounces, threads=threads, progress=progress,
    )
    typer.echo(f"wrote {path}")
