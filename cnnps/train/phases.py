"""Running ``train.phases`` (:mod:`cnnps.train.phase_params`): each phase a run of the train
stage in a folder of its own, then the last phase's weights as the stage's model.

Phase ``k`` (1-based) of name ``N`` runs in ``data_dir/train/phases/kk-N/`` exactly as a
single run does in ``data_dir/train/`` (:func:`cnnps.train.loop.train`: checkpoints,
resume, precision, validation, its own ``model.pt`` and ``metrics.json``), with the params
of :meth:`cnnps.train.params.Params.phase` and as its ``init`` the weights it starts from:
the previous phase's ``model.pt`` (the first phase: ``train.init`` or random weights), or
``start.pt`` in its folder, the weighted mean of earlier phases' ``model.pt`` (float
tensors summed in the order ``start`` lists them; integer buffers from the first). A phase
of 0 steps validates that mean and writes it as its ``model.pt``.

Resuming: a finished phase writes ``phase.json`` last, holding its key (a hash of its
result-changing params, its steps, the training data's manifest hash and the SHA-256 of
the weights it started from); a rerun skips a phase whose ``phase.json`` key matches and
whose ``model.pt`` is intact, and otherwise runs it, continuing from its newest checkpoint
of the same run key. A change to one phase's settings changes its weights' hash and so
every later phase's key: they run again; earlier ones are kept. A killed chain resumed
ends with the weights of an uninterrupted one.

The stage's outputs: ``data_dir/train/model.pt`` (+ ``.sha256``), a copy of the last
phase's, and ``metrics.json``: the last phase's metrics with ``phases`` (each phase's
name, steps, samples, start, validation) and the whole chain's ``steps`` and
``samples``; ``plots/loss.csv`` and ``plots/val.csv`` hold the phases' curves one after
another (steps counted over the chain).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

from cnnps.infra.atomic import atomic_path, write_text
from cnnps.infra.hashing import stable_hash
from cnnps.models.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint, write_sha256_file
from cnnps.train.params import Params

PHASES_DIR = "phases"
PHASE_RECORD = "phase.json"
START_FILE = "start.pt"


def phase_dir(train_dir: Path, params: Params, i: int) -> Path:
    """The folder of phase ``i`` (0-based): ``train_dir/phases/kk-name``."""
    return Path(train_dir) / PHASES_DIR / f"{i + 1:02d}-{params.phases[i].name}"


def mean_weights(paths: list[Path], weights: list[float], out: Path) -> None:
    """Write the ``weights``-weighted mean of the models at ``paths`` (same network) to
    ``out`` as a model file (config and meta of the first, ``meta["start"]`` naming the
    mean)."""
    model, config, meta = load_checkpoint(paths[0])
    states = [load_checkpoint(p)[0].state_dict() for p in paths]
    mean = {}
    for name, first in states[0].items():
        if torch.is_floating_point(first):
            acc = torch.zeros_like(first, dtype=torch.float64)
            for w, state in zip(weights, states):
                acc += float(w) * state[name].to(torch.float64)
            mean[name] = acc.to(first.dtype)
        else:
            mean[name] = first
    model.load_state_dict(mean)
    meta = {**meta, "start": [[str(p), float(w)] for p, w in zip(paths, weights)]}
    save_checkpoint(out, model, config={"w": config["w"], "dropout": config.get("dropout", 0.2)}, meta=meta)
    write_sha256_file(out)


def _phase_key(p: Params, steps: int, manifest_sha256: str, init_sha: str | None) -> str:
    return stable_hash([p.result_key(), steps, manifest_sha256, init_sha])


def _done(folder: Path, key: str) -> dict | None:
    """The finished phase's record when ``folder`` holds one of ``key`` and an intact model."""
    try:
        record = json.loads((folder / PHASE_RECORD).read_text())
        if record.get("key") == key:
            read_checkpoint(folder / "model.pt")  # checks its SHA-256 file
            return record
    except Exception:  # noqa: BLE001 - missing, unreadable or damaged: run it again
        return None
    return None


def _curve(folder: Path, name: str, offset: int) -> list[str]:
    path = folder / "plots" / name
    if not path.is_file():
        return []
    rows = path.read_text().splitlines()[1:]
    return [f"{int(r.split(',')[0]) + offset},{r.split(',', 1)[1]}" for r in rows if r]


def run_phases(params: Params, data_dir: Path, info, device, *, open_data, load_init, train_one,
               validate_only, stop_after_step: int | None = None, until=None) -> dict:
    """Run ``params.phases`` in ``data_dir/train`` (the module docstring); returns the
    stage's metrics. The stage hands the pieces in: ``open_data(p)`` (training data of
    params ``p``), ``load_init(p, data)`` ((state, sha) of ``p.init``), ``train_one(p, data,
    out_dir, init_state, init_sha, stop, until)`` (one run: its metrics) and
    ``validate_only(p, data, out_dir, init_state, init_sha)`` (a phase of 0 steps).
    ``stop_after_step`` counts steps over the whole chain (tests: a kill); ``until``
    ends the chain in the phase where it first answers true (that phase ends normally,
    later ones wait for a rerun, which continues it)."""
    train_dir = Path(data_dir) / "train"
    previous: str | None = params.init
    done_at: dict[str, Path] = {}
    summary, loss, val = [], ["step,loss"], ["step,val_mean_deg,val_median_deg"]
    offset, metrics = 0, {}
    for i, ph in enumerate(params.phases):
        folder = phase_dir(train_dir, params, i)
        folder.mkdir(parents=True, exist_ok=True)
        init = previous
        if ph.start:
            init = str(folder / START_FILE)
            mean_weights([done_at[n] for n in ph.start], list(ph.start.values()), Path(init))
        p = params.phase(i, init)
        data = open_data(p)
        init_state, init_sha = load_init(p, data)
        key = _phase_key(p, ph.steps, data.manifest_sha256, init_sha)
        record = _done(folder, key)
        if record is None:
            if ph.steps == 0:
                metrics = validate_only(p, data, folder, init_state, init_sha)
            else:
                stop = None if stop_after_step is None else stop_after_step - offset
                metrics = train_one(p, data, folder, init_state, init_sha, stop if stop and stop > 0 else None, until)
            finished = ph.steps == 0 or metrics.get("steps", 0) >= ph.steps
            if not finished:  # ``until`` ended it early: a rerun continues from its checkpoint
                return {**metrics, "phase": ph.name, "phases_done": i}
            record = {"key": key, "name": ph.name, "steps": ph.steps, "metrics": metrics}
            write_text(folder / PHASE_RECORD, json.dumps(record, indent=1))
        metrics = record["metrics"]
        summary.append({"name": ph.name, "steps": ph.steps, "start": dict(ph.start) or None,
                        "samples": metrics.get("samples"), "val_mean_deg": metrics.get("val_mean_deg"),
                        "val_median_deg": metrics.get("val_median_deg")})
        loss += _curve(folder, "loss.csv", offset)
        val += _curve(folder, "val.csv", offset)
        offset += ph.steps
        done_at[ph.name] = folder / "model.pt"
        previous = str(done_at[ph.name])
    if info.is_main:
        with atomic_path(train_dir / "model.pt") as tmp:
            shutil.copyfile(done_at[params.phases[-1].name], tmp)
        write_sha256_file(train_dir / "model.pt")
        write_text(train_dir / "plots" / "loss.csv", "\n".join(loss) + "\n")
        write_text(train_dir / "plots" / "val.csv", "\n".join(val) + "\n")
        metrics = {**metrics, "steps": offset, "samples": sum(s["samples"] or 0 for s in summary), "phases": summary}
        write_text(train_dir / "metrics.json", json.dumps(metrics, indent=1))
    return metrics
