"""One scene of the extract stage (:func:`extract_scene`, a job an executor runs): its
render folder checked and read, its pixels sampled, its rows built (shards of maps or
per-pixel observations, written atomically) and its marker ``scene-<id>.json``, whose
checksum covers everything but its timings."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cnnps.infra import storage
from cnnps.infra.errors import InputError
from cnnps.infra.hashing import add_json_checksum, derive_seed64
from cnnps.infra.progress import progress_bar
from cnnps.io.observation_store import write_capture_observations
from cnnps.io.shards import SceneShardWriter, make_batch, shard_path, shard_schema
from cnnps.ps.rotation import rotation_angles
from cnnps.stages.extract_params import Params
from cnnps.synth.light_subsets import sample_light_masks
from cnnps.synth.render.rendered_folder import folder_problems
from cnnps.synth.training_samples import (
    STREAM_SPARSE,
    apply_capture_effects,
    build_rows,
    draw_capture_effects,
    stream,
)

MARKER_INDENT = 1  # scene-<id>.json is json.dumps(..., indent=1): its checksum hashes that form
MARKER_TIMINGS = ("seconds",)  # not in the marker's checksum: it varies between runs
FIX_RENDER = "rerun `cnnps run-stage render` (it re-renders exactly the damaged part), then this stage"
# layout observations: at most this share of a render's values may lie above float16's range
# and be clipped to it (Cycles fireflies); more stops the stage naming the scene
FIREFLY_FRACTION = 1e-4


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
