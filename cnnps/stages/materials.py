"""The ``materials`` stage: per scene (mesh view × category), a mask, normals and material maps.

Library side (also used by the render stage):

- :func:`rasterize` — an orthographic z-buffer rasteriser in NumPy. The camera looks down
  −z and covers x, y ∈ [−1, 1]; pixel (r, c) samples its centre
  x = −1 + (c + ½)·2/S, y = 1 − (r + ½)·2/S (row 0 on top), as Cycles does with the
  0.01 px Gaussian pixel filter. The first hit is the largest z. The normal is the smooth
  one: vertex normals (angle-weighted, as Blender computes them) interpolated with the
  barycentrics of the hit and normalised. **Flip rule:** when the hit face is seen from
  behind (its geometric normal has n_z < 0: open meshes, inconsistent winding) the normal is
  negated, as Cycles does for back-facing hits. The smooth normal of a front face can still
  have a slightly negative n_z at silhouettes (a few pixels); it is kept as it is, since it is
  the normal the renderer shades with. Zeros outside the mask.
  trimesh's ray module needs rtree/embree (not installed) and is far slower; this
  rasteriser takes about 0.1–0.3 s for 256² and 100 k faces (see the tests).
- :func:`sample_material_maps` — SLIC superpixels inside the mask (on the normal map), one
  random parameter row per superpixel drawn from the category ranges (:mod:`cnnps.synth.bsdf`).
- :func:`write_material_maps` — one folder per scene, written atomically.

Stage side: :class:`Params` and :func:`run` write ``data_dir/materials/<view_id>-<category>/``.
A scene's key hashes the view key, size, superpixels, compactness, the category's ranges
and the seed, so changing one category's ranges redoes only that category's scenes.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from cnnps.core.atomic import atomic_dir
from cnnps.core.errors import ConfigError, InputError
from cnnps.core.executor import ExecutorParams
from cnnps.synth.bsdf import CATEGORIES, PARAM_NAMES, CategoryRanges, MaterialRanges, sample_parameters

VERSION = 1
_CHUNK = 1 << 22  # candidate (triangle, pixel) pairs per rasterisation chunk (~4 M)


# --------------------------------------------------------------------------- rasteriser


@dataclass
class Raster:
    mask: np.ndarray  # (S,S) bool
    normal: np.ndarray  # (S,S,3) float32, unit, zeros outside
    depth: np.ndarray  # (S,S) float32, z of the first hit, -inf outside
    face: np.ndarray  # (S,S) int64, hit face index, -1 outside


def pixel_centres(size: int) -> tuple[np.ndarray, np.ndarray]:
    """x (S,) of the columns and y (S,) of the rows of an S×S image over [−1, 1]²."""
    t = (np.arange(size) + 0.5) * (2.0 / size)
    return -1.0 + t, 1.0 - t


def rasterize_full(mesh, size: int, vertex_normals: np.ndarray | None = None) -> Raster:
    """Rasterise ``mesh`` orthographically (see the module docstring); all buffers."""
    S = int(size)
    if S < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    VN = np.asarray(mesh.vertex_normals if vertex_normals is None else vertex_normals, dtype=np.float64)
    npix = S * S
    zbuf = np.full(npix, -np.inf)
    fbuf = np.full(npix, -1, dtype=np.int64)
    bbuf = np.zeros((npix, 3))
    if len(F):
        # continuous pixel coordinates: pixel centres sit on integers
        cx = (V[:, 0] + 1.0) * (S / 2.0) - 0.5
        cy = (1.0 - V[:, 1]) * (S / 2.0) - 0.5
        tx, ty, tz = cx[F], cy[F], V[F, 2]  # (T,3) each
        c0 = np.clip(np.ceil(tx.min(axis=1)), 0, S).astype(np.int64)
        c1 = np.clip(np.floor(tx.max(axis=1)), -1, S - 1).astype(np.int64)
        r0 = np.clip(np.ceil(ty.min(axis=1)), 0, S).astype(np.int64)
        r1 = np.clip(np.floor(ty.max(axis=1)), -1, S - 1).astype(np.int64)
        w = c1 - c0 + 1
        h = r1 - r0 + 1
        area = (tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0]) - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0])
        ok = (w > 0) & (h > 0) & (np.abs(area) > 1e-12)
        ids = np.nonzero(ok)[0]
        counts = (w * h)[ids]
        ends = np.cumsum(counts)
        start = 0
        while start < len(ids):
            base = ends[start - 1] if start else 0
            stop = int(np.searchsorted(ends, base + _CHUNK, side="right"))
            stop = max(stop, start + 1)
            _raster_chunk(ids[start:stop], counts[start:stop], tx, ty, tz, area, c0, r0, w, S, zbuf, fbuf, bbuf)
            start = stop
    mask = fbuf >= 0
    normal = np.zeros((npix, 3))
    if mask.any():
        f = fbuf[mask]
        n = np.einsum("pk,pkj->pj", bbuf[mask], VN[F[f]])
        e1 = V[F[f, 1]] - V[F[f, 0]]
        e2 = V[F[f, 2]] - V[F[f, 0]]
        back = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0  # geometric normal z < 0
        n[back] *= -1.0
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        bad = norm[:, 0] < 1e-12  # cancelling vertex normals: fall back to the face normal
        if bad.any():
            g = np.cross(e1[bad], e2[bad])
            g *= np.sign(g[:, 2:3] + 1e-300)
            n[bad] = g
            norm[bad] = np.linalg.norm(g, axis=1, keepdims=True)
        normal[mask] = n / norm
    return Raster(
        mask.reshape(S, S),
        normal.reshape(S, S, 3).astype(np.float32),
        zbuf.reshape(S, S).astype(np.float32),
        fbuf.reshape(S, S),
    )


def _raster_chunk(ids, counts, tx, ty, tz, area, c0, r0, w, S, zbuf, fbuf, bbuf):
    total = int(counts.sum())
    tri = np.repeat(ids, counts)
    offs = np.cumsum(counts) - counts
    local = np.arange(total) - np.repeat(offs, counts)
    ww = w[tri]
    rr = r0[tri] + local // ww
    cc = c0[tri] + local % ww
    x0, x1, x2 = tx[tri, 0], tx[tri, 1], tx[tri, 2]
    y0, y1, y2 = ty[tri, 0], ty[tri, 1], ty[tri, 2]
    a = area[tri]
    l0 = ((x1 - cc) * (y2 - rr) - (x2 - cc) * (y1 - rr)) / a
    l1 = ((x2 - cc) * (y0 - rr) - (x0 - cc) * (y2 - rr)) / a
    l2 = 1.0 - l0 - l1
    eps = -1e-9
    inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
    if not inside.any():
        return
    tri, rr, cc = tri[inside], rr[inside], cc[inside]
    lam = np.stack([l0[inside], l1[inside], l2[inside]], axis=1)
    z = (lam * tz[tri]).sum(axis=1)
    pix = rr * S + cc
    # nearest (largest z) per pixel within the chunk: sort by (pix, z), take each group's last
    order = np.lexsort((z, pix))
    pix_s = pix[order]
    last = np.ones(len(order), dtype=bool)
    last[:-1] = pix_s[1:] != pix_s[:-1]
    sel = order[last]
    p = pix[sel]
    better = z[sel] > zbuf[p]
    p, sel = p[better], sel[better]
    zbuf[p] = z[sel]
    fbuf[p] = tri[sel]
    bbuf[p] = lam[sel]


def rasterize(mesh, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(mask (S,S) bool, normal (S,S,3) float32)`` of ``mesh`` seen by the orthographic camera."""
    r = rasterize_full(mesh, size)
    return r.mask, r.normal


# --------------------------------------------------------------------------- material maps


@dataclass
class MaterialMaps:
    labels: np.ndarray  # (S,S) int32, superpixel index, -1 outside the mask
    params: dict[str, np.ndarray]  # base_color (S,S,3), others (S,S); float32, 0 outside
    table: dict[str, np.ndarray]  # per superpixel: base_color (P,3), others (P,)
    category: str
    mask: np.ndarray  # (S,S) bool


def slic_labels(mask: np.ndarray, n_segments: int, image: np.ndarray | None = None, compactness: float = 0.1) -> np.ndarray:
    """SLIC labels (S,S) int32 inside ``mask`` (−1 outside), relabelled 0..P'−1.

    ``image``: (S,S,C) or (S,S) features to segment (e.g. the normal map); ``None`` uses
    the pixel coordinates (compact, grid-like cells). SLIC with a mask is deterministic
    (scikit-image seeds its k-means placement itself).
    """
    from skimage.segmentation import slic

    mask = np.asarray(mask, dtype=bool)
    labels = np.full(mask.shape, -1, dtype=np.int32)
    if not mask.any():
        return labels
    if image is None:
        yy, xx = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]].astype(np.float64)
        image = np.stack([yy, xx], axis=-1) / max(mask.shape)
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 2:
        image = image[..., None]
    n = int(min(n_segments, mask.sum()))
    seg = slic(image, n_segments=n, compactness=compactness, mask=mask, start_label=0, channel_axis=-1, convert2lab=False, enforce_connectivity=True)
    seg = np.where(mask, seg, -1)
    # relabel densely (0..P'-1) in order of first appearance (row-major)
    inside = seg[mask]
    _, first, inv = np.unique(inside, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    labels[mask] = rank[inv].astype(np.int32)
    return labels


def sample_material_maps(
    mask: np.ndarray,
    category: str,
    superpixels: int = 5000,
    seed: int = 0,
    ranges: MaterialRanges | CategoryRanges | None = None,
    image: np.ndarray | None = None,
    compactness: float = 0.1,
    *,
    labels: np.ndarray | None = None,
) -> MaterialMaps:
    """Per-superpixel random parameters of ``category`` as per-pixel maps.

    ``superpixels``: SLIC segments P (paper: 5000 for training, 100 for test).
    ``image``: features for SLIC (the normal map is a good choice; ``None`` = coordinates).
    ``ranges``: :class:`MaterialRanges` (the category's ranges are taken) or a
    :class:`CategoryRanges`; ``None`` = the paper's defaults. ``labels``: precomputed
    superpixel labels (skips SLIC).
    """
    mask = np.asarray(mask, dtype=bool)
    cat = category.lower()
    if isinstance(ranges, CategoryRanges):
        cr = ranges
    else:
        cr = (ranges or MaterialRanges()).get(cat)
    if labels is None:
        labels = slic_labels(mask, superpixels, image, compactness)
    labels = np.asarray(labels, dtype=np.int32)
    n = int(labels.max()) + 1 if mask.any() else 0
    rng = np.random.default_rng(seed)
    table = sample_parameters(cr, n, rng)
    params: dict[str, np.ndarray] = {}
    inside = labels >= 0
    for name in PARAM_NAMES:
        col = table[name]
        shape = mask.shape + col.shape[1:]
        out = np.zeros(shape, dtype=np.float32)
        out[inside] = col[labels[inside]]
        params[name] = out
    return MaterialMaps(labels, params, table, cat, mask)


def preview_image(maps: MaterialMaps) -> np.ndarray:
    """(S, 2S, 3) uint8 sRGB-ish picture: base colour (left); roughness, specular/4, sheen as R, G, B (right)."""
    base = np.clip(maps.params["base_color"], 0, 1)
    right = np.stack([maps.params["roughness"], maps.params["specular"] / 4.0, maps.params["sheen"]], axis=-1)
    img = np.clip(np.concatenate([base, right], axis=1), 0, 1)
    img[np.concatenate([~maps.mask, ~maps.mask], axis=1)] = 0.15
    return (img * 255 + 0.5).astype(np.uint8)


def write_material_maps(out_dir: str | Path, maps: MaterialMaps, normal: np.ndarray | None = None, meta: dict | None = None) -> None:
    """Write a scene folder atomically: ``<param>.npy``, ``labels.npy``, ``mask.png``,
    ``normal.npy``, ``preview.png`` and ``material.json`` (``meta`` merged in)."""
    import cv2

    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        for name, arr in maps.params.items():
            np.save(tmp / f"{name}.npy", arr.astype(np.float32))
        np.save(tmp / "labels.npy", maps.labels.astype(np.int32))
        if normal is not None:
            np.save(tmp / "normal.npy", np.asarray(normal, dtype=np.float32))
        if not cv2.imwrite(str(tmp / "mask.png"), maps.mask.astype(np.uint8) * 255):
            raise InputError(tmp / "mask.png", "cannot write image")
        if not cv2.imwrite(str(tmp / "preview.png"), preview_image(maps)[..., ::-1]):
            raise InputError(tmp / "preview.png", "cannot write image")
        info = {
            "category": maps.category,
            "superpixels_found": int(maps.labels.max()) + 1 if maps.mask.any() else 0,
            "pixels": int(maps.mask.sum()),
            "params": list(maps.params),
            "table": {k: v.tolist() for k, v in maps.table.items()},
        }
        info.update(meta or {})
        (tmp / "material.json").write_text(json.dumps(info, indent=1) + "\n")


# --------------------------------------------------------------------------- stage


@dataclass(frozen=True)
class Params:
    """Parameters of the materials stage (``materials:`` in params.yaml).

    ``size``: image side S (pixels); ``superpixels``: SLIC segments per scene (paper:
    5000 train / 100 test); ``categories``: subset of diffuse, specular, metallic;
    ``ranges``: a :class:`MaterialRanges` or a dict of per-category overrides
    (``{"specular": {"specular": [0, 4]}}``); ``seed``; ``compactness``: SLIC
    compactness on the normal map; ``executor``: how scenes are run (params.yaml's shared
    ``executor`` section; ``None`` = in this process); ``workers``: overrides
    ``executor.workers`` when set (1 = in this process, 0 = one per core).
    """

    size: int = 128
    superpixels: int = 5000
    categories: tuple[str, ...] = CATEGORIES
    ranges: MaterialRanges = field(default_factory=MaterialRanges)
    seed: int = 0
    compactness: float = 0.1
    executor: ExecutorParams | None = None
    workers: int | None = None
    prune: bool = True

    def __post_init__(self):
        if isinstance(self.ranges, dict):
            object.__setattr__(self, "ranges", MaterialRanges.from_dict(self.ranges))
        elif self.ranges is None:
            object.__setattr__(self, "ranges", MaterialRanges())
        if not isinstance(self.ranges, MaterialRanges):
            raise ConfigError(f"materials.ranges must be a mapping, got {type(self.ranges).__name__}")
        if isinstance(self.categories, str):
            raise ConfigError("materials.categories must be a list of category names")
        cats = tuple(str(c).lower() for c in self.categories)
        object.__setattr__(self, "categories", cats)
        if not cats:
            raise ConfigError("materials.categories is empty")
        for c in cats:
            if c not in CATEGORIES:
                raise ConfigError(f"materials.categories: unknown category {c!r} (choose from {', '.join(CATEGORIES)})")
        if len(set(cats)) != len(cats):
            raise ConfigError(f"materials.categories has duplicates: {list(cats)}")
        if not isinstance(self.size, int) or not 8 <= self.size <= 4096:
            raise ConfigError(f"materials.size must be an integer in [8, 4096], got {self.size!r}")
        if not isinstance(self.superpixels, int) or self.superpixels < 1:
            raise ConfigError(f"materials.superpixels must be an integer >= 1, got {self.superpixels!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"materials.seed must be an integer >= 0, got {self.seed!r}")
        if not self.compactness > 0:
            raise ConfigError(f"materials.compactness must be > 0, got {self.compactness}")
        if self.workers is not None and (not isinstance(self.workers, int) or self.workers < 0):
            raise ConfigError(f"materials.workers must be an integer >= 0 (0 = one per core), got {self.workers!r}")


def scene_key(view_key: str, category: str, params: Params) -> str:
    """Content key of one scene: only what affects its folder (one category's ranges)."""
    from cnnps.stages.meshes import stable_hash

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
    from cnnps.stages.meshes import list_views

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
                    "seed": int(np.random.SeedSequence([params.seed, int(key[:15], 16)]).generate_state(1)[0]),
                    "base_seed": params.seed,
                    "out_dir": str(Path(data_dir) / "materials" / f"{vdir.name}-{cat}"),
                }
            )
    return jobs


def _scene_is_current(out_dir: Path, key: str) -> bool:
    try:
        return json.loads((out_dir / "material.json").read_text()).get("key") == key
    except (OSError, ValueError):
        return False


def _scene_job(job: dict) -> str:
    """Rasterise one view, sample one category's maps, write the scene (top level: picklable).

    Idempotent: the folder's content depends only on the job (its key and seed), so a
    retried job rewrites the same files, and one whose folder a duplicate already
    finished returns at once."""
    from cnnps.stages.meshes import read_view_mesh

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
    """Write every (view × category) scene under ``data_dir/materials`` (skipping current ones)."""
    from cnnps.core.executor import get_executor

    out_root = Path(data_dir) / "materials"
    jobs = plan_scenes(params, data_dir)
    out_root.mkdir(parents=True, exist_ok=True)
    todo = [j for j in jobs if not _scene_is_current(Path(j["out_dir"]), j["key"])]
    if todo:
        own = executor is None
        if own:
            ep = params.executor or ExecutorParams(workers=1)
            if params.workers is not None:
                ep = dataclasses.replace(ep, workers=params.workers)
            executor = get_executor(ep)
        try:
            # one CPU per job: the rasteriser and SLIC are single-threaded NumPy / scikit-image
            executor.map(_scene_job, todo, desc="materials", num_cpus=1)
        finally:
            if own:
                executor.close()
    if params.prune:
        wanted = {j["scene_id"] for j in jobs}
        for p in out_root.iterdir():
            if p.is_dir() and p.name not in wanted and ((p / "material.json").is_file() or p.name.endswith(".tmp")):
                shutil.rmtree(p, ignore_errors=True)
    print(f"materials: {len(jobs)} scenes ({len(jobs) - len(todo)} up to date, {len(todo)} written) in {out_root}")
