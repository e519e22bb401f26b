"""The `cnnps integrate` command: a normal map -> depth.npy, depth.png, surface.ply."""

from __future__ import annotations

from pathlib import Path

import typer

from cnnps.pipeline.app import app


@app.command("integrate")
def integrate(
    normals: Path = typer.Argument(..., help="H x W x 3 normal map (.npy, capture frame: x right, y up, z toward the camera), e.g. the normal.npy of `cnnps predict`."),
    mask: Path = typer.Option(..., "--mask", "-m", help="Mask image (non-zero = object), the same size as the normals, e.g. the capture's mask.png."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created if needed; other files in it are kept): depth.npy, depth.png, surface.ply."),
    discontinuities: bool = typer.Option(False, "--discontinuities/--no-discontinuities", help="Robust (Cauchy) reweighting that lets depth jump at occlusions instead of spreading the error (slower; off by default)."),
    sigma: str = typer.Option("0.1", "--sigma", metavar="S", help="With --discontinuities: the residual scale, in pixels of height, above which an equation is down-weighted."),
    nz_min: str = typer.Option("0.05", "--nz-min", metavar="NZ", help="Smallest n_z used: steeper normals are clamped (slope <= 1/NZ) and down-weighted."),
) -> None:
    """Integrate a normal map into a height map and a triangle mesh."""
    import typing

    from cnnps.api.surfaces import integrate as integrate_normals
    from cnnps.infra.errors import InputError
    from cnnps.infra.options import parse
    from cnnps.io.images import read_mask
    from cnnps.io.surface import read_normals
    from cnnps.ps.integrate import check_inputs

    hints = typing.get_type_hints(integrate_normals, include_extras=True)
    nz = parse("--nz-min", nz_min, hints["nz_min"])
    s = parse("--sigma", sigma, hints["sigma"])
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    n = read_normals(normals)
    m = read_mask(mask)
    n, m = check_inputs(n, m, normals, mask)  # everything checked before anything is written
    report = integrate_normals(n, m, nz_min=nz, discontinuities=discontinuities, sigma=s).write(out)
    if report["clamped_pixels"]:
        typer.echo(f"note: {report['clamped_pixels']} pixels had n_z < {nz:g} (grazing normals); "
                   "their slopes were clamped and down-weighted")
    if report["faces"] == 0:
        typer.echo("cnnps: warning: the mask has no 2 x 2 block of pixels: surface.ply has no triangles", err=True)
    depth_range = (report["depth_max"] or 0.0) - (report["depth_min"] or 0.0)
    typer.echo(
        f"{normals.name}: {report['pixels']} pixels, {report['components']} component"
        f"{'s' if report['components'] != 1 else ''}, depth range {depth_range:.1f} px, "
        f"residual {report['residual_rms']:.3g} px, {report['faces']} faces -> {out} "
        f"({report['seconds']:.1f} s)"
    )
