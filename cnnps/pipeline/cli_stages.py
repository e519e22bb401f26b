"""The pipeline commands: ``cnnps stages``, ``cnnps run-stage NAME``, ``cnnps demo``.

Every command validates the parameters of *all* stages before any work starts, so a
typo in the ``eval`` section fails in seconds, not after an hour of rendering.

One writer per data folder: ``run-stage`` and ``demo`` hold the data folder's lock
(:mod:`cnnps.pipeline.lock`) while they write, so a second run on the same folder stops at
once with one line naming the first (its command, PID, host and start time). ``demo``
holds it for the whole pipeline and hands it to the ``cnnps run-stage`` processes its
``dvc repro`` starts; under torchrun only rank 0 takes it. ``stages`` only reads.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import typer

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.pipeline.app import app
from cnnps.stages import STAGES

PARAMS_HELP = "Params file (default: params.yaml in the current folder)."
PRESET_HELP = (
    "Use cnnps/presets/NAME.yaml instead of params.yaml (demo, full, cpu-train, ...; `cnnps stages` lists them), "
    "or a params file by its path (docs/recipes/cpu-train-v4.yaml)."
)
DATA_HELP = "Folder for stage outputs (default: data_dir from the params file, else data)."


EXECUTOR_HELP = "Run per-scene jobs with 'local' (process pool) or 'ray' (overrides params `executor.kind`)."
ADDRESS_HELP = "Ray cluster address: auto, host:port or ray://host:port (overrides params `executor.address`)."


def _config(
    params: Optional[Path],
    preset: Optional[str],
    data_dir: Optional[Path],
    executor: Optional[str] = None,
    address: Optional[str] = None,
):
    import dataclasses

    from cnnps.pipeline import config as cfg

    if params is not None and preset is not None:
        raise ConfigError("give either --params or --preset, not both")
    path = cfg.preset_path(preset) if preset is not None else params
    conf = cfg.load_config(path, data_dir=data_dir)
    changes = {k: v for k, v in (("kind", executor), ("address", address)) if v is not None}
    if changes:
        if address is not None and changes.get("kind", conf.executor.kind) != "ray":
            raise ConfigError("--address applies to --executor ray")
        conf = dataclasses.replace(conf, executor=dataclasses.replace(conf.executor, **changes))
    return conf


def _data_lock(data_dir: Path, command: str):
    """The data folder's lock (:class:`cnnps.pipeline.lock.DataFolderLock`) for ``command``;
    a no-op in the ranks > 0 of a torchrun job (rank 0 holds it; the others write nothing)."""
    from cnnps.pipeline.lock import DataFolderLock

    if int(os.environ.get("WORLD_SIZE", "1") or 1) > 1 and os.environ.get("RANK", "0") not in ("", "0"):
        return contextlib.nullcontext()
    return DataFolderLock(data_dir, command)


def _fmt_time(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


@app.command("stages")
def stages_cmd(
    params: Optional[Path] = typer.Option(None, "--params", help=PARAMS_HELP),
    preset: Optional[str] = typer.Option(None, "--preset", help=PRESET_HELP),
    data_dir: Optional[Path] = typer.Option(None, "--data-dir", help=DATA_HELP),
    check: bool = typer.Option(False, "--check", help="Validate every stage's params and print them."),
) -> None:
    """List the pipeline stages in order (and the presets); --check validates the params."""
    from cnnps.pipeline import config as cfg

    if not check:
        typer.echo("stages (in order): " + " -> ".join(cfg.STAGES))
        typer.echo("presets: " + (", ".join(cfg.list_presets()) or "(none)"))
        return
    import yaml

    conf = _config(params, preset, data_dir)
    all_params = cfg.load_all(conf)
    out = {name: cfg.params_to_dict(p) for name, p in all_params.items()}
    typer.echo(yaml.safe_dump(out, sort_keys=False).rstrip())
    typer.echo(f"# {conf.where}: all {len(all_params)} stages valid; data in {conf.data_dir}")


@app.command("run-stage")
def run_stage_cmd(
    name: str = typer.Argument(..., help=f"Stage: {', '.join(STAGES[:-1])} or {STAGES[-1]}."),
    params: Optional[Path] = typer.Option(None, "--params", help=PARAMS_HELP),
    preset: Optional[str] = typer.Option(None, "--preset", help=PRESET_HELP),
    data_dir: Optional[Path] = typer.Option(None, "--data-dir", help=DATA_HELP),
    executor: Optional[str] = typer.Option(None, "--executor", help=EXECUTOR_HELP),
    address: Optional[str] = typer.Option(None, "--address", help=ADDRESS_HELP),
) -> None:
    """Run one pipeline stage (what each `dvc.yaml` stage calls)."""
    from cnnps.pipeline import config as cfg

    cfg.check_stage_name(name)
    conf = _config(params, preset, data_dir, executor, address)
    all_params = cfg.load_all(conf)  # every stage, before any work
    t0 = time.perf_counter()
    with _data_lock(conf.data_dir, f"cnnps run-stage {name}"):  # one writer per data folder
        cfg.run_stage(name, conf, all_params)
    typer.echo(f"cnnps: stage {name} done in {_fmt_time(time.perf_counter() - t0)} ({conf.data_dir})", err=True)


def _dvc_usable(root: Path) -> bool:
    return (
        (root / "dvc.yaml").is_file()
        and (root / ".dvc").is_dir()
        and (root / ".git").exists()
        and importlib.util.find_spec("dvc") is not None
    )


def _run_dvc_repro(root: Path, env: dict[str, str] | None = None) -> None:
    env = dict(os.environ if env is None else env)
    # `cnnps run-stage` in dvc.yaml must resolve to this installation's command.
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env.setdefault("DVC_NO_ANALYTICS", "1")
    cmd = [sys.executable, "-m", "dvc", "repro"]
    typer.echo(f"cnnps: running {' '.join(cmd[2:])} in {root}", err=True)
    rc = subprocess.call(cmd, cwd=root, env=env)
    if rc != 0:
        raise CnnpsError(f"dvc repro failed (exit {rc}); see the output above")


@app.command("demo")
def demo_cmd(
    params: Optional[Path] = typer.Option(None, "--params", help=PARAMS_HELP),
    preset: Optional[str] = typer.Option(None, "--preset", help=PRESET_HELP),
    data_dir: Optional[Path] = typer.Option(None, "--data-dir", help=DATA_HELP),
    use_dvc: bool = typer.Option(True, "--dvc/--no-dvc", help="Use `dvc repro` when this is a DVC repository."),
) -> None:
    """Run the whole pipeline (meshes -> ... -> eval), then print the evaluation table.

    With the default params.yaml in a DVC repository this is `dvc repro` (only what
    changed re-runs); otherwise the stages run one after another in this process
    (each stage still skips scenes whose inputs did not change).
    """
    from cnnps.pipeline import config as cfg

    conf = _config(params, preset, data_dir)
    all_params = cfg.load_all(conf)
    root = Path.cwd()
    default_setup = (
        params is None or params.resolve() == (root / cfg.DEFAULT_PARAMS).resolve()
    ) and preset is None and conf.data_dir.resolve() == (root / cfg.DEFAULT_DATA_DIR).resolve()
    t0 = time.perf_counter()
    with _data_lock(conf.data_dir, "cnnps demo") as lock:  # the whole pipeline, one writer
        if use_dvc and default_setup and _dvc_usable(root):
            # the `cnnps run-stage` processes of dvc repro inherit the lock through their environment
            _run_dvc_repro(root, lock.child_env() if lock is not None else None)
        else:
            for name in cfg.STAGES:
                typer.echo(f"cnnps: stage {name} ...", err=True)
                t1 = time.perf_counter()
                cfg.run_stage(name, conf, all_params)
                typer.echo(f"cnnps: stage {name} done in {_fmt_time(time.perf_counter() - t1)}", err=True)
    elapsed = time.perf_counter() - t0

    metrics_path = conf.data_dir / "eval" / "metrics.json"
    report_path = conf.data_dir / "eval" / "report.md"
    if not metrics_path.is_file():
        raise CnnpsError(f"{metrics_path}: the eval stage wrote no metrics")
    from cnnps.stages.eval_report import format_table
    from cnnps.stages.eval_scoring import score_shipped

    metrics = json.loads(metrics_path.read_text())
    typer.echo("cnnps: scoring the shipped model on the same test captures ...", err=True)
    shipped = score_shipped(metrics, all_params["eval"])  # the demo's short model next to the real one
    typer.echo(format_table(metrics, shipped))
    typer.echo(f"\nreport: {report_path}")
    typer.echo(f"pipeline finished in {_fmt_time(elapsed)}")
