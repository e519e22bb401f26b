"""Reading a rendered capture folder: whether it is finished and whether its files match
the checksums its ``scene.json`` records. No renderer and no Blender: what the extract
stage and every other reader of a render import; the images, lights, mask and normals
themselves are read by :mod:`cnnps.io.capture` like any capture folder.

A folder is finished when its ``scene.json`` (written last) holds the key and every image
it lists exists (:func:`is_complete`). ``scene.json`` records every other file of the
folder (``files``: name -> ``{"bytes", "sha256"}``) and a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`, indent :data:`cnnps.io.capture.SCENE_INDENT`,
leaving out the two timing fields :data:`SCENE_TIMINGS`, so it is the same for every run
that writes the same folder); :func:`folder_problems` lists what does not match (a
truncated, NaN-filled or byte-flipped image, or a ``scene.json`` edited by hand). A
``scene.json`` without these entries is complete when every file exists.

A folder being rendered holds :data:`PENDING_FILE` (its key) until ``scene.json``
replaces it; a folder holding either is a render folder (:data:`RENDER_MARKERS`, ours to
empty).

Example::

    if is_complete(folder, key):            # one read of every file
        capture = load_capture(folder)
    for path, problem in folder_problems(folder):
        print(f"{path}: {problem}")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.infra.hashing import check_file_record, json_checksum_ok
from cnnps.infra.stage_folders import read_json
from cnnps.io.capture import DEPTH_GT_FILE, NORMAL_GT_FILE, SCENE_FILE, SCENE_INDENT

# scene.json is written by cnnps.io.capture.write_scene (indent SCENE_INDENT): its checksum hashes that form
SCENE_TIMINGS = ("render_seconds", "images_rendered_last_run")  # not in its checksum: they vary between runs
PENDING_FILE = ".pending.json"  # the key of a folder being rendered; SCENE_FILE replaces it at the end
RENDER_MARKERS = (SCENE_FILE, PENDING_FILE)  # a folder holding one is a render folder (ours to empty)


def is_complete(out: Path, key: str, verify: bool = True) -> bool:
    """Whether ``out`` is a finished capture of ``key``: its ``scene.json`` holds the key
    and every image it lists exists (no Blender needed to tell) and, with ``verify``, the
    folder matches the checksums ``scene.json`` records (:func:`folder_problems`: one
    read of every file)."""
    meta = read_json(out / SCENE_FILE)
    if not meta or meta.get("key") != key:
        return False
    names = meta.get("filenames") or []
    if not (bool(names) and all((out / n).is_file() for n in names) and (out / NORMAL_GT_FILE).is_file()):
        return False
    return not verify or not folder_problems(out, meta)


def folder_problems(out: Path, meta: dict | None = None) -> list[tuple[Path, str]]:
    """``(file, problem)`` for every file of the finished capture ``out`` that does not
    match what its ``scene.json`` (``meta``: read when None) records: the record's own
    checksum first (a ``scene.json`` edited by hand cannot vouch for anything, so it is
    the only problem then), then each file's size and SHA-256. Empty when all match, or
    when ``scene.json`` predates checksums (nothing to check against)."""
    out = Path(out)
    if meta is None:
        meta = read_json(out / SCENE_FILE) or {}
    ok = json_checksum_ok(meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    if ok is False:
        return [(out / SCENE_FILE, "edited by hand or damaged: its content does not match its checksum")]
    problems = []
    for name, record in (meta.get("files") or {}).items():
        problem = check_file_record(out / name, record)
        if problem is not None:
            problems.append((out / name, problem))
    return problems


def decode_problem(path: Path) -> str | None:
    """Why a file of a capture folder without a checksum record cannot be kept (not
    readable by its decoder, or NaN / infinite values; the depth map may hold NaN off the
    object), or None when it reads as a whole."""
    from cnnps.io.images import read_image_raw

    try:
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
            if path.name == DEPTH_GT_FILE:
                if not np.issubdtype(arr.dtype, np.number) or arr.ndim != 2 or np.isinf(arr).any():
                    return "not an H x W depth map (finite, or NaN off the object)"
            elif not np.issubdtype(arr.dtype, np.number) or arr.ndim != 3 or not np.isfinite(arr).all():
                return "not a finite H x W x 3 normal map"
        else:
            arr = read_image_raw(path)
            if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
                return "holds NaN or infinite pixels"
    except InputError as exc:
        return exc.problem
    except Exception as exc:  # noqa: BLE001 - any decoder failure: the file is damaged
        return f"unreadable ({type(exc).__name__})"
    return None


def is_render_folder(path: Path) -> bool:
    """Whether ``path`` is a capture folder :func:`cnnps.synth.capture_render.render_into` wrote
    (finished or not)."""
    return path.is_dir() and any((path / n).is_file() for n in RENDER_MARKERS)
