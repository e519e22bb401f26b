"""The `cnnps predict` command: normals (and, with --depth, a surface) for one capture folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from cnnps.core.errors import ConfigError
from cnnps.pipeline.app import app


def _parse_int(name: str, text: str, minimum: int) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {text!r}") from None
    if value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {text!r}")
    return value


def parse_drop(text: Optional[str]) -> Optional[list[int]]:
    """'0,1,2' -> [0, 1, 2]; '' or 'none' -> [] (drop nothing); None -> None (default)."""
    if text is None:
        return None
    text = text.strip()
    if text.lower() in ("", "none"):
        return []
    out = []
    for part in text.replace(" ", ",").split(","):
        if not part:
            continue
        if "-" in part[1:]:  # a range a-b, inclusive
            a, b = part.split("-", 1)
            lo, hi = _parse_int("--drop", a, 0), _parse_int("--drop", b, 0)
            if hi < lo:
                raise ConfigError(f"--drop: empty range {part!r}")
            out.extend(range(lo, hi + 1))
        else:
            out.append(_parse_int("--drop", part, 0))
    return out


@app.command("predict")
def predict(
    capture_dir: Path = typer.Argument(..., help="Capture folder (DiLiGenT layout: filenames.txt, light_directions.txt, light_intensities.txt, mask.png, images)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (written atomically): normal.npy, normal.png, and error.png + metrics.json when ground truth exists."),
    model: Optional[Path] = typer.Option(None, "--model", help="CNN-PS checkpoint (default: the shipped cnnps/models/weights/cnnps_default.pt)."),
    method: str = typer.Option("cnn", "--method", help="cnn | lambertian (least-squares baseline)."),
    rotations: str = typer.Option("10", "--rotations", metavar="K", help="Test-time rotations averaged (cnn; 10 = the paper)."),
    device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
    precision: str = typer.Option("auto", "--precision", help="auto | fp32 | bf16. auto: the fastest path within 0.05 deg of fp32 on this machine, measured once (about 1 s) and cached."),
    batch_size: Optional[str] = typer.Option(None, "--batch-size", metavar="N", help="Observation maps per network batch (default 256 on a CPU, 4096 on CUDA)."),
    drop: Optional[str] = typer.Option(None, "--drop", metavar="INDICES", help="Image indices to leave out, 0-based, e.g. '0,1,2' or '0-19'; 'none' drops nothing (bearPNG drops its first 20 by default)."),
    shadow_threshold: Optional[str] = typer.Option(None, "--shadow-threshold", metavar="T", help="lambertian: per pixel, use only lights brighter than this fraction of its brightest, in [0, 1)."),
    grey: str = typer.Option("mean", "--grey", help="mean | luminance: how RGB becomes grey."),
    linearize: Optional[str] = typer.Option(None, "--linearize", metavar="srgb|none", help="How 8/16-bit images become linear: srgb = decode the sRGB curve (camera JPEG/PNG), none = already linear (DiLiGenT, raw converters). Unset: taken as linear, with a note when images are 8-bit."),
    saturated: str = typer.Option("exclude", "--saturated", metavar="exclude|keep", help="exclude: observations with a channel >= 0.99 of the format's maximum are left out (missing); keep: use them as stored."),
    sparse_fill: str = typer.Option("auto", "--sparse-fill", metavar="auto|on|off", help="cnn: add virtual Lambertian observations to sparse maps, per pixel only where a Lambertian fit explains its observations; auto = with fewer than 50 images."),
    depth: bool = typer.Option(False, "--depth", help="Also integrate the normals into depth.npy, depth.png and surface.ply."),
    tile_pixels: str = typer.Option("65536", "--tile-pixels", metavar="N", help="Mask pixels processed at a time (memory ~ N x images x 8 bytes)."),
    scratch: Optional[Path] = typer.Option(None, "--scratch", metavar="DIR", help="Folder for the temporary pixel stack of large captures (default: next to --out; about pixels x images x 4 bytes)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Say which inference path ran and why."),
) -> None:
    """Predict surface normals for a capture folder."""
    from cnnps.pipeline.predict import DEFAULT_BATCH_SIZE, predict_capture

    k = _parse_int("--rotations", rotations, 1)
    bs = DEFAULT_BATCH_SIZE if batch_size is None else _parse_int("--batch-size", batch_size, 1)
    tiles = _parse_int("--tile-pixels", tile_pixels, 1)
    if linearize is not None and linearize not in ("srgb", "none"):
        raise ConfigError(f"--linearize must be srgb or none, got {linearize!r}")
    t = None
    if shadow_threshold is not None:
        try:
            t = float(shadow_threshold)
        except ValueError:
            raise ConfigError(f"--shadow-threshold must be a number in [0, 1), got {shadow_threshold!r}") from None
    if grey not in ("mean", "luminance"):
        raise ConfigError(f"--grey must be mean or luminance, got {grey!r}")
    result = predict_capture(
        capture_dir,
        out,
        method=method,
        model=model,
        rotations=k,
        device=device,
        precision=precision,
        batch_size=bs,
        drop=parse_drop(drop),
        shadow_threshold=t,
        grey=grey,
        progress=progress,
        linearize=linearize,
        depth=depth,
        tile_pixels=tiles,
        scratch_dir=scratch,
        saturated=saturated,
        sparse_fill=sparse_fill,
    )
    if verbose and result.get("precision_choice"):
        how = result["precision_choice"]
        cached = " (cached)" if how.get("cached") else ""
        typer.echo(f"cnnps: precision {result['precision']}{cached}: {how['reason']}", err=True)
    fill = result.get("sparse_fill")
    if verbose and fill and fill["used"]:
        typer.echo(f"cnnps: sparse fill ({fill['mode']}): {fill['filled_pixels']} of {result['pixels']} pixels "
                   "got virtual Lambertian observations", err=True)
    for note in result.get("notes", []):
        typer.echo(f"note: {note}")
    for notice in result.get("notices", []):
        typer.echo(f"cnnps: note: {notice}", err=True)
    for warning in result.get("warnings", []):
        typer.echo(f"cnnps: warning: {warning}", err=True)
    how = method if method == "lambertian" else f"cnn, K={k}"
    line = f"{Path(capture_dir).name} ({how}, {result['n_images']} images, {result['pixels']} pixels)"
    if "mean_deg" in result:
        line += f": mean {result['mean_deg']:.2f} deg, median {result['median_deg']:.2f} deg"
    line += f" -> {out} ({result['seconds']:.1f} s)"
    typer.echo(line)
