"""Resumable training state: ``checkpoints/step-NNNNNNNN.pt`` files and torch RNG states.

A training-state checkpoint is a plain ``torch.save`` dict (read back with
``weights_only=True``) holding model, optimiser, torch RNG states (of every rank under
torchrun), the step, the metric history and the run key (see
:func:`cnnps.stages.train.run_key`): a run resumes only from a checkpoint of the same
key. It is written atomically; the newest ``keep`` are kept. Not to be confused with the
model file (:mod:`cnnps.models.checkpoint`), which holds the weights only.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path

import torch

from cnnps.infra.atomic import atomic_path

CKPT_FORMAT = 1


def checkpoint_path(ckpt_dir: Path, step: int) -> Path:
    return ckpt_dir / f"step-{step:08d}.pt"


def list_checkpoints(ckpt_dir: Path) -> list[Path]:
    """Training-state checkpoints in ``ckpt_dir``, oldest first (none if it does not exist)."""
    return sorted(ckpt_dir.glob("step-*.pt"))


def save_training_state(ckpt_dir: Path, state: dict, keep: int) -> Path:
    """Write ``state`` (its ``"step"`` names the file) atomically; keep the newest ``keep``."""
    path = checkpoint_path(ckpt_dir, state["step"])
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        # through a file object: torch names the zip's root folder "archive" (given a path,
        # it names it after the temporary file), so the bytes depend only on the state
        torch.save(state, fh)
    for old in list_checkpoints(ckpt_dir)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def read_training_state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def load_training_state(ckpt_dir: Path, run_key: str | Iterable[str]) -> dict | None:
    """The newest readable checkpoint of this run key (or of any of these keys: a run whose
    precision is still to be chosen, :mod:`cnnps.train.precision`); others are deleted, each
    with one line on stderr naming it (a checkpoint of other settings, data or code version:
    say a changed default such as ``train.cpu.dropout_masks``; the run starts from its
    beginning)."""
    keys = {run_key} if isinstance(run_key, str) else set(run_key)
    for path in reversed(list_checkpoints(ckpt_dir)):
        try:
            state = read_training_state(path)
        except Exception:  # noqa: BLE001 - any failure to read: not a finished checkpoint
            path.unlink(missing_ok=True)  # unreadable: cannot be one we finished writing
            continue
        if state.get("run_key") in keys and state.get("format") == CKPT_FORMAT:
            return state
        print(f"train: {path}: a checkpoint of other settings or data (its run key differs): removed",
              file=sys.stderr)
        path.unlink(missing_ok=True)
    return None


def rng_states(device: torch.device) -> tuple:
    """(CPU RNG state, CUDA RNG state of the current device or None)."""
    return torch.get_rng_state(), torch.cuda.get_rng_state() if device.type == "cuda" else None


def set_rng_states(cpu_rng, cuda_rng, device: torch.device) -> None:
    """Restore what :func:`rng_states` returned (a None part is left as it is)."""
    if cpu_rng is not None:
        torch.set_rng_state(cpu_rng)
    if device.type == "cuda" and cuda_rng is not None:
        torch.cuda.set_rng_state(cuda_rng)
