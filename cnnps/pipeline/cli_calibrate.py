"""The `cnnps calibrate` command: light directions (and intensities) from ball photos."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from cnnps.pipeline.app import app


def _ball_line(what: str, ball) -> str:
    return (f"{what}: centre x={ball.cx:.2f}, y={ball.cy:.2f} px, radius {ball.radius:.2f} px "
            f"({ball.source}; fit RMS {ball.rms_px:.2f} px)")


BALLS, PHOTOS, OUTPUT = "Balls", "Photos", "Output"  # the --help panels; the details: docs/calibration.md


@app.command("calibrate")
def calibrate(
    chrome_dirs: list[Path] = typer.Argument(..., metavar="CHROME_DIR...",
                                             help="Chrome ball photos, one per light (two folders or more: point lights)."),
    matte: Optional[Path] = typer.Option(None, "--matte", metavar="DIR",
                                         help="Matte white ball photos: the intensities (optional).",
                                         rich_help_panel=BALLS),
    matte_radius: Optional[float] = typer.Option(None, "--matte-radius", metavar="R",
                                                 help="Point lights: the matte ball's radius.", rich_help_panel=BALLS),
    ball_radius: Optional[float] = typer.Option(None, "--ball-radius", metavar="R",
                                                help="Point lights: the chrome balls' radius.", rich_help_panel=BALLS),
    intrinsics: Optional[Path] = typer.Option(None, "--intrinsics", metavar="K.txt",
                                              help="The camera's 3x3 K (needed for point lights).",
                                              rich_help_panel=BALLS),
    linearize: Optional[str] = typer.Option(None, "--linearize", metavar="srgb|none",
                                            help="How 8/16-bit photos become linear, as in predict.",
                                            rich_help_panel=PHOTOS),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder, written whole.", rich_help_panel=OUTPUT),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bars.", rich_help_panel=OUTPUT),
) -> None:
    """Calibrate the lights from photos of a chrome ball: their directions (and, with
    --matte, their intensities from a matte white ball; without it `cnnps predict`
    estimates them from the object), or point-light positions from two or more chrome
    balls of known radius. Writes light_directions.txt (or light_positions.txt and
    intrinsics.txt), light_intensities.txt with --matte, calibration.json and .png.
    Details: docs/calibration.md."""
    from cnnps.api.calibration import SCALE_NOTE, check_out_dir, write_calibration
    from cnnps.api.calibration import calibrate as run

    if ball_radius is not None or len(chrome_dirs) > 1:
        _point_lights(chrome_dirs, out, matte, matte_radius, ball_radius, intrinsics, linearize, progress)
        return
    if matte_radius is not None:
        from cnnps.infra.errors import ConfigError

        raise ConfigError("--matte-radius applies to point lights (--ball-radius and two or more CHROME_DIRs)")
    chrome_dir = chrome_dirs[0]
    check_out_dir(out, chrome_dir, matte)
    cal = run(chrome_dir, matte, progress=progress, linearize=linearize,
              intrinsics=None if intrinsics is None else _read_k(intrinsics))
    write_calibration(cal, out)
    for notice in cal.notices:
        typer.echo(f"cnnps: note: {notice}", err=True)
    typer.echo(_ball_line("chrome ball", cal.ball))
    if cal.matte_ball is not None:
        typer.echo(_ball_line("matte ball", cal.matte_ball))
        typer.echo(f"light_intensities.txt: {SCALE_NOTE}")
    else:
        typer.echo("note: no --matte: light_intensities.txt not written; without one in the object's capture, "
                   "cnnps predict estimates the intensities from the object (docs/capture.md)")
    saturated = sum(1 for h in cal.highlights if h.saturated_px)
    extra = f", {saturated} with a clipped core" if saturated else ""
    typer.echo(f"{len(cal.names)} light directions{extra} -> {out} (check the highlights in "
               f"{Path(out) / 'calibration.png'}; {cal.report['seconds']:.1f} s)")


def _point_lights(chrome_dirs, out, matte, matte_radius, ball_radius, intrinsics, linearize, progress) -> None:
    from cnnps.api.calibration import check_out_dir
    from cnnps.api.point_calibration import (
        calibrate_point_lights,
        write_point_calibration,
    )
    from cnnps.infra.errors import ConfigError

    if ball_radius is None or intrinsics is None:
        raise ConfigError("point lights (two or more CHROME_DIRs) need --ball-radius and --intrinsics")
    if matte_radius is not None and matte is None:
        raise ConfigError("--matte-radius needs --matte (the matte ball's photos)")
    check_out_dir(out, *chrome_dirs, *([] if matte is None else [matte]))
    K = _read_k(intrinsics)
    cal = calibrate_point_lights(chrome_dirs, ball_radius=ball_radius, intrinsics=K, linearize=linearize,
                                 progress=progress, matte_dir=matte, matte_radius=matte_radius)
    write_point_calibration(cal, out)
    for notice in cal.notices:
        typer.echo(f"cnnps: note: {notice}", err=True)
    for ball in cal.report["balls"]:
        typer.echo(f"ball {ball['folder']}: radius {ball['radius_px']:.2f} px, centre "
                   f"({', '.join(f'{v:.4g}' for v in ball['centre'])})")
    if cal.intensities is not None:
        mb = cal.report["matte_ball"]
        typer.echo(f"matte ball {mb['folder']}: radius {mb['radius_px']:.2f} px, centre "
                   f"({', '.join(f'{v:.4g}' for v in mb['centre'])}); light_intensities.txt: "
                   f"{cal.report['intensities']['scale']}")
    else:
        typer.echo("note: no --matte: light_intensities.txt not written (identical LEDs: '1 1 1' on every line)")
    worst = max(cal.report["lights"], key=lambda r: r["residual_relative"])
    typer.echo(f"{len(cal.names)} light positions -> {out} (largest residual {worst['residual']:.3g}, "
               f"{100 * worst['residual_relative']:.2f} % of its distance, {worst['image']}; "
               f"{cal.report['seconds']:.1f} s)")


def _read_k(path: Path):
    from cnnps.infra.errors import InputError
    from cnnps.io.capture import read_intrinsics

    K = read_intrinsics(path)
    if K is None:
        raise InputError(path, "intrinsics file not found")
    return K
