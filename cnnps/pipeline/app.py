"""The Typer application object; command modules register themselves on it."""

import typer

app = typer.Typer(
    name="cnnps",
    help="Learning-based calibrated photometric stereo (CNN-PS): render, train, predict.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Learning-based calibrated photometric stereo (CNN-PS): render, train, predict."""
