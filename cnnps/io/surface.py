"""From a normal map to a surface: depth.npy, depth.png and surface.ply.

:func:`build_surface` integrates a normal map over its mask (:mod:`cnnps.ps.integrate`)
into a :class:`Surface`; :meth:`Surface.write` (and :func:`write_surface_outputs`, both
at once) writes, into one folder:

- ``depth.npy``: H x W float32 heights along +z (toward the camera) in pixel units
  (orthographic camera, 1 x 1 pixels), NaN outside the mask, mean 0 over each
  4-connected component of the mask; with a pinhole camera (``intrinsics=K``) the depth
  along the optical axis instead (positive, each component scaled to the median
  ``distance``: the unit of the light positions under point lights, else up to scale);
- ``depth.png``: a picture of it: the heights colour-mapped (TURBO: blue far, red near),
  shaded by the normals under a light from the upper left, black outside the mask;
- ``surface.ply``: a binary little-endian PLY triangle mesh with vertex normals (float32
  x, y, z, nx, ny, nz per vertex; a uchar count and three int32 vertex numbers per face;
  the same bytes ``trimesh`` writes for :attr:`Surface.mesh`). Its vertices
  are the centres of the mask pixels that belong to a triangle, at
  x = column - (W - 1) / 2, y = (H - 1) / 2 - row, z = depth (pixel units, the capture
  frame, centred on the image), with the input normals as vertex normals. Every 2 x 2
  block of pixel centres gives two triangles when all four are in the mask and one when
  three are (so diagonal mask borders stay smooth); faces wind counter-clockwise seen
  from +z, so their normals face the camera. Mask pixels with no 2 x 2 block around them
  (isolated pixels, one-pixel-wide lines) carry no triangle and are left out. With a
  pinhole camera the vertices are the 3D points depth x diag(1, -1, -1) K^-1 (u, v, 1)
  (the capture frame, camera at the origin, the object at z < 0). Vertices are numbered
  in row-major pixel order; faces list every block's first triangle of a full block, then
  every second one, then the blocks of three (:data:`TRIANGLES`), each in row-major block
  order. The file is written a band of rows at a time (:class:`MeshLayout`), so writing
  it needs no mesh in memory.

The three files are all written under temporary names first and renamed into place
only when every one of them is complete (:mod:`cnnps.infra.atomic`): a failure leaves the
folder as it was.
"""

from __future__ import annotations

import contextlib
import functools
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.ps.integrate import check_normal_array, integrate

OUTPUT_FILES = ("depth.npy", "depth.png", "surface.ply")
LIGHT = np.array([-1.0, 1.0, 2.0]) / np.sqrt(6.0)  # upper left, in front


def read_normals(path: str | Path) -> np.ndarray:
    """Load an H x W x 3 ``.npy`` normal map (no pickles); InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found" if not path.exists() else "not a file")
    try:
        normals = np.load(path, allow_pickle=False)
    except Exception as exc:  # ValueError (pickled / not .npy), OSError, EOFError ...
        raise InputError(path, f"unreadable .npy array ({exc})") from exc
    if not isinstance(normals, np.ndarray):
        raise InputError(path, "expected one .npy array, got an .npz archive")
    return check_normal_array(normals, path)


# The two triangles of a full 2 x 2 block, then the one of each block of three, as
# (which corners are present, the triangle's corners): a top-left, b top-right, d
# bottom-left, e bottom-right; all counter-clockwise seen from +z. The mesh lists every
# block's triangle of the first kind in row-major block order, then of the second, and
# so on.
TRIANGLES = (
    ("abde", "adb"), ("abde", "bde"),  # all four: split along the b-d diagonal
    ("abd", "adb"), ("abe", "aeb"), ("ade", "ade"), ("bde", "bde"),  # exactly three
)
CHUNK_PIXELS = 1 << 16  # grid pixels per band of rows (mesh layout, PLY writing, depth picture)
PLY_VERTEX = np.dtype([("vertex", "<f4", (3,)), ("normals", "<f4", (3,))])
PLY_FACE = np.dtype([("count", "<u1"), ("index", "<i4", (3,))])
# the header trimesh.exchange.ply.export_ply writes for vertices with normals and faces
PLY_HEADER = ("ply\nformat binary_little_endian 1.0\ncomment https://github.com/mikedh/trimesh\n"
              "element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              "element face {faces}\nproperty list uchar int vertex_indices\nend_header\n")


def _bands(H: int, W: int, overlap: int = 0):
    """(r0, r1) row bands of about CHUNK_PIXELS pixels covering rows 0 .. H - 1 - overlap."""
    step = max(1, CHUNK_PIXELS // max(W, 1))
    for r0 in range(0, H - overlap, step):
        yield r0, min(r0 + step, H - overlap)


def _corners(present: np.ndarray) -> dict:
    """The (h, w) presence of each corner of the h x w blocks of ``present`` (h + 1, w + 1)."""
    return {"a": present[:-1, :-1], "b": present[:-1, 1:], "d": present[1:, :-1], "e": present[1:, 1:]}


def _selected(corner: dict, kind: str) -> np.ndarray:
    """Blocks whose present corners are exactly ``kind`` (e.g. ``"abd"``)."""
    sel = None
    for name, here in corner.items():
        flag = here if name in kind else ~here
        sel = flag if sel is None else sel & flag
    return sel


@dataclass
class MeshLayout:
    """Which pixels and triangles of a mask make the surface mesh (module docstring).

    present: (H, W) bool, the pixels with a height; used: (H, W) bool, those that are a
    corner of a triangle (the vertices, numbered in row-major order); row_start: (H + 1,)
    int64, the number of the first vertex of each row (the last entry: the vertex count);
    counts: the number of triangles of each of :data:`TRIANGLES`.
    """

    present: np.ndarray
    used: np.ndarray
    row_start: np.ndarray
    counts: tuple[int, ...]

    @classmethod
    def of(cls, depth: np.ndarray, mask: np.ndarray) -> MeshLayout:
        """The layout of the mask pixels where ``depth`` (H, W) is finite."""
        present = np.asarray(mask, dtype=bool) & np.isfinite(depth)
        H, W = present.shape
        used = np.zeros((H, W), dtype=bool)
        counts = [0] * len(TRIANGLES)
        for i0, i1 in _bands(H, W, overlap=1):
            corner = _corners(present[i0:i1 + 1])
            kinds = {}
            for k, (kind, _) in enumerate(TRIANGLES):
                sel = kinds.get(kind)
                if sel is None:
                    sel = kinds[kind] = _selected(corner, kind)
                counts[k] += int(np.count_nonzero(sel))
            tri = kinds["abde"] | kinds["abd"] | kinds["abe"] | kinds["ade"] | kinds["bde"]
            used[i0:i1, :-1] |= tri & corner["a"]
            used[i0:i1, 1:] |= tri & corner["b"]
            used[i0 + 1:i1 + 1, :-1] |= tri & corner["d"]
            used[i0 + 1:i1 + 1, 1:] |= tri & corner["e"]
        row_start = np.zeros(H + 1, dtype=np.int64)
        np.cumsum(np.count_nonzero(used, axis=1), out=row_start[1:])
        return cls(present, used, row_start, tuple(counts))

    @property
    def vertices(self) -> int:
        return int(self.row_start[-1])

    @property
    def faces(self) -> int:
        return sum(self.counts)

    def vertex_chunks(self, depth: np.ndarray, normals: np.ndarray, intrinsics=None):
        """(positions (k, 3) float64, unit normals (k, 3) float64) of the vertices, in
        order, a band of rows at a time (positions: module docstring)."""
        H, W = self.used.shape
        for r0, r1 in _bands(H, W):
            r, c = np.nonzero(self.used[r0:r1])
            if r.size == 0:
                continue
            r += r0
            z = depth[r, c].astype(np.float64)
            if intrinsics is None:
                xyz = np.stack([c - (W - 1) / 2.0, (H - 1) / 2.0 - r, z], axis=1)
            else:
                from cnnps.ps.camera import pixel_rays

                xyz = pixel_rays(intrinsics, r, c) * z[:, None]
            n = normals[r, c].astype(np.float64)
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            yield xyz, n

    def face_chunks(self):
        """(k, 3) int64 vertex numbers of the triangles, in order, a band of blocks at a time."""
        H, W = self.used.shape
        for kind, triangle in TRIANGLES:
            for i0, i1 in _bands(H, W, overlap=1):
                corner = _corners(self.present[i0:i1 + 1])
                sel = _selected(corner, kind)
                if not sel.any():
                    continue
                band = self.used[i0:i1 + 1]
                number = np.cumsum(band, axis=1, dtype=np.int64)
                number += self.row_start[i0:i1 + 1, None] - 1  # the vertex number where used
                index = _corners(number)
                yield np.stack([index[v][sel] for v in triangle], axis=1)


def surface_mesh(depth: np.ndarray, normals: np.ndarray, mask: np.ndarray, intrinsics=None):
    """A ``trimesh.Trimesh`` of the masked height field, or with ``intrinsics`` (a pinhole
    K) of the depth map's 3D points (layout: module docstring). ``depth`` (H, W), NaN
    where there is no surface; ``normals`` (H, W, 3), capture frame; ``mask`` (H, W)."""
    import trimesh

    layout = MeshLayout.of(depth, mask)
    normals = np.asarray(normals)
    chunks = list(layout.vertex_chunks(depth, normals, intrinsics))
    vertices = np.concatenate([v for v, _ in chunks]) if chunks else np.zeros((0, 3))
    vertex_normals = np.concatenate([n for _, n in chunks]) if chunks else np.zeros((0, 3))
    del chunks
    faces = [f for f in layout.face_chunks()]
    faces = np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=vertex_normals, process=False,
                           validate=False)


def write_ply(file, layout: MeshLayout, depth: np.ndarray, normals: np.ndarray, intrinsics=None) -> None:
    """Write the mesh of ``layout`` as binary little-endian PLY into ``file`` (an open binary
    file), a band of rows at a time: vertices as float32 x, y, z and nx, ny, nz, faces as
    a uchar count and three int32 vertex numbers (what ``trimesh`` writes for the same
    mesh, byte for byte)."""
    file.write(PLY_HEADER.format(vertices=layout.vertices, faces=layout.faces).encode("ascii"))
    for xyz, n in layout.vertex_chunks(depth, normals, intrinsics):
        rec = np.empty(len(xyz), dtype=PLY_VERTEX)
        rec["vertex"] = xyz
        rec["normals"] = n
        file.write(rec.tobytes())
    for faces in layout.face_chunks():
        rec = np.empty(len(faces), dtype=PLY_FACE)
        rec["count"] = 3
        rec["index"] = faces
        file.write(rec.tobytes())


def depth_picture(depth: np.ndarray, normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint8 RGB (H, W, 3): heights colour-mapped (TURBO, the 0.5th percentile blue, the
    99.5th red), times a Lambertian shading 0.35 + 0.65 max(0, n . l) of the normals;
    black outside the mask. Computed a band of rows at a time."""
    import cv2

    mask = np.asarray(mask, dtype=bool) & np.isfinite(depth)
    normals = np.asarray(normals)
    H, W = mask.shape
    out = np.zeros((H, W, 3), dtype=np.uint8)
    if not mask.any():
        return out
    lo, hi = np.percentile(depth[mask].astype(np.float64), [0.5, 99.5], overwrite_input=True)
    for r0, r1 in _bands(H, W):
        m = mask[r0:r1]
        if not m.any():
            continue
        z = depth[r0:r1][m].astype(np.float64)
        level = np.clip((z - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(z.shape, 0.5)
        rgb = cv2.applyColorMap(np.round(level * 255).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
        n = normals[r0:r1][m].astype(np.float64)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        shade = 0.35 + 0.65 * np.clip(n @ LIGHT, 0.0, 1.0)
        out[r0:r1][m] = np.clip(np.round(rgb * shade[:, None]), 0, 255).astype(np.uint8)
    return out


@dataclass(eq=False)
class Surface:
    """A normal map integrated into a surface (:func:`build_surface`).

    depth: (H, W) float32 heights along +z in pixel units, NaN outside the mask, mean 0
    per 4-connected component (with ``intrinsics``: depth along the optical axis);
    picture: (H, W, 3) uint8 shaded height picture; report: the integration's JSON-ready
    summary (``method``, ``pixels``, ``components``, ``residual_rms``, ``clamped_pixels``,
    ``depth_min``, ``depth_max``, ``vertices``, ``faces``, ``seconds``, ...); normals:
    the (H, W, 3) normal map integrated (the array given, not a copy); mask: (H, W) bool;
    intrinsics: the pinhole K, or None (orthographic); layout: the mesh's
    :class:`MeshLayout`. :attr:`mesh` (a ``trimesh.Trimesh``, layout: module docstring)
    is built from these on first use; :meth:`write` writes the mesh without building it.
    """

    depth: np.ndarray
    picture: np.ndarray
    report: dict
    normals: np.ndarray = field(repr=False)
    mask: np.ndarray = field(repr=False)
    intrinsics: np.ndarray | None = field(default=None, repr=False)
    layout: MeshLayout | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.layout is None:
            self.layout = MeshLayout.of(self.depth, self.mask)

    @functools.cached_property
    def mesh(self):
        """The ``trimesh.Trimesh`` of the surface with vertex normals (module docstring)."""
        return surface_mesh(self.depth, self.normals, self.mask, self.intrinsics)

    def write(self, out_dir) -> dict:
        """Write depth.npy, depth.png and surface.ply into ``out_dir`` (created if missing;
        other files in it are left alone), all renamed into place only once all three are
        complete; surface.ply is written a band of rows at a time. Returns :attr:`report`
        with ``files`` and the total ``seconds``."""
        from cnnps.infra.atomic import atomic_path
        from cnnps.io.images import write_png

        t0 = time.perf_counter()
        out_dir = Path(out_dir)
        if out_dir.exists() and not out_dir.is_dir():
            raise InputError(out_dir, "exists and is not a folder")
        with contextlib.ExitStack() as stack:  # every file complete before any rename
            tmp = {name: stack.enter_context(atomic_path(out_dir / name)) for name in OUTPUT_FILES}
            np.save(tmp["depth.npy"], self.depth)
            write_png(tmp["depth.png"], self.picture)
            with open(tmp["surface.ply"], "wb") as f:
                write_ply(f, self.layout, self.depth, self.normals, self.intrinsics)
        report = dict(self.report)
        report.update(files=list(OUTPUT_FILES), seconds=round(report["seconds"] + time.perf_counter() - t0, 3))
        return report


def build_surface(normals: np.ndarray, mask: np.ndarray, **options) -> Surface:
    """Integrate ``normals`` (H x W x 3, capture frame) over ``mask`` (H x W bool) into a
    :class:`Surface` (depth, picture, report; the mesh on demand); nothing is written.
    ``options`` go to :func:`cnnps.ps.integrate.integrate`. Raises :class:`InputError`
    (bad normals or mask; no path) or ValueError (bad options)."""
    t0 = time.perf_counter()
    result = integrate(normals, mask, **options)
    normals = np.asarray(normals)
    if not np.issubdtype(normals.dtype, np.floating):
        normals = normals.astype(np.float64)
    mask = np.asarray(mask).astype(bool).reshape(result.depth.shape)
    K = options.get("intrinsics")
    if K is not None:
        from cnnps.ps.camera import check_intrinsics

        K = check_intrinsics(K)
    layout = MeshLayout.of(result.depth, mask)
    picture = depth_picture(result.depth if K is None else -result.depth, normals, mask)  # near = red
    report = result.report()
    report["integrate_seconds"] = report.pop("seconds")
    report.update(vertices=layout.vertices, faces=layout.faces, seconds=time.perf_counter() - t0)
    return Surface(result.depth, picture, report, normals, mask, K, layout)


def write_surface_outputs(out_dir: Path, normals: np.ndarray, mask: np.ndarray, **options) -> dict:
    """:func:`build_surface` then :meth:`Surface.write` into ``out_dir``: depth.npy,
    depth.png and surface.ply (what ``cnnps predict --depth`` and ``cnnps integrate``
    write). Returns the report (``method``, ``pixels``, ``components``, ``equations``,
    ``residual_rms`` (pixels), ``clamped_pixels``, ``cg_iterations``, ``depth_min``,
    ``depth_max``, ``vertices``, ``faces``, ``files``, ``seconds`` (all of it) and
    ``integrate_seconds``). Nothing is written when the input or options are bad.
    """
    return build_surface(normals, mask, **options).write(out_dir)
