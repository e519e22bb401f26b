"""A run's checkpoints and validation log in either layout: one run of the train stage
(``data/train/checkpoints``, ``data/train/plots/val.csv``) or a chain of ``train.phases``
(:mod:`cnnps.train.phases`: phase ``k`` of name ``N`` in ``data/train/phases/kk-N/``, its
steps counted from 0). Steps here are the chain's: a phase's step plus the steps of the
phases before it (for a run without phases, the step itself).

``params`` is the run's params.yaml as a dict. This module loads no torch.
"""

from __future__ import annotations

from pathlib import Path

PHASES_DIR = "phases"  # cnnps.train.phases.PHASES_DIR (that module loads torch)


def phases(params: dict) -> list[dict]:
    """The run's ``train.phases`` (each ``{name, steps, set, start}``); [] for a run without."""
    return list((params.get("train") or {}).get("phases") or [])


def train_folders(data: Path, params: dict) -> list[tuple[int, Path]]:
    """(steps before it, folder) of each phase in order; a run without phases: its one
    folder ``data/train`` at 0."""
    train = Path(data) / "train"
    chain = phases(params)
    if not chain:
        return [(0, train)]
    out, before = [], 0
    for i, ph in enumerate(chain):
        out.append((before, train / PHASES_DIR / f"{i + 1:02d}-{ph['name']}"))
        before += int(ph["steps"])
    return out


def checkpoints(data: Path, params: dict) -> list[tuple[int, Path]]:
    """The run's ``step-NNNNNNNN.pt`` checkpoints as (chain step, path), in chain order."""
    out = []
    for before, folder in train_folders(data, params):
        for p in sorted((folder / "checkpoints").glob("step-*.pt")):
            out.append((before + int(p.stem.split("-")[1]), p))
    return sorted(out, key=lambda c: c[0])


def newest(data: Path, params: dict) -> tuple[int, Path] | None:
    """The newest checkpoint (chain step, path): the chain's last; None before the first."""
    cks = checkpoints(data, params)
    return cks[-1] if cks else None


def planned_steps(params: dict) -> int:
    """The steps the run plans: its phases' steps summed, else ``train.max_steps`` (0 if unset)."""
    chain = phases(params)
    if chain:
        return sum(int(ph["steps"]) for ph in chain)
    return int((params.get("train") or {}).get("max_steps") or 0)


def val_rows(data: Path, params: dict) -> list[tuple[int, list[str]]] | None:
    """The train stage's validation log as (chain step, the row's other columns as
    written: mean, median): each phase's ``plots/val.csv`` offset by the steps before it
    (a run without phases: ``data/train/plots/val.csv``); None while there is no such file."""
    out, found = [], False
    for before, folder in train_folders(data, params):
        src = folder / "plots" / "val.csv"
        if not src.is_file():
            continue
        found = True
        for ln in src.read_text().splitlines()[1:]:
            if ln.strip():
                step, *rest = ln.split(",")
                out.append((int(float(step)) + before, rest))
    return out if found else None


def check_one_network(params: dict) -> None:
    """SystemExit when a phase changes the network (a ``model.*`` key in its ``set``):
    a checkpoint's weights are exported with the base ``train.model`` options."""
    for ph in phases(params):
        keys = [k for k in (ph.get("set") or {}) if k == "model" or str(k).startswith("model.")]
        if keys:
            raise SystemExit(f"train.phases: phase {ph['name']!r} sets {', '.join(keys)}; exporting its checkpoints "
                             "needs every phase to train the base train.model network")
