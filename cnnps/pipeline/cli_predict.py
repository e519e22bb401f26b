"""The `cnnps predict` command: normals (and, with --depth, a surface) for one capture folder.

Its flags are the command's own (``--out``, ``--drop``, ...) and one per option of
:func:`cnnps.predict`, made from the options' declarations
(:func:`cnnps.api.prediction_options.declared_options`: name, type, default, help) when typer
builds the command, so a solver, camera or light model registered before ``cnnps`` runs
is among the choices and its options among the flags.
"""

from __future__ import annotations

import inspect
import typing
from pathlib import Path
from typing import Annotated, Optional

import typer

from cnnps.api.cameras import CAMERAS
from cnnps.api.light_models import LIGHT_MODELS
from cnnps.api.prediction_options import CAPTURE, METHOD, OUTPUT, PANELS
from cnnps.api.solvers import SOLVERS
from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Declared, choices
from cnnps.pipeline.app import app


def _parse_int(name: str, text: str, minimum: int) -> int:
    from cnnps.infra.options import Range, parse

    return parse(name, text, Annotated[int, Range(ge=minimum)])


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


# the capture's flags, shared with cnnps check
DROP_FLAG = typer.Option(None, "--drop", metavar="INDICES", help="Images to leave out: 0,1 or 0-19.",
                         rich_help_panel=CAPTURE)
MASK_FLAG = typer.Option("auto", "--mask", metavar="auto|file|estimate", help="mask.png, or made from the photos.",
                         rich_help_panel=CAPTURE)
INTENSITIES_FLAG = typer.Option("auto", "--intensities", metavar="auto|file|estimate|exif",
                                help="light_intensities.txt, estimated, or EXIF exposure.", rich_help_panel=CAPTURE)
LIGHTS_FLAG = typer.Option(None, "--lights", metavar="DIR", help="Light files from there (cnnps calibrate's -o).",
                           rich_help_panel=CAPTURE)


def _command(
    capture_dir: Path = typer.Argument(..., help="Capture folder (docs/capture.md)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder, written whole.", rich_help_panel=OUTPUT),
    drop: Optional[str] = DROP_FLAG,
    mask: str = MASK_FLAG,
    intensities: str = INTENSITIES_FLAG,
    lights: Optional[Path] = LIGHTS_FLAG,
    check: bool = typer.Option(False, "--check", help="Also say what hurts (as cnnps check does).",
                               rich_help_panel=OUTPUT),
    depth: bool = typer.Option(False, "--depth", help="Also integrate a surface.", rich_help_panel=OUTPUT),
    report: bool = typer.Option(True, "--report/--no-report", help="Write report.html.", rich_help_panel=OUTPUT),
    scratch: Optional[Path] = typer.Option(None, "--scratch", metavar="DIR", help="Folder for the pixel stack.",
                                           rich_help_panel=OUTPUT),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bars.", rich_help_panel=OUTPUT),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Say which path ran and why.", rich_help_panel=OUTPUT),
) -> None:
    """The command's own parameters (not options of :func:`cnnps.predict`): their flags."""


# flags whose choices are a registry's names, read when the command is built
_REGISTRIES = {"method": SOLVERS, "camera_model": CAMERAS, "light_model": LIGHT_MODELS}


def _flag_of(d: Declared) -> inspect.Parameter:
    """The ``--flag`` of one declared option of :func:`cnnps.predict`: its help (with
    its default unless it is None or the help says it), its metavar (a registry's names,
    the declared one, or a Literal's choices); its text is parsed by :func:`predict`."""
    registry = _REGISTRIES.get(d.name)
    metavar = "|".join(registry) if registry is not None else d.metavar or "|".join(map(str, choices(d.type))) or None
    help_text = d.help if d.default is None or "(default" in d.help else f"{d.help} (default: {d.default})"
    path = Path in typing.get_args(d.type) or d.type is Path
    return inspect.Parameter(d.name, inspect.Parameter.KEYWORD_ONLY, annotation=Optional[Path] if path else Optional[str],
                             default=typer.Option(None, d.flag, metavar=metavar, help=help_text,
                                                  rich_help_panel=d.panel or METHOD))


class _PredictCommand:
    """Predict surface normals for a capture folder."""

    __name__ = "predict"

    @property
    def __signature__(self) -> inspect.Signature:
        """The command's parameters, then a flag per option of :func:`cnnps.predict`
        (:func:`cnnps.api.prediction_options.declared_options`), read when typer builds the
        command: a solver, camera or light model registered by then is listed."""
        from cnnps.api.prediction_options import declared_options

        capture_dir, *own = inspect.signature(_command, eval_str=True).parameters.values()
        flags = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own]
        flags += [_flag_of(d) for d in declared_options().values()]
        flags.sort(key=lambda p: PANELS.index(p.default.rich_help_panel))  # --help's groups in this order
        return inspect.Signature([capture_dir] + flags)

    @property
    def __annotations__(self) -> dict:
        return {p.name: p.annotation for p in self.__signature__.parameters.values()}

    def __call__(self, **values) -> None:
        predict(**values)


def parse_options(texts: dict) -> dict:
    """{name: value}: each option of :func:`cnnps.predict` the command line set
    (``texts``: {name: text or None}) parsed as its declared type
    (:func:`cnnps.infra.options.parse`, one line naming the flag); unset ones left out."""
    from cnnps.api.prediction_options import declared_options
    from cnnps.infra.options import parse

    declared_ = declared_options()
    return {name: parse(declared_[name].flag, text, declared_[name].type) for name, text in texts.items()
            if text is not None}


def predict(capture_dir: Path, out: Path, drop: Optional[str], mask: str, intensities: str, lights: Optional[Path],
            check: bool, depth: bool, report: bool, scratch: Optional[Path], progress: bool, verbose: bool, **options) -> None:
    """``cnnps predict``: the command's own values (:func:`_command`'s flags), and
    ``options``, :func:`cnnps.predict`'s as the command line gives them (text, or None when
    unset); the set ones are parsed (:func:`parse_options`) and
    passed on to :func:`cnnps.predict_folder`, the others left to their declared defaults."""
    from cnnps.api.prediction import predict_folder

    from cnnps.api.capture_estimates import IntensitySource, Source
    from cnnps.infra.options import parse

    result = predict_folder(capture_dir, out, drop=parse_drop(drop), mask=parse("--mask", mask, Source),
                            intensities=parse("--intensities", intensities, IntensitySource), lights_dir=lights, check=check, depth=depth,
                            report=report, scratch_dir=scratch, progress=progress, command="cnnps predict",
                            **parse_options(options))
    _report(result, capture_dir, out, verbose)


app.command("predict")(_PredictCommand())


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
    how = result["method"] + ("" if result.get("rotations") is None else f", K={result['rotations']}")
    line = f"{Path(capture_dir).name} ({how}, {result['n_images']} images, {result['pixels']} pixels)"
    if "mean_deg" in result:
        line += f": mean {result['mean_deg']:.2f} deg, median {result['median_deg']:.2f} deg"
    line += f" -> {out} ({result['seconds']:.1f} s)"
    typer.echo(line)
