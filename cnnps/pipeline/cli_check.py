"""The `cnnps check` command: what will hurt a capture's normals, before predicting."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from cnnps.api.prediction_options import CAPTURE, OUTPUT
from cnnps.pipeline.app import app
from cnnps.pipeline.cli_predict import DROP_FLAG, INTENSITIES_FLAG, LIGHTS_FLAG, MASK_FLAG


@app.command("check")
def check(
    capture_dir: Path = typer.Argument(..., help="Capture folder (docs/capture.md)."),
    drop: Optional[str] = DROP_FLAG,
    mask: str = MASK_FLAG,
    intensities: str = INTENSITIES_FLAG,
    lights: Optional[Path] = LIGHTS_FLAG,
    linearize: Optional[str] = typer.Option(None, "--linearize", metavar="srgb|none",
                                            help="How 8/16-bit images become linear.", rich_help_panel=CAPTURE),
    json_out: Optional[Path] = typer.Option(None, "--json", metavar="FILE",
                                            help="Also write the findings there (atomically).", rich_help_panel=OUTPUT),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bars.", rich_help_panel=OUTPUT),
) -> None:
    """Say what will hurt the normals of CAPTURE_DIR and how to fix it: clipped and dim
    images, frames that moved, the lights' count and cone, the intensities, differing
    EXIF exposure. Exits 0 with warnings; refuses (exit 2) only what `cnnps predict`
    refuses. Details: docs/capture.md."""
    import json

    from cnnps.api.capture_check import check_capture
    from cnnps.api.capture_estimates import IntensitySource, Source
    from cnnps.infra.atomic import write_text
    from cnnps.infra.options import parse
    from cnnps.io.srgb import Linearize
    from cnnps.pipeline.cli_predict import parse_drop

    result = check_capture(capture_dir, drop=parse_drop(drop), mask=parse("--mask", mask, Source),
                           intensities=parse("--intensities", intensities, IntensitySource), lights_dir=lights,
                           linearize=None if linearize is None else parse("--linearize", linearize, Linearize),
                           progress=progress)
    for line in result.summary:
        typer.echo(line)
    for finding in result.findings:
        typer.echo(f"{finding.level}: {finding.kind}: {finding.message}")
    n = len(result.warnings)
    typer.echo(f"{n} warning{'s' if n != 1 else ''}; cnnps predict will run on this capture"
               + ("" if n else ": nothing found that will hurt"))
    if json_out is not None:
        write_text(json_out, json.dumps({"capture": str(capture_dir), **result.record()}, indent=1))
