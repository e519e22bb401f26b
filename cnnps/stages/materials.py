"""The ``materials`` stage: per scene (mesh view × category), a mask, normals and material maps.

For every view under ``data_dir/meshes`` and every category, this writes
``data_dir/materials/<view_id>-<category>/``: the view rasterised orthographically
(:func:`cnnps.synth.raster.rasterize`: mask and smooth normals at the pixel centres the
renderer samples) and SLIC superpixel material maps drawn on its normal map
(:func:`cnnps.synth.material_maps.sample_material_maps`), written by
:func:`cnnps.synth.material_maps.write_material_maps`.

A scene's key hashes the view key, size, superpixels, compactness, the category's ranges
and the seed, so changing one category's ranges redoes only that category's scenes, and
adding a category (``narrow`` is opt-in: the default list is the paper's three) adds
scenes without touching the others.
Scene folders no longer planned are removed (``prune``, default on).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.executor import ExecutorParams, stage_executor
from cnnps.infra.hashing import entropy_seed, key_entropy, stable_hash
from cnnps.infra.options import Count, Range, check_fields
from cnnps.infra.stage_folders import prune_stale, read_json
from cnnps.stages.meshes import list_views
from cnnps.synth.bsdf import (
    DEFAULT_CATEGORIES,
    CategoryRanges,
    MaterialRanges,
    checked_categories,
    checked_ranges,
)
from cnnps.synth.material_maps import sample_material_maps, write_material_maps
from cnnps.synth.meshes import read_view_mesh
from cnnps.synth.raster import rasterize

VERSION = 1  # bump when what is written for the same inputs changes


@dataclass(frozen=True)
class Params:
    """Parameters of the materials stage (``materials:`` in params.yaml).

    ``size``: image side S (pixels); ``superpixels``: SLIC segments per scene (paper:
    5000 train / 100 test); ``categories``: subset of diffuse, specular, metallic
    (the paper's, the default) and narrow (opt-in narrow-lobe glossy dielectrics:
    :mod:`cnnps.synth.bsdf`); ``ranges``: a :class:`MaterialRanges` or a dict of per-category overrides
    (``{"specular": {"specular": [0, 4]}}``); ``seed``; ``compactness``: SLIC
    compactness on the normal map; ``executor``: how scenes are run (params.yaml's shared
    ``executor`` section; ``None`` = in this process); ``workers``: overrides
    ``executor.workers`` when set (1 = in this process, 0 = one per core).
    """

    size: Annotated[int, Range(ge=8, le=4096)] = 128
    superpixels: Count = 5000
    categories: tuple[str, ...] = DEFAULT_CATEGORIES
    ranges: MaterialRanges = field(default_factory=MaterialRanges)
    seed: Annotated[int, Range(ge=0)] = 0
    compactness: Annotated[float, Range(gt=0.0)] = 0.1
    executor: ExecutorParams | None = None
    workers: Annotated[int, Range(ge=0)] | None = None  # 0 = one per core
    prune: bool = True

    def __post_init__(self):
        object.__setattr__(self, "ranges", checked_ranges("materials", self.ranges))
        object.__setattr__(self, "categories", checked_categories("materials", self.categories))
        check_fields(self, "materials.")  # the declared ranges: size, superpixels, seed, compactness, workers


def scene_key(view_key: str, category: str, params: Params) -> str:
    """Content key of one scene: only what affects its folder (one category's ranges)."""
    return stable_hash(
        {
            "version": VERSION,
            "view": view_key,
            "category": category,
            "ranges": asdict(params.ranges.get(category)),
            "size": params.size,
            "superpixels": params.superpixels,
            "compactness": params.compactness,
            "seed": params.seed,
        }
    )


def plan_scenes(params: Params, data_dir: Path) -> list[dict]:
    """One job per (view × category): picklable dicts for :func:`_scene_job`."""
    views = list_views(data_dir)
    if not views:
        raise ConfigError(f"materials: no mesh views in {Path(data_dir) / 'meshes'} (run the meshes stage first)")
    jobs = []
    for vdir in views:
        try:
            vmeta = json.loads((vdir / "view.json").read_text())
        except (OSError, ValueError) as exc:
            raise InputError(vdir / "view.json", f"unreadable view description: {exc}") from None
        if "key" not in vmeta:
            raise InputError(vdir / "view.json", "no 'key' field (rerun the meshes stage)")
        for cat in params.categories:
            key = scene_key(vmeta["key"], cat, params)
            jobs.append(
                {
                    "scene_id": f"{vdir.name}-{cat}",
                    "key": key,
                    "view_dir": str(vdir),
                    "view_id": vdir.name,
                    "view_key": vmeta["key"],
                    "category": cat,
                    "size": params.size,
                    "superpixels": params.superpixels,
                    "compactness": params.compactness,
                    "ranges": asdict(params.ranges.get(cat)),
                    "seed": entropy_seed(params.seed, key_entropy(key)),
                    "base_seed": params.seed,
                    "out_dir": str(Path(data_dir) / "materials" / f"{vdir.name}-{cat}"),
                }
            )
    return jobs


def _scene_is_current(out_dir: Path, key: str) -> bool:
    return (read_json(out_dir / "material.json") or {}).get("key") == key


def _scene_job(job: dict) -> str:
    """Rasterise one view, sample one category's maps, write the scene (top level: picklable).

    Idempotent: the folder's content depends only on the job (its key and seed), so a
    retried job rewrites the same files, and one whose folder a duplicate already
    finished returns at once."""
    out_dir = Path(job["out_dir"])
    if _scene_is_current(out_dir, job["key"]):
        return job["scene_id"]

    mesh = read_view_mesh(job["view_dir"])
    mask, normal = rasterize(mesh, job["size"])
    if not mask.any():
        raise InputError(Path(job["view_dir"]) / "mesh.ply", "mesh covers no pixel of the image")
    cr = CategoryRanges.from_dict(job["ranges"], job["category"])
    maps = sample_material_maps(mask, job["category"], job["superpixels"], job["seed"], cr, image=normal, compactness=job["compactness"])
    meta = {
        "scene_id": job["scene_id"],
        "key": job["key"],
        "view_id": job["view_id"],
        "view_key": job["view_key"],
        "size": job["size"],
        "superpixels": job["superpixels"],
        "compactness": job["compactness"],
        "ranges": job["ranges"],
        "seed": job["seed"],
        "base_seed": job["base_seed"],
        "version": VERSION,
    }
    try:
        write_material_maps(out_dir, maps, normal, meta)
    except OSError:
        if not _scene_is_current(out_dir, job["key"]):
            raise
        # a duplicate of this job (e.g. a Ray retry) renamed the same content in first
    return job["scene_id"]


def run(params: Params, data_dir: Path, executor=None) -> None:
    """Write every (view × category) scene under ``data_dir/materials`` (skipping current ones).

    ``executor``: runs the per-scene jobs (:mod:`cnnps.infra.executor`); None = one made
    from ``params.executor`` / ``params.workers`` (default: in this process), closed at the end.
    """
    out_root = Path(data_dir) / "materials"
    jobs = plan_scenes(params, data_dir)
    out_root.mkdir(parents=True, exist_ok=True)
    todo = [j for j in jobs if not _scene_is_current(Path(j["out_dir"]), j["key"])]
    if todo:
        with stage_executor(params, executor) as ex:
            # one CPU per job: the rasteriser and SLIC are single-threaded NumPy / scikit-image
            ex.map(_scene_job, todo, desc="materials", num_cpus=1)
    if params.prune:
        prune_stale(out_root, {j["scene_id"] for j in jobs}, ["material.json"], build_folders=True)
    print(f"materials: {len(jobs)} scenes ({len(jobs) - len(todo)} up to date, {len(todo)} written) in {out_root}")
