"""The `cnnps report` command: report.html again, from a finished `cnnps predict` folder."""

from __future__ import annotations

from pathlib import Path

import typer

from cnnps.pipeline.app import app


@app.command("report")
def report(
    out_dir: Path = typer.Argument(..., help="A folder `cnnps predict` wrote (prediction.json, normal.npy, ...)."),
) -> None:
    """Write OUT_DIR/report.html again from the files of a finished prediction: the normals
    relit by a light you drag, the confidence, the errors, the surface and the record, in
    one page that opens from disk. The histogram of the errors needs the capture's ground
    truth, read again from the capture folder the prediction records."""
    from cnnps.io.report import rebuild_report

    path = rebuild_report(out_dir)
    typer.echo(f"{path} ({path.stat().st_size / 1e6:.1f} MB)")
