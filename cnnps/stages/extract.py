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
import time
from dataclasses import asdict, dataclass, replace
from typing import Annotated, Literal, get_args
from fnmatch import fnmatch, fnmatchcase
from pathlib import Path

import numpy as np

from cnnps.infra import storage
from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.executor import ExecutorParams, runs_in_process, stage_executor
from cnnps.infra.hashing import (
    add_json_checksum,
    bytes_sha256,
    derive_seed64,
    json_checksum_ok,
    stable_hash,
)
from cnnps.infra.options import Count, Range, check_fields
from cnnps.infra.progress import progress_bar
from cnnps.io.capture import SCENE_FILE, SCENE_INDENT
from cnnps.io.observation_store import OBSERVATION_FORMAT, write_capture_observations
from cnnps.io.observation_store import SUFFIX as OBSERVATION_SUFFIX
from cnnps.io.shards import (
    MANIFEST,
    MANIFEST_INDENT,
    SceneShardWriter,
    file_size,
    make_batch,
    shard_path,
    shard_problem,
    shard_schema,
)
from cnnps.ps.rotation import rotation_angles
from cnnps.synth.light_subsets import RULE, check_light_subsets, sample_light_masks
from cnnps.synth.render.rendered_folder import SCENE_TIMINGS, folder_problems
from cnnps.synth.training_samples import (
    STREAM_SPARSE,
    apply_capture_effects,
    build_rows,
    draw_capture_effects,
    stream,
)

FORMAT_VERSION = 1  # bump when the rows written for the same inputs change
MARKER_INDENT = 1  # scene-<id>.json is json.dumps(..., indent=1): its checksum hashes that form
MARKER_TIMINGS = ("seconds",)  # not in the marker's checksum: it varies between runs
FIX_RENDER = "rerun `cnnps run-stage render` (it re-renders exactly the damaged part), then this stage"


Fraction = Annotated[float, Range(ge=0.0, le=1.0)]  # a share or strength in [0, 1]
Layout = Literal["maps", "observations"]  # what a scene becomes: shards of maps, or per-pixel observations
LAYOUTS = get_args(Layout)


@dataclass(frozen=True)
class Params:
    """``extract:`` in params.yaml. A field declared with a type (a range, a choice) is
    checked from its declaration (:func:`cnnps.infra.options.check_fields`); the light-subset
    settings by :func:`cnnps.synth.light_subsets.check_light_subsets`; the rest below."""

    w: Annotated[int, Range(ge=4, le=256)] = 32
    # the light-subset rule (module docstring, steps 1 and 2): cnnps.synth.light_subsets declares it
    min_lights: int = RULE.min_lights
    max_lights: int = RULE.max_lights
    cone_min_deg: float = RULE.cone_min_deg
    cone_max_deg: float = RULE.cone_max_deg
    rotations: Annotated[int, Range(ge=1, le=127)] = 10
    ambient_max: Fraction = 0.0  # per-pixel ambient offset a ~ U(0, ambient_max), times the pixel's brightest light
    # sensor and capture realism (module docstring, step 4; each 0 / empty = off)
    intensity_error: Fraction = 0.0  # per scene and light: intensity factor 1 + e, e ~ N(0, intensity_error)
    direction_error_deg: Annotated[float, Range(ge=0.0, le=90.0)] = 0.0  # per scene and light: written direction turned by |N(0, this)| degrees
    black_level_max: Fraction = 0.0  # per scene: offset b * E, b ~ U(0, black_level_max), E the scene's full scale
    noise_max: Fraction = 0.0  # per pixel: read and shot noise levels ~ U(0, noise_max) x the pixel's brightest value
    saturated_fraction_max: Fraction = 0.0  # per scene: clip at the (1 - f) quantile of pixel peaks, f ~ U(0, this)
    quantize_bits: tuple[int, ...] = ()  # per scene: a bit depth drawn from these, grid E / (2^bits - 1)
    # sparse light subsets (module docstring, step 2): a pixel is sparse with this probability
    sparse_fraction: Fraction = 0.0
    sparse_min_lights: int = RULE.sparse_min_lights  # sparse k is log-uniform in [sparse_min_lights, min_lights)
    pixels_per_scene: Annotated[int, Range(ge=0)] = 0  # 0 = every foreground pixel
    val_fraction: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.1
    val_scenes: tuple[str, ...] = ()  # explicit validation scenes (or view ids); overrides val_fraction
    seed: int = 0
    rows_per_group: Count = 8192
    rows_per_shard: Count = 262144
    chunk_pixels: Count = 2048
    # how scenes are run: params.yaml's shared ``executor`` section (None = in this process);
    # ``workers`` overrides executor.workers when set (1 = in this process, 0 = one per core)
    executor: ExecutorParams | None = None
    workers: Annotated[int, Range(ge=0)] | None = None
    # where shards + manifest go: a path or an fsspec URL (s3://, gs://, file://, memory://);
    # None = data_dir/extract. The train stage reads the same place (train.data.shards).
    output: str | None = None
    # what a scene becomes: "maps" (the shards) or "observations" (one file of per-pixel
    # observations, cnnps.io.observation_store; pixels_per_scene and the map params unused)
    layout: Layout = "maps"
    # which rendered scenes the stage reads: fnmatch patterns of scene ids
    # (``<source>-<view>-<hash>``, e.g. ["*-0-*", "*-1-*"] = views 0 and 1); empty = every scene
    scenes: tuple[str, ...] = ()

    def __post_init__(self):
        check_fields(self, "extract.")
        check_light_subsets("extract", self, self.sparse_fraction)
        bits = tuple(self.quantize_bits)
        if not all(isinstance(b, (int, np.integer)) and not isinstance(b, bool) and 1 <= b <= 16 for b in bits):
            raise ConfigError(f"extract.quantize_bits must be bit depths in [1, 16], got {list(bits)}")
        object.__setattr__(self, "quantize_bits", tuple(sorted({int(b) for b in bits})))
        if self.output is not None and (not isinstance(self.output, str) or not self.output.strip()):
            raise ConfigError(f"extract.output must be a folder path or URL, got {self.output!r}")
        object.__setattr__(self, "val_scenes", tuple(self.val_scenes))
        patterns = [self.scenes] if isinstance(self.scenes, str) else list(self.scenes)
        bad = [p for p in patterns if not isinstance(p, str) or not p.strip()]
        if bad:
            raise ConfigError(f"extract.scenes must be a list of scene-id patterns, got {bad[0]!r}")
        object.__setattr__(self, "scenes", tuple(sorted(set(patterns))))

    def row_key(self) -> dict:
        """The params that change the rows of a scene (not the split, not parallelism)."""
        if self.layout == "observations":  # the rows' params are the loader's
            return {"layout": self.layout, "format": FORMAT_VERSION, "observation_format": OBSERVATION_FORMAT}
        d = self.manifest_params()
        for k in ("val_fraction", "val_scenes", "scenes"):  # which scenes, not their rows
            d.pop(k, None)
        d["format"] = FORMAT_VERSION
        return d

    def manifest_params(self) -> dict:
        """The params recorded in the manifest: not where or how the stage ran."""
        d = asdict(self)
        for k in ("executor", "workers", "output"):
            d.pop(k)
        for k, default in OMITTED_AT_DEFAULT.items():  # absent = default: the keys of format 1
            if d[k] == default:
                d.pop(k)
        if not self.sparse_fraction:  # no sparse pixels: their size has no effect on the rows
            d.pop("sparse_min_lights", None)
        return d


# Params outside format 1's keys: left out of manifest_params() and row_key() at these
# (their "off") values, so a Params that leaves them alone has format 1's cache keys and
# manifest.
OMITTED_AT_DEFAULT = {
    "ambient_max": 0.0,
    "intensity_error": 0.0,
    "direction_error_deg": 0.0,
    "black_level_max": 0.0,
    "noise_max": 0.0,
    "saturated_fraction_max": 0.0,
    "quantize_bits": (),
    "sparse_fraction": 0.0,
    "sparse_min_lights": RULE.sparse_min_lights,
    "layout": "maps",
    "scenes": (),
}
# layout observations: at most this share of a render's values may lie above float16's range
# and be clipped to it (Cycles fireflies); more stops the stage naming the scene
FIREFLY_FRACTION = 1e-4


def scene_cache_key(scene_key: str, params: Params) -> str:
    """Cache key of a scene's rows: its render key and the row params (json's default
    spacing, 32 hex digits: the keys of format 1)."""
    return stable_hash({"scene": scene_key, "params": params.row_key()}, compact=False)[:32]


# -- sampling (vectorised over pixels) ------------------------------------------------


# -- one scene --------------------------------------------------------------------------


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


@dataclass
class SceneJob:
    scene_id: str
    folder: Path
    key: str  # cache key (scene key + row params)
    scene_key: str
    out_dir: str | Path  # local folder or fsspec URL
    params: Params
    threads: int = 0
    progress: bool = True
    checksummed: bool = True  # its scene.json records the folder's checksums (checked before the job)


def check_render_folder(folder: Path, meta: dict) -> None:
    """InputError naming the first file of a rendered scene that does not match the
    checksums its ``scene.json`` records (nothing to check when it records none)."""
    problems = folder_problems(folder, meta)
    if problems:
        path, problem = problems[0]
        more = f" (and {len(problems) - 1} more file(s) of this scene)" if len(problems) > 1 else ""
        raise InputError(path, f"{problem}{more}; {FIX_RENDER}")


def _load_render(folder: Path, checksummed: bool):
    """The rendered capture, every image decoded and checked finite; a damaged file ->
    InputError naming it and the fix. The render stage finds a damaged file by itself
    only in a folder whose ``scene.json`` records checksums; in an older folder the file
    must be deleted first."""
    from cnnps.io.capture import load_capture

    try:
        return load_capture(folder)
    except InputError as exc:
        fix = FIX_RENDER if checksummed else f"delete it and {FIX_RENDER}"
        raise InputError(exc.path, f"{exc.problem}; {fix}") from None


def _scene_pixels(valid: np.ndarray, scene_seed: int, limit: int | None) -> np.ndarray:
    """The indices of the ``valid`` mask pixels to extract, in the scene's seeded random
    order, the first ``limit`` of them (None or 0: all)."""
    rng = np.random.default_rng([scene_seed, 0])
    pix = np.flatnonzero(valid)
    pix = pix[rng.permutation(len(pix))]
    return pix[:limit] if limit else pix


def extract_scene(job: SceneJob) -> dict:
    """Extract one scene into its shards and marker; returns the marker's contents."""
    if job.threads:
        _limit_threads(job.threads)
    p = job.params
    t0 = time.perf_counter()
    cap = _load_render(job.folder, job.checksummed)
    if cap.normal_gt is None:
        raise InputError(job.folder, f"rendered scene has no ground-truth normals (normal_gt.npy); {FIX_RENDER}")
    if p.layout == "observations":
        info = write_capture_observations(job.out_dir, job.scene_id, cap, scene_key=job.scene_key,
                                          clip_fraction=FIREFLY_FRACTION)
        return _write_marker(job, t0, info["lights"], info["rows"], 0, info["rows"], [info])
    rr, cc = np.nonzero(cap.mask)
    normals = cap.normal_gt[rr, cc].astype(np.float64)
    norm = np.linalg.norm(normals, axis=1)
    valid = np.isfinite(norm) & (norm > 0.5)
    I_all = cap.pixel_intensities()  # (P, m), mask pixels row-major, like rr, cc
    scene_seed = derive_seed64(p.seed, job.scene_key)
    pix = _scene_pixels(valid, scene_seed, p.pixels_per_scene)
    angles = rotation_angles(p.rotations)
    angles_deg = np.degrees(angles).astype(np.float32)
    schema = shard_schema(p.w)
    m = cap.lights.shape[0]
    fx = draw_capture_effects(
        scene_seed, I_all, np.flatnonzero(valid), cap.lights,
        ambient_max=p.ambient_max, noise_max=p.noise_max, intensity_error=p.intensity_error,
        direction_error_deg=p.direction_error_deg, black_level_max=p.black_level_max,
        saturated_fraction_max=p.saturated_fraction_max, quantize_bits=p.quantize_bits,
    )
    map_lights = cap.lights if fx.lights is None else fx.lights  # the directions written into the maps
    dropped_dark = 0
    rows_written = 0
    bar = progress_bar(total=len(pix), desc=f"extract {job.scene_id}", unit="px", disable=not job.progress, leave=False)
    with bar, SceneShardWriter(job.out_dir, f"shard-{job.scene_id}", schema, p.rows_per_group, p.rows_per_shard) as wr:
        for c, start in enumerate(range(0, len(pix), p.chunk_pixels)):
            sel = pix[start : start + p.chunk_pixels]
            crng = np.random.default_rng([scene_seed, 1, c])
            mask, cone_deg, k = sample_light_masks(
                crng, cap.lights, len(sel), p.min_lights, p.max_lights, p.cone_min_deg, p.cone_max_deg,
                sparse_fraction=p.sparse_fraction, sparse_min_lights=p.sparse_min_lights,
                sparse_rng=stream(scene_seed, STREAM_SPARSE, c) if p.sparse_fraction else None,
            )
            I = I_all[sel]
            lit = (np.where(mask, I, 0.0) > 0).any(axis=1)
            dropped_dark += int((~lit).sum())
            sel, mask, cone_deg, k, I = sel[lit], mask[lit], cone_deg[lit], k[lit], I[lit]
            I = apply_capture_effects(I, mask, fx, scene_seed, c)
            n = normals[sel] / norm[sel, None]
            maps, rot_n = build_rows(I, n, map_lights, mask, angles, p.w)
            if not (np.isfinite(maps).all() and np.isfinite(rot_n).all()):  # never write NaN maps
                raise InputError(job.folder, "non-finite observation maps (NaN or infinite rendered values?); "
                                 f"{FIX_RENDER}")
            R, P = len(angles), len(sel)
            order = crng.permutation(R * P)  # interleave rotations and pixels inside the chunk
            r_idx, p_idx = np.divmod(order, P)
            wr.write(
                make_batch(
                    schema,
                    maps.reshape(R * P, p.w, p.w)[order],
                    rot_n.reshape(R * P, 3)[order],
                    job.scene_id,
                    rr[sel][p_idx],
                    cc[sel][p_idx],
                    k[p_idx],
                    cone_deg[p_idx],
                    r_idx,
                    angles_deg[r_idx],
                )
            )
            rows_written += R * P
            bar.update(len(sel) + int((~lit).sum()))
    return _write_marker(job, t0, m, len(pix) - dropped_dark, dropped_dark, rows_written, [asdict(s) for s in wr.infos])


def _write_marker(job: SceneJob, t0: float, m: int, pixels: int, dropped_dark: int, rows: int, shards: list) -> dict:
    record = {"scene": job.scene_id, "key": job.key, "scene_key": job.scene_key, "lights": int(m),
              "pixels": int(pixels), "dropped_dark_pixels": dropped_dark, "rows": rows,
              "seconds": round(time.perf_counter() - t0, 3), "shards": shards}
    record = add_json_checksum(record, indent=MARKER_INDENT, skip=MARKER_TIMINGS)
    storage.write_text(shard_path(job.out_dir, f"scene-{job.scene_id}.json"), json.dumps(record, indent=MARKER_INDENT))
    return record


def _limit_threads(n: int) -> None:
    try:
        import threadpoolctl  # type: ignore

        threadpoolctl.threadpool_limits(n)
    except ImportError:
        pass


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
