"""The resume and checksum state machine of a rendered capture folder: the steps
:func:`cnnps.synth.capture_render.render_into` takes so that a folder rendered light by
light survives a kill, a full disk or damaged files, and a rerun renders only what is
missing. Every camera and light model alike; no Blender here.

The states of ``out`` for a key K, and what a run does in each:

- finished for K (``scene.json`` holds K, every file matches its record): nothing
  (:func:`finished`, which also removes a ``.pending.json`` a kill left beside it);
- unfinished for K (``.pending.json`` holds K, light files intact), or finished for K with
  damaged images: resumed (:func:`prepare_folder`): the temporary files a kill left are
  deleted (:func:`remove_temp_files`), damaged images (or the mask, normals and depth) are
  deleted, and only the missing images are rendered, with the lights read back from the
  folder and the same seeds, so the folder ends with the bytes it had;
- anything else of ours (another key, damaged light files or intrinsics, an untrustworthy
  ``scene.json``): started afresh (:func:`_start_folder`): the folder appears (built under
  a temporary name, then renamed) already holding ``.pending.json`` (K) and the light files
  (and the intrinsics), so the lights are fixed FIRST; a finished capture of another key
  waits at :func:`previous_path` until the new one is complete (:func:`restore_previous`
  puts it back after a failure, :func:`take_back_previous` when the key goes back);
- not ours (a non-empty folder without ``.pending.json`` or ``scene.json``): refused
  (:func:`check_not_foreign`, InputError), never emptied; an existing empty one is filled
  in place.

Each image is written atomically (temp name, rename); ``scene.json`` with its checksum is
written LAST as the completion marker (:func:`write_scene_json`). Files of a killed run
(no record yet) are checked by decoding (readable, finite) before they are kept. The
images of a folder depend only on its key and seeds (Cycles is deterministic per seed), so
a retried or duplicated job resumes or rewrites the same pixels. What a finished folder is
and how it is checked: :mod:`cnnps.synth.render.rendered_folder`.

Example (what render_into does around the rendering)::

    if not finished(out, key):
        check_not_foreign(out)
        lights = prepare_folder(out, key, scene, light_record)   # (m, 3) as written
        ...                                                       # render the missing images
        write_scene_json(out, record)
"""

from __future__ import annotations

import glob
import json
import re
import shutil
from pathlib import Path

import numpy as np

from cnnps.infra.atomic import publish_mode, write_text
from cnnps.infra.errors import InputError
from cnnps.infra.hashing import add_json_checksum, check_file_record, json_checksum_ok
from cnnps.infra.stage_folders import read_json
from cnnps.io.capture import (
    SCENE_FILE,
    SCENE_INDENT,
    Capture,
    read_light_directions,
    write_capture_files,
    write_scene,
)
from cnnps.io.capture.files import read_light_positions
from cnnps.synth.render.rendered_folder import (
    PENDING_FILE,
    SCENE_TIMINGS,
    decode_problem,
    is_complete,
    is_render_folder,
)
from cnnps.synth.render.scene import GEOMETRY_FILES, Scene


def finished(out: Path, key: str) -> bool:
    """:func:`~cnnps.synth.render.rendered_folder.is_complete`, and a finished folder's
    leftover ``.pending.json`` removed (a kill between writing ``scene.json`` and removing
    the marker leaves both)."""
    if not is_complete(out, key):
        return False
    (out / PENDING_FILE).unlink(missing_ok=True)
    return True


def _drop_damaged(out: Path, names: list[str], records: dict, geometry: tuple[str, ...] = GEOMETRY_FILES) -> list[str]:
    """Delete the images and ``geometry`` files (mask, normals, depth) of ``out`` that do
    not match their record (``records``: name -> {"bytes", "sha256"}) or, without one, do
    not decode as whole finite files; they are rendered again. Returns the names deleted."""
    dropped = []
    for name in list(names) + list(geometry):
        path = out / name
        if not path.is_file():
            continue
        record = records.get(name)
        problem = check_file_record(path, record) if record else decode_problem(path)
        if problem is not None:
            path.unlink()
            dropped.append(name)
    if any(n in dropped for n in geometry):  # written together: redo them all
        for n in geometry:
            (out / n).unlink(missing_ok=True)
    return dropped


def prepare_folder(out: Path, key: str, scene: Scene, record: Capture) -> np.ndarray:
    """Make ``out`` ready for the images still missing; the lights to render with
    (directions, or capture-frame positions of point lights).

    A folder of this ``key`` (unfinished, or finished with damaged files) whose light files
    are intact is resumed with the lights it holds (:func:`_reopen`); any other is started
    afresh with ``record`` (:func:`_start_folder`), a finished capture of another key set
    aside until the new one is complete."""
    records = _resume_records(out, key, scene)
    written = None if records is None else _written_lights(out, len(scene.lights), scene.point_lights)
    if written is None:
        _set_aside(out)
        return _start_folder(out, key, record)
    _reopen(out, key, record.filenames, records, scene.geometry_files())
    return written


def _resume_records(out: Path, key: str, scene: Scene) -> dict | None:
    """The file records ``out`` is resumed with (``{}`` when its ``scene.json`` has none or
    cannot be trusted), or None when it cannot be resumed: a finished folder only when its
    ``scene.json`` is the one we wrote for ``key`` and its light files are intact, an
    unfinished one when its ``.pending.json`` holds ``key``."""
    pending = read_json(out / PENDING_FILE) or {}
    done_meta = read_json(out / SCENE_FILE) or {}
    done_ok = (done_meta.get("key") == key
               and json_checksum_ok(done_meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS) is not False)
    records = (done_meta.get("files") or {}) if done_ok else {}
    light_files = scene.light_files()
    resume = (pending.get("key") == key or done_ok) and all((out / n).is_file() for n in light_files)
    if resume and any(check_file_record(out / n, records[n]) for n in light_files if n in records):
        resume = False
    return records if resume else None


def _written_lights(out: Path, m: int, point_lights: bool) -> np.ndarray | None:
    """The (m, 3) lights ``out`` holds (those of the interrupted run: the directions, or the
    positions of point lights), or None when they do not read as m lights."""
    try:
        if point_lights:
            L = read_light_positions(out, m, [])
        else:
            L = read_light_directions(out, unit=False)
    except InputError:
        return None
    return L if L is not None and L.shape == (m, 3) else None


def _reopen(out: Path, key: str, names: list[str], records: dict, geometry: tuple[str, ...]) -> None:
    """Resume ``out``: unfinished again, without the files a killed run half-wrote and
    without its damaged (or unverifiable and unreadable) files, which are rendered again."""
    if (out / SCENE_FILE).is_file():
        # not complete any more: a killed resume must find .pending.json, not nothing
        write_text(out / PENDING_FILE, json.dumps({"key": key}) + "\n")
        (out / SCENE_FILE).unlink()
    remove_temp_files(out)  # half-written files of the killed run
    _drop_damaged(out, names, records, geometry)  # damaged (or unverifiable and unreadable) files


def write_scene_json(out: Path, scene: dict) -> None:
    """``scene.json`` with its checksum, written last: the folder is complete."""
    scene = add_json_checksum(scene, indent=SCENE_INDENT, skip=SCENE_TIMINGS)
    write_scene(out, scene)
    (out / PENDING_FILE).unlink(missing_ok=True)


# the temporary names of cnnps.infra.atomic: ``.{stem}.XXXXXXXX.tmp{suffix}`` (atomic_path) and
# ``.{name}.XXXXXXXX.tmp`` (atomic_dir, and _start_folder's build folder)
_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def remove_temp_files(folder: Path) -> list[Path]:
    """Delete the hidden temporary files (and folders) that atomic writes left in ``folder``
    when their process was killed. Call it only while no other job writes there."""
    removed = []
    for p in Path(folder).iterdir():
        if _TEMP_NAME.match(p.name):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def check_not_foreign(out: Path) -> None:
    """Refuse an existing ``out`` that holds something not of ours (never delete it)."""
    if out.exists() and not is_render_folder(out) and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out.absolute(), "exists and is not a cnnps render folder; choose a new or empty folder")


def previous_path(out: Path) -> Path:
    """Where a finished capture waits while ``out`` is rendered again for another key:
    the hidden sibling ``.<name>.previous`` (readers of a render folder skip hidden names)."""
    return out.parent / f".{out.name}.previous"


def _set_aside(out: Path) -> None:
    """Move a finished capture (``scene.json``) at ``out`` to :func:`previous_path`, so a
    re-render for another key that fails (a full disk) can put it back."""
    if not (out / SCENE_FILE).is_file():
        return
    prev = previous_path(out)
    if prev.exists():
        shutil.rmtree(prev)
    out.rename(prev)


def restore_previous(out: Path, prev: Path) -> None:
    """After a failed re-render: the set-aside version back at ``out``, the partial one gone."""
    if not prev.is_dir():
        return
    if out.exists():
        shutil.rmtree(out, ignore_errors=True)
    prev.rename(out)


def take_back_previous(out: Path, key: str) -> bool:
    """A set-aside version that is complete for ``key`` (a re-render for another key was
    killed, then the parameters went back) replaces ``out``; True when it did."""
    prev = previous_path(out)
    if not (prev.is_dir() and is_complete(prev, key)):
        return False
    if out.exists():
        shutil.rmtree(out)
    prev.rename(out)
    (out / PENDING_FILE).unlink(missing_ok=True)
    return True


def _start_folder(out: Path, key: str, record: Capture) -> np.ndarray:
    """Make ``out`` hold ``.pending.json`` (the key) and the light files of ``record``
    (names, directions or positions, intensities, intrinsics: :func:`cnnps.io.capture.write_capture_files`),
    so a folder with this key always has its lights. Returns the lights to render, as read
    back from the directions or positions file (a resumed run reads the same numbers).

    Only a folder of ours (``.pending.json`` or ``scene.json``) is emptied; any other
    non-empty ``out`` is refused (InputError). A new folder is built under a temporary
    name and renamed into place; if a duplicate of this job created it meanwhile (same
    key), its lights are used. An existing empty folder (or one of ours, emptied) is
    filled in place: marker without a key first, so a kill leaves it recognisably ours.
    """
    import tempfile

    m, point_lights = len(record.filenames), record.light_positions is not None
    if is_render_folder(out):  # another key, or killed while being set up
        write_text(out / PENDING_FILE, json.dumps({"key": None}) + "\n")
        for p in out.iterdir():
            if p.name == PENDING_FILE:
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
    else:
        check_not_foreign(out)

    if out.is_dir():  # empty (but for our key-less marker)
        write_text(out / PENDING_FILE, json.dumps({"key": None}) + "\n")
        write_capture_files(out, record)
        write_text(out / PENDING_FILE, json.dumps({"key": key}) + "\n")
        return _written_lights(out, m, point_lights)

    out.parent.mkdir(parents=True, exist_ok=True)
    build = re.compile(rf"^\.{re.escape(out.name)}\.[A-Za-z0-9_]{{8}}\.tmp$")
    for p in out.parent.glob(f".{glob.escape(out.name)}.*.tmp"):  # build folders of killed runs
        if p.is_dir() and build.match(p.name):
            shutil.rmtree(p, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        write_text(tmp / PENDING_FILE, json.dumps({"key": key}) + "\n")
        write_capture_files(tmp, record)
        publish_mode(tmp, is_dir=True)  # mkdtemp made it private (0700)
        tmp.rename(out)
    except OSError:  # out appeared meanwhile (a duplicate job): resume what it started
        pending = read_json(out / PENDING_FILE) or read_json(out / SCENE_FILE) or {}
        if pending.get("key") != key or _written_lights(out, m, point_lights) is None:
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _written_lights(out, m, point_lights)
