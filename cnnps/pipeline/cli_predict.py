"""The `cnnps predict` command: normals (and, with --depth, a surface) for one capture folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from cnnps.api.cameras import CAMERAS
from cnnps.api.light_models import LIGHT_MODELS
from cnnps.api.solvers import SOLVERS
from cnnps.infra.errors import ConfigError
from cnnps.pipeline.app import app


def _parse_int(name: str, text: str, minimum: int) -> int:
    from cnnps.infra.options import Range, parse

    return parse(name, text, Annotated[int, Range(ge=minimum)])


def _default(name: str):
    """The default of :func:`cnnps.predict`'s option ``name``: shown in the help, never
    repeated here (an option left unset is not passed on)."""
    import inspect

    from cnnps.api.prediction import predict

    return inspect.signature(predict).parameters[name].default


def parse_drop(text: Optional[str]) -> Optional[list[int]]:
    """'0,1,2' -> [0, 1, 2]; '0-19' -> [0, ..., 19]; '' or 'none' -> [] and None -> None
    (both drop nothing)."""
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
    out: Path = typer.Option(..., "--out", "-o", help="Output folder, written whole, by one run at a time (a second run into it stops at once): normal.npy, normal.png, and error.png + metrics.json when ground truth exists."),
    model: Optional[Path] = typer.Option(None, "--model", help="CNN-PS checkpoint (default: the shipped cnnps/models/weights/cnnps_default.pt)."),
    method: Optional[str] = typer.Option(None, "--method", metavar="|".join(SOLVERS), help=f"The normal solver, by its name in cnnps/api/solvers.py: cnn (the network), lambertian (least squares, the baseline) or another registered there. (default: {_default('method')})"),
    rotations: Optional[str] = typer.Option(None, "--rotations", metavar="K", help=f"Test-time rotations averaged (cnn; 10 = the paper). (default: {_default('rotations')})"),
    device: Optional[str] = typer.Option(None, "--device", metavar="auto|cpu|cuda", help=f"Where the network runs; auto = CUDA when available. (default: {_default('device')})"),
    precision: Optional[str] = typer.Option(None, "--precision", metavar="auto|fp32|bf16", help=f"auto: the fastest path within 0.05 deg of fp32 on this machine, measured once (about 1 s) and cached. (default: {_default('precision')})"),
    batch_size: Optional[str] = typer.Option(None, "--batch-size", metavar="N", help="Observation maps per network batch (default 256 on a CPU, 4096 on CUDA)."),
    drop: Optional[str] = typer.Option(None, "--drop", metavar="INDICES", help="Image indices to leave out, 0-based, e.g. '0,1,2' or '0-19' (default: none). DiLiGenT's bearPNG: '0-19' scores it as the benchmark does."),
    shadow_threshold: Optional[str] = typer.Option(None, "--shadow-threshold", metavar="T", help="lambertian: per pixel, use only lights brighter than this fraction of its brightest, in [0, 1)."),
    grey: Optional[str] = typer.Option(None, "--grey", metavar="mean|luminance", help=f"How RGB becomes grey. (default: {_default('grey')})"),
    linearize: Optional[str] = typer.Option(None, "--linearize", metavar="srgb|none", help="How 8/16-bit images become linear: srgb = decode the sRGB curve (camera JPEG/PNG), none = already linear (DiLiGenT, raw converters). Unset: taken as linear, with a note when images are 8-bit. Camera RAW photos are always read linearly."),
    saturated: Optional[str] = typer.Option(None, "--saturated", metavar="exclude|keep", help=f"exclude: observations with a channel >= 0.99 of the format's maximum are left out (missing); keep: use them as stored. (default: {_default('saturated')})"),
    sparse_fill: Optional[str] = typer.Option(None, "--sparse-fill", metavar="auto|on|off", help=f"cnn: add virtual Lambertian observations to sparse maps, per pixel only where a Lambertian fit explains its observations; auto = with fewer than 50 images. (default: {_default('sparse_fill')})"),
    depth: bool = typer.Option(False, "--depth", help="Also integrate the normals into depth.npy, depth.png and surface.ply."),
    report: bool = typer.Option(True, "--report/--no-report", help="Write report.html: the normals relit by a light you drag, the confidence, the errors, the surface and the record, in one page that opens from disk (`cnnps report OUT_DIR` makes it again)."),
    tile_pixels: Optional[str] = typer.Option(None, "--tile-pixels", metavar="N", help=f"Mask pixels processed at a time (memory ~ N x images x 8 bytes). (default: {_default('tile_pixels')})"),
    camera_model: Optional[str] = typer.Option(None, "--camera-model", metavar="|".join(CAMERAS), help="The camera, by its name in cnnps/api/cameras.py. (default: pinhole when the capture has intrinsics.txt, else orthographic)"),
    light_model: Optional[str] = typer.Option(None, "--light-model", metavar="|".join(LIGHT_MODELS), help="The lights, by their model's name in cnnps/api/light_models.py. (default: point when the capture has light_positions.txt, else directional)"),
    distance: Optional[str] = typer.Option(None, "--distance", metavar="D", help="Point lights (light_positions.txt): the object's median depth along the optical axis, in the positions' unit; starts the rounds and sets depth.npy's scale. (default: the lights' median distance from the camera)"),
    rounds: Optional[str] = typer.Option(None, "--rounds", metavar="N", help=f"Point lights: the most rounds of normals -> depth -> per-pixel lights. (default: {_default('rounds')})"),
    depth_tolerance: Optional[str] = typer.Option(None, "--depth-tolerance", metavar="T", help=f"Point lights: stop once a round changes the depth by less than this (median relative change). (default: {_default('depth_tolerance')})"),
    scratch: Optional[Path] = typer.Option(None, "--scratch", metavar="DIR", help="Folder for the temporary pixel stack of large captures (default: next to --out; about pixels x images x 4 bytes)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars (one line per bar when the output is not a terminal)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Say which inference path ran and why."),
) -> None:
    """Predict surface normals for a capture folder."""
    from cnnps.api.prediction import predict_folder
    from cnnps.infra.options import Count, Positive, UnitFraction, parse

    given = {"method": method, "device": device, "precision": precision, "grey": grey, "linearize": linearize,
             "saturated": saturated, "sparse_fill": sparse_fill, "model": model, "camera_model": camera_model,
             "light_model": light_model,
             "rotations": None if rotations is None else parse("--rotations", rotations, Count),
             "batch_size": None if batch_size is None else parse("--batch-size", batch_size, Count),
             "tile_pixels": None if tile_pixels is None else parse("--tile-pixels", tile_pixels, Count),
             "distance": None if distance is None else parse("--distance", distance, Positive),
             "rounds": None if rounds is None else parse("--rounds", rounds, Count),
             "depth_tolerance": None if depth_tolerance is None else parse("--depth-tolerance", depth_tolerance, Positive),
             "shadow_threshold": (None if shadow_threshold is None
                                  else parse("--shadow-threshold", shadow_threshold, UnitFraction))}
    result = predict_folder(capture_dir, out, drop=parse_drop(drop), depth=depth, report=report, scratch_dir=scratch,
                            progress=progress, command="cnnps predict", **{k: v for k, v in given.items() if v is not None})
    _report(result, capture_dir, out, verbose)


def _age(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def _report(result: dict, capture_dir: Path, out: Path, verbose: bool) -> None:
    """The run's lines: -v details and notices on stderr, notes and the summary on stdout."""
    if verbose and result.get("precision_choice"):
        how = result["precision_choice"]
        cached = ""
        if how.get("cached"):
            age = how.get("age_seconds")
            cached = " (cached)" if age is None else f" (cached, measured {_age(age)} ago)"
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
    how = result["method"] if result["method"] == "lambertian" else f"cnn, K={result['rotations']}"
    line = f"{Path(capture_dir).name} ({how}, {result['n_images']} images, {result['pixels']} pixels)"
    if "mean_deg" in result:
        line += f": mean {result['mean_deg']:.2f} deg, median {result['median_deg']:.2f} deg"
    line += f" -> {out} ({result['seconds']:.1f} s)"
    typer.echo(line)
