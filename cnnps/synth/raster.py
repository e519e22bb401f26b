"""An orthographic z-buffer rasteriser in NumPy: mask, normals, depth and face per pixel.

The camera looks down −z and covers x, y ∈ [−1, 1]; pixel (r, c) samples its centre
x = −1 + (c + ½)·2/S, y = 1 − (r + ½)·2/S (row 0 on top), as Cycles does with the
0.01 px Gaussian pixel filter. The first hit is the largest z. The normal is the smooth
one: vertex normals (angle-weighted, as Blender computes them) interpolated with the
barycentrics of the hit and normalised. **Flip rule:** when the hit face is seen from
behind (its geometric normal has n_z < 0: open meshes, inconsistent winding, a mesh
turned inside out) the normal is negated, as Cycles does for back-facing hits. The smooth
normal of a front face can still have a slightly negative n_z at silhouettes (a few
pixels); it is kept as it is, since it is the normal the renderer shades with. Zeros
outside the mask.

trimesh's ray module needs rtree/embree (not installed) and is far slower; this
rasteriser is single-threaded NumPy, the work cut into chunks of :data:`_CHUNK`
candidate (triangle, pixel) pairs (its speed: docs/performance.md#other-commands).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_CHUNK = 1 << 22  # candidate (triangle, pixel) pairs per rasterisation chunk (~4 M)


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
