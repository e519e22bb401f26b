"""The weights a run's folder in git (``tools/runs/NAME/``) keeps: the newest weights
themselves (``intermediate.pt``, float16) while the run is in progress, and only their
record (``intermediate.json``) once it is finished, so the tracked tree holds no finished
run's weights. Weights that would take the tracked tree over its limit
(:mod:`tools.tree_size`) stay outside it even while the run is in progress: the record
alone, with ``kept``.

``intermediate.json``::

    {"file": "intermediate.pt", "bytes": 5314093, "sha256": "adbb2015...",
     "steps": 24000,            # the steps the weights have made
     "planned_steps": 24000,    # the run's plan
     "finished": true,
     "kept": "/work/runs/NAME/intermediate.pt",      # where the bytes were written, outside the tree
     "git": {"commit": "51541c2...", "path": "tools/runs/NAME/intermediate.pt"}}  # or: a commit that holds them

A run is finished when its plan is spent (``steps >= planned_steps``) or when it ended on
purpose before that (``long_run.py save --final``). ``kept`` and ``git`` are there when
known. Whatever reads a folder's weights back (:func:`carried_weights`) checks a file
against the record's size and SHA-256, so weights put back by hand (``git show
COMMIT:PATH > PATH``) are verified, and stops with one line naming the file and how to
get it back when the folder has the record alone.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

WEIGHTS = "intermediate.pt"
RECORD = "intermediate.json"


def weights_record(weights: Path, *, steps: int, planned: int, finished: bool, **where) -> dict:
    """The record of the weights file ``weights``: its size and SHA-256, the steps it has
    made of the ``planned`` ones, whether the run is finished, and ``where`` (``kept``,
    ``git``) when given."""
    from cnnps.infra.hashing import file_record

    return {"file": WEIGHTS, **file_record(weights), "steps": int(steps), "planned_steps": int(planned),
            "finished": bool(finished), **where}


def write_record(folder: Path, record: dict) -> Path:
    from cnnps.infra.atomic import write_text

    folder.mkdir(parents=True, exist_ok=True)
    out = folder / RECORD
    write_text(out, json.dumps(record, indent=1) + "\n")
    return out


def read_record(folder: Path) -> dict | None:
    """``folder``'s ``intermediate.json``, or None when it has none."""
    path = Path(folder) / RECORD
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
        if not isinstance(rec, dict) or len(str(rec["sha256"])) != 64:
            raise ValueError
        int(rec["steps"])
    except (ValueError, KeyError, TypeError):
        raise SystemExit(f"{path}: not a weights record (expected {{\"sha256\", \"bytes\", \"steps\", ...}})") from None
    return rec


def carry(folder: Path, weights: Path, *, steps: int, planned: int, finished: bool,
          room: int | None = None) -> Path | None:
    """Put a run's newest weights (the file ``weights``, outside the tree) into its folder
    in git: while the run is in progress, the file as ``intermediate.pt`` (replacing the
    one there) with its record; once finished, the record alone (``kept``: ``weights``),
    and the folder's ``intermediate.pt`` goes. ``room``: the bytes git's tracked tree may
    still grow by (:func:`tools.tree_size.room`, counting the folder's present weights as
    gone); weights bigger than that stay where they are, as for a finished run, with a
    record that says the run is in progress. Returns the weights file in the folder, or
    None when the weights stay outside it."""
    folder = Path(folder)
    weights = Path(weights).resolve()
    dst = folder / WEIGHTS
    no_room = room is not None and weights != dst.resolve() and weights.stat().st_size > room
    if finished or no_room:  # the record alone, naming where the file is
        write_record(folder, weights_record(weights, steps=steps, planned=planned, finished=finished, kept=str(weights)))
        dst.unlink(missing_ok=True)
        return None
    record = weights_record(weights, steps=steps, planned=planned, finished=False)
    folder.mkdir(parents=True, exist_ok=True)
    if weights != dst.resolve():
        tmp = folder / f".{WEIGHTS}.tmp"
        shutil.copyfile(weights, tmp)
        os.replace(tmp, dst)
    write_record(folder, record)
    return dst


def recovery(record: dict, path: Path) -> str:
    """How to get the weights of ``record`` back to ``path``, in words (one line)."""
    git = record.get("git") or {}
    if git.get("commit") and git.get("path"):
        return (f"get it back from git with `git show {git['commit']}:{git['path']} > {git['path']}` "
                "(in the repository's root)")
    if record.get("kept"):
        return f"it was written to {record['kept']}: copy that file to {path}"
    return "no copy of it is recorded"


def carried_weights(folder: Path) -> Path | None:
    """The weights file of a run's folder in git to restore from, checked against the
    folder's record: None when the folder has neither; SystemExit (one line naming the
    file and how to get it back) when the record is there and the file is not, or when the
    file is not the one recorded."""
    folder = Path(folder)
    path, record = folder / WEIGHTS, read_record(folder)
    if record is None:
        return path if path.is_file() else None
    sha = record["sha256"]
    if not path.is_file():
        raise SystemExit(f"{path}: not here; {folder / RECORD} keeps only its SHA-256 ({sha[:12]}…, step "
                         f"{record['steps']}): {recovery(record, path)}")
    from cnnps.infra.hashing import check_file_record

    why = check_file_record(path, record)
    if why:
        raise SystemExit(f"{path}: not the weights {RECORD} records (SHA-256 {sha[:12]}…): {why}; "
                         f"{recovery(record, path)}")
    return path
