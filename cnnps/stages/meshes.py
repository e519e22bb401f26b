"""The ``meshes`` stage: load source meshes and procedural shapes, pose them, write views.

:class:`Params` and :func:`run` write, for every (source mesh or procedural shape) × view,
``data_dir/meshes/<view_id>/mesh.ply`` (loaded and normalised by
:func:`cnnps.synth.meshes.load_mesh` or made by :func:`cnnps.synth.procedural.make_shape`,
then posed by a seeded random rotation; camera frame: x right, y up, z toward the
camera) and ``view.json``. A view's ``key`` is a hash of everything that determines its
mesh (source file bytes or procedural kind and seed, view index, seed, radius, code
version); ``view_id = <stem>-<k>-<key[:8]>``. Views whose ``view.json`` already holds
the same key are skipped, so adding a mesh only adds its views. View folders that are no
longer in the plan are removed (``prune``, default on): the materials stage iterates
over every view folder, and a stale view would otherwise keep producing stale scenes.

Poses are seeded per source (``seed``, the source's sha256, view index), not by position
in the file list, so adding or removing another mesh never changes a view.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh

from cnnps.infra.atomic import atomic_dir
from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import entropy_seed, file_sha256, key_entropy, stable_hash
from cnnps.infra.options import Count, Range, check_fields
from cnnps.infra.progress import progress_bar
from cnnps.infra.stage_folders import prune_stale, read_json
from cnnps.synth.meshes import (
    MESH_EXTENSIONS,
    RADIUS,
    load_mesh,
    normalize_mesh,
    pose_mesh,
    random_rotation,
)

VERSION = 1  # bump when the processing below changes what is written


def _procedural_kinds():
    from cnnps.synth.procedural import PROCEDURAL_KINDS

    return PROCEDURAL_KINDS


@dataclass(frozen=True)
class Params:
    """Parameters of the meshes stage (``meshes:`` in params.yaml).

    ``mesh_dir``: folder of mesh files (relative paths are relative to the working
    directory); ``None`` for procedural shapes only. ``extensions``: file suffixes taken
    from it (searched recursively). ``procedural``: number of procedural shapes, their
    kinds cycling through ``procedural_kinds``. ``views_per_mesh``: random poses per
    source mesh and per procedural shape. ``seed``: seeds every pose and shape.
    """

    mesh_dir: str | None = None
    extensions: tuple[str, ...] = MESH_EXTENSIONS
    procedural: Annotated[int, Range(ge=0)] = 0
    procedural_kinds: tuple[str, ...] = field(default_factory=lambda: tuple(_procedural_kinds()))
    views_per_mesh: Count = 1
    seed: Annotated[int, Range(ge=0)] = 0
    radius: Annotated[float, Range(gt=0.0, le=1.0)] = RADIUS
    prune: bool = True

    def __post_init__(self):
        object.__setattr__(self, "extensions", tuple(e.lower() if e.startswith(".") else "." + e.lower() for e in self.extensions))
        object.__setattr__(self, "procedural_kinds", tuple(self.procedural_kinds))
        check_fields(self, "meshes.")  # the declared ranges: procedural, views_per_mesh, seed, radius
        for e in self.extensions:
            if e not in MESH_EXTENSIONS:
                raise ConfigError(f"meshes.extensions: unsupported {e!r} (choose from {', '.join(MESH_EXTENSIONS)})")
        known = _procedural_kinds()
        for k in self.procedural_kinds:
            if k not in known:
                raise ConfigError(f"meshes.procedural_kinds: unknown kind {k!r} (choose from {', '.join(known)})")
        if self.procedural > 0 and not self.procedural_kinds:
            raise ConfigError("meshes.procedural_kinds is empty but meshes.procedural > 0")
        if self.mesh_dir is None and self.procedural == 0:
            raise ConfigError("meshes: nothing to do (set meshes.mesh_dir or meshes.procedural > 0)")


@dataclass(frozen=True)
class ViewSpec:
    view_id: str
    key: str
    kind: str  # "file" or a procedural kind
    source: str  # file path relative to mesh_dir, or "procedural:<kind>:<shape_seed>"
    source_sha256: str | None
    shape_seed: int | None
    view_index: int
    rotation: tuple[tuple[float, ...], ...]


def _slug(text: str) -> str:
    out = "".join(c if c.isalnum() or c in "_." else "_" for c in text)
    return out.strip("._") or "mesh"


def mesh_files(params: Params) -> list[Path]:
    """The source mesh files of ``params.mesh_dir`` (sorted); ConfigError when it is missing.

    A folder without mesh files is fine when procedural shapes are asked for: the
    repository's ``meshes/`` folder (params.yaml's default, a DVC dependency) holds only
    a README until meshes are dropped into it.
    """
    if params.mesh_dir is None:
        return []
    root = Path(params.mesh_dir)
    if not root.is_dir():
        raise ConfigError(f"meshes.mesh_dir: folder not found: {root}")
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in params.extensions and not p.name.startswith("."))
    if not files and params.procedural == 0:
        raise ConfigError(f"meshes.mesh_dir: no mesh files ({', '.join(params.extensions)}) in {root}")
    return files


def plan_views(params: Params) -> list[ViewSpec]:
    """Every view the stage should write, with its content key (no mesh is loaded)."""
    views: list[ViewSpec] = []
    base = {"version": VERSION, "seed": params.seed, "radius": params.radius}
    root = Path(params.mesh_dir) if params.mesh_dir is not None else None
    stems: dict[str, int] = {}
    for path in mesh_files(params):
        sha = file_sha256(path)
        rel = path.relative_to(root).as_posix()
        stem = _slug(path.stem)
        stems[stem] = stems.get(stem, 0) + 1
        for k in range(params.views_per_mesh):
            rng = np.random.default_rng([params.seed, key_entropy(sha), k])
            rot = random_rotation(rng)
            key = stable_hash({**base, "kind": "file", "sha256": sha, "view": k})
            views.append(ViewSpec(f"{stem}-{k}-{key[:8]}", key, "file", rel, sha, None, k, tuple(map(tuple, rot.tolist()))))
    kinds = params.procedural_kinds
    for i in range(params.procedural):
        kind = kinds[i % len(kinds)]
        shape_seed = entropy_seed(params.seed, 7919, i)
        for k in range(params.views_per_mesh):
            rng = np.random.default_rng([params.seed, shape_seed, k])
            rot = random_rotation(rng)
            key = stable_hash({**base, "kind": kind, "shape_seed": shape_seed, "view": k})
            views.append(
                ViewSpec(f"proc_{kind}_{i}-{k}-{key[:8]}", key, kind, f"procedural:{kind}:{shape_seed}", None, shape_seed, k, tuple(map(tuple, rot.tolist())))
            )
    return views


def _view_is_current(view_dir: Path, key: str) -> bool:
    meta = read_json(view_dir / "view.json") or {}
    return meta.get("key") == key and (view_dir / "mesh.ply").is_file()


def write_view(out_dir: Path, spec: ViewSpec, mesh: trimesh.Trimesh, params: Params) -> None:
    """Pose ``mesh`` (already normalised) and write ``mesh.ply`` + ``view.json`` atomically."""
    posed = pose_mesh(mesh, np.asarray(spec.rotation))
    meta = {
        "view_id": spec.view_id,
        "key": spec.key,
        "kind": spec.kind,
        "source": spec.source,
        "source_sha256": spec.source_sha256,
        "shape_seed": spec.shape_seed,
        "view_index": spec.view_index,
        "rotation": [list(r) for r in spec.rotation],
        "seed": params.seed,
        "radius": params.radius,
        "n_vertices": int(len(posed.vertices)),
        "n_faces": int(len(posed.faces)),
        "watertight": bool(posed.is_watertight),
        "frame": "camera: x right, y up, z toward the camera",
        "version": VERSION,
    }
    with atomic_dir(out_dir / spec.view_id) as tmp:
        # vertex normals are written too (angle-weighted, as Blender computes them), so the
        # renderer and the rasteriser of the materials stage shade with the same normals
        posed.export(str(tmp / "mesh.ply"), encoding="binary", vertex_normal=True)
        (tmp / "view.json").write_text(json.dumps(meta, indent=2) + "\n")


def list_views(data_dir: Path) -> list[Path]:
    """The view folders under ``data_dir/meshes`` (sorted), each with a view.json."""
    root = Path(data_dir) / "meshes"
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / "view.json").is_file())


def run(params: Params, data_dir: Path) -> None:
    """Write every planned view under ``data_dir/meshes`` (skipping current ones)."""
    from cnnps.synth.procedural import make_shape

    out_dir = Path(data_dir) / "meshes"
    views = plan_views(params)  # ConfigError for a missing folder happens here, before any work
    out_dir.mkdir(parents=True, exist_ok=True)
    todo = [v for v in views if not _view_is_current(out_dir / v.view_id, v.key)]
    # Group by source so a mesh file is loaded once for all its views.
    cache: dict[str, trimesh.Trimesh] = {}
    root = Path(params.mesh_dir) if params.mesh_dir is not None else None
    for spec in progress_bar(todo, desc="meshes", unit="view", disable=not todo, leave=True):
        if spec.source not in cache:
            cache.clear()
            if spec.kind == "file":
                cache[spec.source] = load_mesh(root / spec.source, params.radius)
            else:
                cache[spec.source] = normalize_mesh(make_shape(spec.kind, spec.shape_seed), params.radius)
        write_view(out_dir, spec, cache[spec.source], params)
    if params.prune:
        prune_stale(out_dir, {v.view_id for v in views}, ["view.json"], build_folders=True)
    print(f"meshes: {len(views)} views ({len(views) - len(todo)} up to date, {len(todo)} written) in {out_dir}")
