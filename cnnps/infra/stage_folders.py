"""Per-item output folders of the stages: their marker files and the pruning of stale ones.

A stage writes one folder per planned item (a view, a scene, a test capture), each
holding a JSON marker (``view.json``, ``material.json``, ``scene.json``, ...) with its
content key. :func:`prune_stale` removes the folders of items that are no longer
planned, touching only folders that carry one of the stage's markers (never a user's
folder that happens to sit there).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Iterable

# build folders of cnnps.infra.atomic.atomic_dir (and the render stage's): ``.{name}.XXXXXXXX.tmp``
_BUILD_FOLDER = re.compile(r"^\..+\.tmp$")


def read_json(path: str | Path) -> dict | None:
    """The JSON object in ``path``, or None when it is missing or not valid JSON."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def prune_stale(root: str | Path, wanted: Iterable[str], markers: Iterable[str], *, build_folders: bool = False) -> list[Path]:
    """Delete the folders under ``root`` that are not in ``wanted`` but hold one of ``markers``.

    ``build_folders``: also delete the hidden ``.<name>.XXXXXXXX.tmp`` build folders that
    killed atomic writes left (call it only while no job of the stage writes there).
    Returns the folders deleted; a missing ``root`` holds nothing to prune.
    """
    root = Path(root)
    if not root.is_dir():
        return []
    wanted = set(wanted)
    markers = tuple(markers)
    removed = []
    for p in sorted(root.iterdir()):
        if not p.is_dir() or p.is_symlink() or p.name in wanted:
            continue
        if any((p / m).is_file() for m in markers) or (build_folders and _BUILD_FOLDER.match(p.name)):
            shutil.rmtree(p)
            removed.append(p)
    return removed
