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
- ``surface.ply``: a binary PLY triangle mesh (trimesh) with vertex normals. Its vertices
  are the centres of the mask pixels that belong to a triangle, at
  x = column - (W - 1) / 2, y = (H - 1) / 2 - row, z = depth (pixel units, the capture
  frame, centred on the image), with the input normals as vertex normals. Every 2 x 2
  block of pixel centres gives two triangles when all four are in the mask and one when
  three are (so diagonal mask borders stay smooth); faces wind counter-clockwise seen
  from +z, so their normals face the camera. Mask pixels with no 2 x 2 block around them
  (isolated pixels, one-pixel-wide lines) carry no triangle and are left out. With a
  pinhole camera the vertices are the 3D points depth x diag(1, -1, -1) K^-1 (u, v, 1)
  (the capture frame, camera at the origin, the object at z < 0).

The three files are all written under temporary names first and renamed into place
only when every one of them is complete (:mod:`cnnps.infra.atomic`): a failure leaves the
folder as it was.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
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


def surface_mesh(depth: np.ndarray, normals: np.ndarray, mask: np.ndarray, intrinsics=None):
    """A ``trimesh.Trimesh`` of the masked height field, or with ``intrinsics`` (a pinhole
    K) of the depth map's 3D points (layout: module docstring)."""
    import trimesh

    mask = np.asarray(mask, dtype=bool) & np.isfinite(depth)
    H, W = mask.shape
    index = np.full((H, W), -1, dtype=np.int64)
    rows, cols = np.nonzero(mask)
    index[rows, cols] = np.arange(rows.size)
    # corners of each 2 x 2 block: a top-left, b top-right, d bottom-left, e bottom-right
    a, b = index[:-1, :-1], index[:-1, 1:]
    d, e = index[1:, :-1], index[1:, 1:]
    A, B, D, E = a >= 0, b >= 0, d >= 0, e >= 0
    full = A & B & D & E
    tris = [
        # all four: split along the b-d diagonal; (a, d, b) and (b, d, e) are counter-clockwise from +z
        np.stack([a[full], d[full], b[full]], 1),
        np.stack([b[full], d[full], e[full]], 1),
        # exactly three: the triangle of the three present corners, same orientation
        _three(~E & A & B & D, a, d, b),
        _three(~D & A & B & E, a, e, b),
        _three(~B & A & D & E, a, d, e),
        _three(~A & B & D & E, b, d, e),
    ]
    faces = np.concatenate(tris, axis=0)
    used = np.zeros(rows.size, dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    faces = remap[faces]
    r, c = rows[used], cols[used]
    if intrinsics is None:
        vertices = np.stack([c - (W - 1) / 2.0, (H - 1) / 2.0 - r, depth[r, c].astype(np.float64)], axis=1)
    else:
        from cnnps.ps.camera import pixel_rays

        vertices = pixel_rays(intrinsics, r, c) * depth[r, c].astype(np.float64)[:, None]
    n = np.asarray(normals, dtype=np.float64)[r, c]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_normals=n, process=False, validate=False)


def _three(sel: np.ndarray, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    return np.stack([i[sel], j[sel], k[sel]], 1)


def depth_picture(depth: np.ndarray, normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """uint8 RGB (H, W, 3): heights colour-mapped (TURBO, low = blue), times a Lambertian
    shading 0.35 + 0.65 max(0, n . l) of the normals; black outside the mask."""
    import cv2

    mask = np.asarray(mask, dtype=bool) & np.isfinite(depth)
    out = np.zeros(depth.shape + (3,), dtype=np.uint8)
    if not mask.any():
        return out
    z = depth[mask].astype(np.float64)
    lo, hi = np.percentile(z, [0.5, 99.5])
    level = np.clip((z - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(z.shape, 0.5)
    rgb = cv2.applyColorMap(np.round(level * 255).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    n = np.asarray(normals, dtype=np.float64)[mask]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    shade = 0.35 + 0.65 * np.clip(n @ LIGHT, 0.0, 1.0)
    out[mask] = np.clip(np.round(rgb * shade[:, None]), 0, 255).astype(np.uint8)
    return out


@dataclass
class Surface:
    """A normal map integrated into a surface (:func:`build_surface`).

    depth: (H, W) float32 heights along +z in pixel units, NaN outside the mask, mean 0
    per 4-connected component; mesh: a ``trimesh.Trimesh`` of the masked height field
    (layout: module docstring); picture: (H, W, 3) uint8 shaded height picture; report:
    the integration's JSON-ready summary (``method``, ``pixels``, ``components``,
    ``residual_rms``, ``clamped_pixels``, ``depth_min``, ``depth_max``, ``vertices``,
    ``faces``, ``seconds``, ...).
    """

    depth: np.ndarray
    mesh: object
    picture: np.ndarray
    report: dict

    def write(self, out_dir) -> dict:
        """Write depth.npy, depth.png and surface.ply into ``out_dir`` (created if missing;
        other files in it are left alone), all renamed into place only once all three are
        complete. Returns :attr:`report` with ``files`` and the total ``seconds``."""
        from cnnps.infra.atomic import atomic_path
        from cnnps.io.images import write_png

        t0 = time.perf_counter()
        out_dir = Path(out_dir)
        ply = self.mesh.export(file_type="ply", encoding="binary", vertex_normal=True)
        if out_dir.exists() and not out_dir.is_dir():
            raise InputError(out_dir, "exists and is not a folder")
        with contextlib.ExitStack() as stack:  # every file complete before any rename
            tmp = {name: stack.enter_context(atomic_path(out_dir / name)) for name in OUTPUT_FILES}
            np.save(tmp["depth.npy"], self.depth)
            write_png(tmp["depth.png"], self.picture)
            tmp["surface.ply"].write_bytes(ply)
        report = dict(self.report)
        report.update(files=list(OUTPUT_FILES), seconds=round(report["seconds"] + time.perf_counter() - t0, 3))
        return report


def build_surface(normals: np.ndarray, mask: np.ndarray, **options) -> Surface:
    """Integrate ``normals`` (H x W x 3, capture frame) over ``mask`` (H x W bool) into a
    :class:`Surface` (depth, mesh, picture, report); nothing is written. ``options`` go to
    :func:`cnnps.ps.integrate.integrate`. Raises :class:`InputError` (bad normals or
    mask; no path) or ValueError (bad options)."""
    t0 = time.perf_counter()
    result = integrate(normals, mask, **options)
    normals = np.asarray(normals, dtype=np.float64)
    mask = np.asarray(mask).astype(bool).reshape(result.depth.shape)
    K = options.get("intrinsics")
    mesh = surface_mesh(result.depth, normals, mask, K)
    picture = depth_picture(result.depth if K is None else -result.depth, normals, mask)  # near = red
    report = result.report()
    report["integrate_seconds"] = report.pop("seconds")
    report.update(vertices=len(mesh.vertices), faces=len(mesh.faces), seconds=time.perf_counter() - t0)
    return Surface(result.depth, mesh, picture, report)


def write_surface_outputs(out_dir: Path, normals: np.ndarray, mask: np.ndarray, **options) -> dict:
    """:func:`build_surface` then :meth:`Surface.write` into ``out_dir``: depth.npy,
    depth.png and surface.ply (what ``cnnps predict --depth`` and ``cnnps integrate``
    write). Returns the report (``method``, ``pixels``, ``components``, ``equations``,
    ``residual_rms`` (pixels), ``clamped_pixels``, ``cg_iterations``, ``depth_min``,
    ``depth_max``, ``vertices``, ``faces``, ``files``, ``seconds`` (all of it) and
    ``integrate_seconds``). Nothing is written when the input or options are bad.
    """
    return build_surface(normals, mask, **options).write(out_dir)
