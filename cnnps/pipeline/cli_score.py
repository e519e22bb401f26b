"""The `cnnps score` command: a weights file's angular error on capture folders with
ground truth, least squares beside it, and the mean over the captures.

Scoring is the eval stage's (:func:`cnnps.stages.evaluate.score_real`): the same numbers
the stage records for ``eval.real_captures`` / ``eval.real_subsets`` in
``data/eval/metrics.json``, each column's normals computed as ``cnnps predict`` computes
them (:func:`cnnps.api.prediction_steps.capture_normals_by`: the solver registry, the camera and
light model registries, the pixel stack and the tile loop; a solver registered in
:mod:`cnnps.api.solvers` is one more column), with ``cnnps predict``'s default options unless told
otherwise (K=10, saturated observations left out, the Lambertian fill below 50 images,
precision auto), and under the DiLiGenT benchmark's rule
(:data:`cnnps.io.capture.DILIGENT_RULES`: a folder named bearPNG is scored without its
first 20 images, and its subsets are drawn from the other 76).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from cnnps.infra.errors import ConfigError, InputError
from cnnps.api.prediction_options import METHOD, OUTPUT
from cnnps.pipeline.app import app

SCORING = "Scoring"

SHIPPED = "shipped"  # MODEL: the weights cnnps ships (cnnps/models/weights/cnnps_default.pt)
OUT_FORMAT = 1  # the --out file's layout version


def _default(name: str):
    """The default of :func:`cnnps.predict`'s option ``name``, as declared
    (:func:`cnnps.api.prediction_options.option_default`, the one place it lives)."""
    from cnnps.api.prediction_options import option_default

    return option_default(name)


def parse_counts(flag: str, text: Optional[str], minimum: int) -> tuple[int, ...]:
    """'10,6' (or '10 6') -> (10, 6); None or '' -> (); each an integer >= ``minimum``."""
    from typing import Annotated

    from cnnps.infra.options import Range, parse

    if text is None:
        return ()
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    values = tuple(parse(flag, p, Annotated[int, Range(ge=minimum)]) for p in parts)
    if len(set(values)) != len(values):
        raise ConfigError(f"{flag}: a number given twice in {text!r}")
    return values


def check_capture_dir(path: Path) -> None:
    """One line (InputError) when ``path`` is not a capture folder with ground truth."""
    from cnnps.io.capture import (
        FILENAMES_FILE,
        GROUND_TRUTH_FILES,
        ground_truth_file,
        is_capture_folder,
    )

    if not path.exists():
        raise InputError(path, "capture folder not found")
    if not path.is_dir():
        raise InputError(path, "not a folder")
    if not is_capture_folder(path):
        raise InputError(path, f"not a capture folder (no {FILENAMES_FILE} and no images)")
    if ground_truth_file(path) is None:
        raise InputError(path, f"no ground truth ({' or '.join(GROUND_TRUTH_FILES)}): nothing to score")


def _model(model: str) -> Path:
    if model == SHIPPED:
        from cnnps.models.shipped import shipped_model_path

        return shipped_model_path()  # its SHA-256 checked against the provenance beside it
    path = Path(model)
    if not path.is_file():
        raise InputError(path, "model file not found" if not path.exists() else "not a file")
    from cnnps.models.shipped import verify_if_shipped

    return verify_if_shipped(path)  # a shipped file named by its path (cnnps_v5.pt) is checked too


@app.command("score")
def score(
    model: str = typer.Argument(..., metavar="MODEL", help=f"Weights (.pt), or '{SHIPPED}'."),
    capture_dirs: list[Path] = typer.Argument(..., metavar="CAPTURE_DIR...", help="Captures with ground truth (docs/results.md)."),
    rotations: Optional[str] = typer.Option(None, "--rotations", metavar="K[,K...]", rich_help_panel=SCORING, help=f"Test-time rotations, a column each. (default: {_default('rotations')})"),
    subsets: Optional[str] = typer.Option(None, "--subsets", metavar="N[,N...]", rich_help_panel=SCORING, help="Also from N of the images (seeded)."),
    exclude_from_mean: Optional[str] = typer.Option(None, "--exclude-from-mean", metavar="NAME[,...]", rich_help_panel=SCORING, help="Shown, left out of the means."),
    seed: int = typer.Option(0, "--seed", rich_help_panel=SCORING, help="Seed of --subsets and --pixels."),
    pixels: int = typer.Option(0, "--pixels", metavar="N", rich_help_panel=SCORING, help="A seeded sample of N mask pixels (0: all)."),
    device: Optional[str] = typer.Option(None, "--device", metavar="auto|cpu|cuda", rich_help_panel=METHOD, help=f"Where the network runs. (default: {_default('device')})"),
    precision: Optional[str] = typer.Option(None, "--precision", metavar="auto|fp32|bf16", rich_help_panel=METHOD, help=f"As cnnps predict. (default: {_default('precision')})"),
    saturated: Optional[str] = typer.Option(None, "--saturated", metavar="exclude|keep", rich_help_panel=METHOD, help=f"As cnnps predict. (default: {_default('saturated')})"),
    sparse_fill: Optional[str] = typer.Option(None, "--sparse-fill", metavar="auto|on|off", rich_help_panel=METHOD, help=f"As cnnps predict. (default: {_default('sparse_fill')})"),
    batch_size: Optional[str] = typer.Option(None, "--batch-size", metavar="N", rich_help_panel=METHOD, help="Maps per network batch."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", metavar="FILE.json", rich_help_panel=OUTPUT, help="Also write the numbers there."),
) -> None:
    """Score a weights file on capture folders with ground truth, least squares beside it.

    Prints per capture (and subset) the mean / median angular error of CNN-PS and of least squares on the same pixels, then the mean over the captures (without those of --exclude-from-mean) per image count. The eval stage records the same numbers for eval.real_captures. Example: cnnps score model.pt ballPNG cowPNG pot1PNG --subsets 10,6 --exclude-from-mean ballPNG --out score.json
    """
    import time

    from cnnps.api.prediction import Precision, Saturated
    from cnnps.infra.machine import Device
    from cnnps.infra.options import Count, parse
    from cnnps.io.capture import MIN_IMAGES
    from cnnps.ps.sparse_fill import SparseFill
    from cnnps.stages import evaluate as ev
    from cnnps.stages.eval_report import format_table

    t0 = time.perf_counter()
    ks = parse_counts("--rotations", rotations, 1) or (int(_default("rotations")),)
    ns = parse_counts("--subsets", subsets, MIN_IMAGES)
    options = {
        "device": parse("--device", device or _default("device"), Device),
        "precision": parse("--precision", precision or _default("precision"), Precision),
        "saturated": parse("--saturated", saturated or _default("saturated"), Saturated),
        "sparse_fill": parse("--sparse-fill", sparse_fill or _default("sparse_fill"), SparseFill),
        "batch_size": 0 if batch_size is None else parse("--batch-size", batch_size, Count),
    }
    for flag, value in (("--seed", seed), ("--pixels", pixels)):
        if value < 0:
            raise ConfigError(f"{flag} must be >= 0, got {value}")
    if out is not None and out.is_dir():
        raise InputError(out, "--out is a folder; give a file name")
    path = _model(model)
    names = []
    for d in capture_dirs:
        check_capture_dir(d)
        names.append(d.name)
    for name in names:
        if names.count(name) > 1:
            raise ConfigError(f"two capture folders are named {name!r}; captures are named by their folders")
    excluded = tuple(x for x in (exclude_from_mean or "").replace(" ", ",").split(",") if x)
    for name in excluded:
        if name not in names:
            raise ConfigError(f"--exclude-from-mean: {name!r} is not the folder name of a given capture "
                              f"({', '.join(names)})")

    params = ev.Params(synthetic=False, real_captures=tuple(str(d) for d in capture_dirs), real_subsets=ns,
                       real_exclude_from_mean=excluded, real_pixels=pixels, rotations=ks, model=str(path), seed=seed, **options)
    metrics = ev.score_real(params)

    from cnnps.infra.hashing import file_sha256

    record = {
        "format": OUT_FORMAT,
        "model": str(path),
        "model_sha256": file_sha256(path),
        "options": {"rotations": list(ks), "subsets": list(ns), "seed": seed, "pixels": pixels, **options,
                    "precision_used": metrics["precision"]},
        "methods": metrics["methods"],
        "captures": metrics["captures"],
        "summary_real": metrics["summary_real"],
        "summary_real_subsets": metrics["summary_real_subsets"],
        "real_exclude_from_mean": metrics["real_exclude_from_mean"],
        "seconds": round(time.perf_counter() - t0, 2),
    }
    typer.echo(format_table(metrics))
    k_text = ", ".join(str(k) for k in ks)
    typer.echo(f"\n{path.name} (sha256 {record['model_sha256'][:8]}), K={k_text}, {metrics['precision']}, "
               f"saturated {options['saturated']}"
               + (f", a sample of {pixels} pixels per capture" if pixels else "") + f"; {record['seconds']:.1f} s")
    if out is not None:
        import json

        from cnnps.infra.atomic import write_text

        out.parent.mkdir(parents=True, exist_ok=True)
        write_text(out, json.dumps(record, indent=2) + "\n")
        typer.echo(f"-> {out}")
