"""The `cnnps calibrate` command: light directions (and intensities) from ball photos."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from cnnps.pipeline.app import app


def _ball_line(what: str, ball) -> str:
    return (f"{what}: centre x={ball.cx:.2f}, y={ball.cy:.2f} px, radius {ball.radius:.2f} px "
            f"({ball.source}; fit RMS {ball.rms_px:.2f} px)")


@app.command("calibrate")
def calibrate(
    chrome_dir: Path = typer.Argument(..., help="Chrome (mirror) ball photos, one per light in the object's light order: filenames.txt, the images (PNG, JPEG, TIFF, EXR), optional mask.png of the ball."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (written atomically): light_directions.txt, light_intensities.txt (with --matte), calibration.json, calibration.png."),
    matte: Optional[Path] = typer.Option(None, "--matte", help="Matte white ball photos under the same lights (same count and order; optional mask.png): per-light RGB intensities."),
    linearize: Optional[str] = typer.Option(None, "--linearize", metavar="srgb|none", help="How 8/16-bit images become linear, as in cnnps predict: srgb = decode the sRGB curve (camera JPEG/PNG), none = already linear. Unset: taken as linear, with a note when images are 8-bit. Camera RAW photos are always read linearly."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Calibrate the lights from photos of a chrome ball (directions) and a matte ball (intensities)."""
    from cnnps.api.calibration import SCALE_NOTE, check_out_dir, write_calibration
    from cnnps.api.calibration import calibrate as run

    check_out_dir(out, chrome_dir, matte)
    cal = run(chrome_dir, matte, progress=progress, linearize=linearize)
    write_calibration(cal, out)
    for notice in cal.notices:
        typer.echo(f"cnnps: note: {notice}", err=True)
    typer.echo(_ball_line("chrome ball", cal.ball))
    if cal.matte_ball is not None:
        typer.echo(_ball_line("matte ball", cal.matte_ball))
        typer.echo(f"light_intensities.txt: {SCALE_NOTE}")
    else:
        typer.echo("note: no --matte: light_intensities.txt not written (give the object's capture one; "
                   "all '1 1 1' assumes equal lights)")
    saturated = sum(1 for h in cal.highlights if h.saturated_px)
    extra = f", {saturated} with a clipped core" if saturated else ""
    typer.echo(f"{len(cal.names)} light directions{extra} -> {out} (check the highlights in "
               f"{Path(out) / 'calibration.png'}; {cal.report['seconds']:.1f} s)")
