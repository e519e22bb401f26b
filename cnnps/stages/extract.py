"""Stage ``extract``: rendered captures -> Parquet shards of training observation maps.

Design notes (the light subsets, sparse pixels, the capture realism, randomness, cache
keys, integrity, the validation split, with measured distributions): ``docs/extract.md``.

Input: ``data_dir/render/<scene_id>/``, the render stage's scenes (images, ``mask.png``,
``normal_gt.npy``, the light files and ``scene.json``: see
:mod:`cnnps.synth.capture_render`), every file checked against the size and SHA-256 its
``scene.json`` records before any job starts. Parameters: :class:`Params` (the
``extract:`` section of params.yaml).

Output, in ``data_dir/extract/`` or at ``Params.output`` (a path or an fsspec URL):

- ``shard-<scene_id>-NNN.parquet``: one row per (foreground pixel, rotation), a w x w
  float16 observation map and its unit normal, both in the row's rotated camera frame
  (x right, y up, z to the camera); schema in :mod:`cnnps.io.shards`;
- ``scene-<scene_id>.json``: per scene, its cache key, shards (size, SHA-256) and a
  checksum of its own content; a rerun skips the scenes whose marker and shards match;
- ``manifest.json`` (written last): params, row counts, the train / val split by scene
  (by ``view_id``), every shard with its size and SHA-256, and its own checksum.

With ``layout: observations`` a scene is one ``obs-<scene_id>.cnnobs`` file instead of
its shards: every mask pixel's values under all lights, the lights, normals and pixels
(:mod:`cnnps.io.observation_store`), for a loader that draws subsets, rotations, realism
and b x b patches itself (:mod:`cnnps.train.patch_dataset`); the steps below are then the
loader's. Same marker, manifest (``"layout": "observations"``) and integrity rules.

Per foreground pixel with a valid ground-truth normal (``docs/extract.md`` has each step
in full):

1. a cone about the view axis with half-angle in [``cone_min_deg``, ``cone_max_deg``],
   widened to hold at least ``min(min_lights, m)`` lights;
2. k lights from the cone, k uniform in [min(min_lights, m), min(max_lights, m)], or,
   for a fraction ``sparse_fraction`` of the pixels, log-uniform in
   [``sparse_min_lights``, min(min_lights, m) - 1];
3. ``rotations`` copies, lights and normal rotated together about z
   (:func:`cnnps.ps.rotation.rotation_angles`), each map built by
   :func:`cnnps.ps.obsmap.observation_maps` (the code prediction uses);
4. sensor and capture realism, each off by default: mis-calibrated intensities and
   directions, ambient, black level, noise, saturation, quantisation
   (:mod:`cnnps.synth.training_samples`).

Pixels whose chosen lights are all dark are dropped (counted in the manifest). A scene's
rows depend only on its own key and the params (seeded by
:func:`cnnps.infra.hashing.derive_seed64`), so scenes are independent jobs for the
executor (:mod:`cnnps.infra.executor`) and a rerun writes the same bytes. A damaged input
stops the stage with one line naming the file and the fix; nothing is written.

Example::

    from cnnps.stages import extract
    extract.run(extract.Params(w=32, rotations=10), data_dir)   # data_dir/render -> data_dir/extract
"""

from __future__ import annotations

import json
from dataclasses import replace
from fnmatch import fnmatch, fnmatchcase
from pathlib import Path

from cnnps.infra import storage
from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.executor import runs_in_process, stage_executor
from cnnps.infra.hashing import (
    add_json_checksum,
    bytes_sha256,
    json_checksum_ok,
    stable_hash,
)
from cnnps.io.capture import SCENE_FILE, SCENE_INDENT
from cnnps.io.observation_store import SUFFIX as OBSERVATION_SUFFIX
from cnnps.io.shards import (
    MANIFEST,
    MANIFEST_INDENT,
    file_size,
    shard_path,
    shard_problem,
)
from cnnps.stages.extract_params import FORMAT_VERSION, Params
from cnnps.stages.extract_scene import (
    FIX_RENDER,
    MARKER_INDENT,
    MARKER_TIMINGS,
    SceneJob,
    check_render_folder,
    extract_scene,
)
from cnnps.synth.render.rendered_folder import SCENE_TIMINGS


def scene_cache_key(scene_key: str, params: Params) -> str:
    """Cache key of a scene's rows: its render key and the row params (json's default
    spacing, 32 hex digits: the keys of format 1)."""
    return stable_hash({"scene": scene_key, "params": params.row_key()}, compact=False)[:32]


def list_scenes(render_dir: Path) -> list[tuple[str, Path, dict]]:
    """(scene_id, folder, scene.json contents) for every rendered scene, sorted by id."""
    if not render_dir.is_dir():
        raise InputError(render_dir, "no rendered scenes (run the render stage first)")
    scenes = []
    for d in sorted(p for p in render_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
        meta_path = d / SCENE_FILE
        if not meta_path.is_file():
            continue  # an unfinished render leaves no scene.json
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(meta_path, f"not valid JSON ({exc}); {FIX_RENDER}") from exc
        if not isinstance(meta, dict) or "key" not in meta:
            raise InputError(meta_path, f"has no 'key'; {FIX_RENDER}")
        if json_checksum_ok(meta, indent=SCENE_INDENT, skip=SCENE_TIMINGS) is False:
            raise InputError(meta_path, f"edited by hand or damaged: its content does not match its checksum; {FIX_RENDER}")
        scenes.append((d.name, d, meta))
    if not scenes:
        raise InputError(render_dir, f"no rendered scenes with a {SCENE_FILE}")
    return scenes


def _cached(out_dir: str | Path, scene_id: str, key: str) -> dict | None:
    marker = shard_path(out_dir, f"scene-{scene_id}.json")
    if not storage.exists(marker):
        return None
    try:
        rec = json.loads(storage.read_text(marker))
    except (json.JSONDecodeError, UnicodeDecodeError, InputError):
        return None
    if not isinstance(rec, dict) or rec.get("key") != key:
        return None
    if json_checksum_ok(rec, indent=MARKER_INDENT, skip=MARKER_TIMINGS) is False:
        return None  # a marker edited by hand (or damaged): extract the scene again
    try:
        for s in rec.get("shards", []):
            path = shard_path(out_dir, s["file"])
            if storage.is_local(path):
                if shard_problem(path, s) is not None:  # missing, truncated or altered: redo the scene
                    return None
            elif file_size(path) != s["bytes"]:  # a URL: by size (train checks the SHA-256)
                return None
    except (KeyError, TypeError, ValueError):
        return None
    return rec


def select_scenes(scenes: list[tuple[str, Path, dict]], params: Params) -> list[tuple[str, Path, dict]]:
    """The scenes whose id matches one of ``params.scenes`` (fnmatch, case-sensitive), in
    their order; all of them when it is empty. A pattern matching no scene -> ConfigError
    naming it. Example: ids ``a-0-x, a-1-y, a-2-z`` and ``("*-0-*", "*-1-*")`` -> the first two."""
    if not params.scenes:
        return scenes
    for pattern in params.scenes:
        if not any(fnmatchcase(sid, pattern) for sid, _, _ in scenes):
            raise ConfigError(f"extract.scenes pattern {pattern!r} matches none of the {len(scenes)} rendered scenes")
    return [s for s in scenes if any(fnmatchcase(s[0], p) for p in params.scenes)]


def split_scenes(scenes: list[tuple[str, Path, dict]], params: Params) -> dict[str, str]:
    """scene_id -> 'train' | 'val' (see the module docstring)."""
    group_of = {sid: str(meta.get("view_id", sid)) for sid, _, meta in scenes}
    groups = sorted(set(group_of.values()))
    if params.val_scenes:
        known = set(group_of) | set(groups)
        unknown = [s for s in params.val_scenes if s not in known]
        if unknown:
            among = " (among those extract.scenes selects)" if params.scenes else ""
            raise ConfigError(f"extract.val_scenes names unknown scenes{among}: {', '.join(unknown)}")
        val = {g for g in groups if g in params.val_scenes} | {
            group_of[s] for s in params.val_scenes if s in group_of
        }
    else:
        n_val = int(round(params.val_fraction * len(groups)))
        if params.val_fraction > 0 and len(groups) >= 2:
            n_val = min(max(n_val, 1), len(groups) - 1)
        ranked = sorted(groups, key=lambda g: bytes_sha256(f"{params.seed}:{g}".encode()))
        val = set(ranked[:n_val])
    return {sid: ("val" if group_of[sid] in val else "train") for sid, _, _ in scenes}


def output_location(params: Params, data_dir: Path) -> str | Path:
    """Where the stage writes: ``params.output`` (path or URL) or ``data_dir/extract``."""
    if params.output is None:
        return Path(data_dir) / "extract"
    if storage.is_local(params.output):
        return storage.local_path(params.output)
    storage.fsspec_fs(params.output)  # an unknown scheme / missing backend: ConfigError now
    return params.output.rstrip("/")


def run(params: Params, data_dir: Path, executor=None) -> None:
    """Extract every rendered scene that ``params.scenes`` selects (skipping cached ones)
    and write the manifest; files of scenes outside it are removed.

    ``executor``: runs the per-scene jobs (``cnnps.infra.executor``); None = one made from
    ``params.executor`` / ``params.workers`` (default: in this process), closed at the end.
    """
    data_dir = Path(data_dir)
    out_dir = output_location(params, data_dir)
    rendered = list_scenes(data_dir / "render")
    scenes = select_scenes(rendered, params)
    if params.scenes:
        print(f"extract: {len(scenes)} of {len(rendered)} rendered scenes selected by extract.scenes")
    split = split_scenes(scenes, params)
    jobs, records = [], {}
    for sid, folder, meta in scenes:
        key = scene_cache_key(str(meta["key"]), params)
        rec = _cached(out_dir, sid, key)
        if rec is not None:
            records[sid] = rec
        else:
            jobs.append(SceneJob(sid, folder, key, str(meta["key"]), out_dir, params, checksummed="files" in meta))
    metas = {sid: meta for sid, _, meta in scenes}
    for j in jobs:  # every input checked before the first job writes anything
        check_render_folder(j.folder, metas[j.scene_id])
    if jobs:
        with stage_executor(params, executor) as ex:
            in_process = runs_in_process(ex, len(jobs))
            if storage.protocol(out_dir) == "memory" and not in_process:
                raise ConfigError(
                    f"extract.output {out_dir}: memory:// exists in one process only; use workers: 1 "
                    "(executor kind local) or a shared location (a path, file://, s3://)"
                )
            threads = ex.threads_per_job(len(jobs))
            if not in_process:
                jobs = [replace(j, threads=threads, progress=False) for j in jobs]
            for rec in ex.map(extract_scene, jobs, desc="extract scenes", num_cpus=threads):
                records[rec["scene"]] = rec
    shards, total = [], {"train": 0, "val": 0}
    for sid, _, _ in scenes:
        rec = records[sid]
        for s in rec["shards"]:
            shards.append({**s, "scene": sid, "split": split[sid]})
        total[split[sid]] += rec["rows"]
    manifest = {
        "format": FORMAT_VERSION,
        "w": params.w,
        "map_dtype": "float16",
        "params": params.manifest_params(),
        "total_rows": total["train"] + total["val"],
        "train_rows": total["train"],
        "val_rows": total["val"],
        "train_scenes": [s for s, _, _ in scenes if split[s] == "train"],
        "val_scenes": [s for s, _, _ in scenes if split[s] == "val"],
        "scenes": {
            sid: {k: records[sid][k] for k in ("key", "scene_key", "rows", "pixels", "dropped_dark_pixels", "lights")}
            | {"split": split[sid]}
            for sid, _, _ in scenes
        },
        "shards": shards,
    }
    if params.layout != "maps":
        manifest["layout"] = params.layout
    manifest = add_json_checksum(manifest, indent=MANIFEST_INDENT)
    storage.write_text(shard_path(out_dir, MANIFEST), json.dumps(manifest, indent=MANIFEST_INDENT))
    _remove_stale(out_dir, {s["file"] for s in shards}, {sid for sid, _, _ in scenes})


def _remove_stale(out_dir: str | Path, keep_files: set[str], keep_scenes: set[str]) -> None:
    """Delete shards and markers no longer in the manifest (after it is written)."""
    for name in storage.listdir(out_dir):
        stale = (
            ((fnmatch(name, "shard-*.parquet") or fnmatch(name, f"obs-*{OBSERVATION_SUFFIX}")) and name not in keep_files)
            or (fnmatch(name, "scene-*.json") and name[len("scene-") : -len(".json")] not in keep_scenes)
        )
        if stale:
            storage.remove(shard_path(out_dir, name))
    if storage.is_local(out_dir):
        for f in [*Path(out_dir).glob(".shard-*.parquet.tmp"), *Path(out_dir).glob(f".obs-*.tmp{OBSERVATION_SUFFIX}")]:
            f.unlink(missing_ok=True)  # left by a killed run (storage.listdir hides them)
