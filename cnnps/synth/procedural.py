"""Seeded procedural shapes that are NOT convex: cast shadows and inter-reflections.

``make_shape(kind, seed)`` returns a mesh centred at the origin and scaled into the
sphere of radius :data:`cnnps.synth.meshes.RADIUS`; the same ``(kind, seed)`` always gives the
same mesh (only NumPy generators seeded from ``seed``; marching cubes is deterministic).
Nothing is downloaded.

Kinds (:data:`PROCEDURAL_KINDS`):

- ``blob``: metaballs: iso-surface of a sum of 4–9 Gaussian bumps with random centres,
  radii and a few negative (carving) bumps; lobes and creases.
- ``bowl``: a cup or bowl: a thick spherical or cylindrical shell cut open at the top
  (deep cavity), sometimes with a handle (torus); implicit surface, watertight.
- ``assembly``: 3–7 overlapping primitives (spheres, boxes, cylinders, capsules, tori)
  at random poses, concatenated (not a manifold boolean: hidden inner surfaces stay,
  which is harmless for opaque rendering).
- ``bumpy``: an icosphere displaced along its normals by random low-frequency noise
  (sums of 3-D sinusoids) deep enough to make valleys.
- ``holed``: a rounded box or ellipsoid pierced by 1–3 cylindrical through-holes, or a
  genus-2 "pretzel" of two fused tori (implicit surface, watertight).

Implicit kinds are meshed with ``skimage.measure.marching_cubes`` on a 72³ grid
(about 20–60 k faces).
"""

from __future__ import annotations

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from cnnps.infra.errors import ConfigError
from cnnps.synth.meshes import normalize_mesh, random_rotation

PROCEDURAL_KINDS = ("blob", "bowl", "assembly", "bumpy", "holed")
GRID = 72  # marching-cubes resolution per axis
MAX_CONVEXITY = 0.9  # redraw a watertight shape whose volume / hull volume is above this
MAX_TRIES = 8


# --------------------------------------------------------------------------- helpers


def _grid(n: int = GRID, extent: float = 1.2):
    t = np.linspace(-extent, extent, n)
    x, y, z = np.meshgrid(t, t, t, indexing="ij")
    return x, y, z, t[1] - t[0], extent


def _mesh_from_field(field: np.ndarray, spacing: float, extent: float, level: float = 0.0, inside_negative: bool = True):
    """Mesh the iso-surface ``field == level``; outward normals (inside is ``field < level``)."""
    f = field if inside_negative else -field
    lv = level if inside_negative else -level
    # pad with "outside" so the surface is closed even if it touches the grid border
    f = np.pad(f, 1, mode="constant", constant_values=max(float(f.max()), lv + 1.0))
    verts, faces, _, _ = marching_cubes(f.astype(np.float32), level=lv, spacing=(spacing,) * 3)
    verts = verts - (extent + spacing)
    mesh = trimesh.Trimesh(verts, faces, process=True)
    # marching_cubes' winding depends on the gradient direction: make normals outward
    trimesh.repair.fix_normals(mesh, multibody=True)
    return mesh


def _smin(a, b, k):
    """Polynomial smooth minimum (smooth union of two distance fields)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _sd_torus(px, py, pz, R, r):
    q = np.sqrt(px**2 + pz**2) - R
    return np.sqrt(q**2 + py**2) - r


def _apply(R, x, y, z, c=(0.0, 0.0, 0.0)):
    """Coordinates of the grid points in a frame rotated by R (R.T @ (p - c))."""
    px, py, pz = x - c[0], y - c[1], z - c[2]
    return (
        R[0, 0] * px + R[1, 0] * py + R[2, 0] * pz,
        R[0, 1] * px + R[1, 1] * py + R[2, 1] * pz,
        R[0, 2] * px + R[1, 2] * py + R[2, 2] * pz,
    )


# --------------------------------------------------------------------------- kinds


def _blob(rng):
    x, y, z, h, ext = _grid()
    n = int(rng.integers(4, 10))
    field = np.zeros_like(x)
    centres = rng.uniform(-0.55, 0.55, size=(n, 3))
    for i in range(n):
        s = rng.uniform(0.14, 0.32)
        w = 1.0 if i < max(3, n - 2) else -rng.uniform(0.4, 0.9)  # a few carving bumps
        d2 = (x - centres[i, 0]) ** 2 + (y - centres[i, 1]) ** 2 + (z - centres[i, 2]) ** 2
        field += w * np.exp(-d2 / (2 * s * s))
    return _mesh_from_field(field, h, ext, level=0.45, inside_negative=False)


def _bowl(rng):
    x, y, z, h, ext = _grid()
    R = rng.uniform(0.6, 0.85)
    t = rng.uniform(0.06, 0.12)
    if rng.random() < 0.5:  # spherical bowl cut at height `cut`
        shell = np.abs(np.sqrt(x**2 + y**2 + z**2) - R) - t / 2
        cut = rng.uniform(-0.1, 0.35) * R
        field = np.maximum(shell, y - cut)
    else:  # cylindrical cup with a bottom, open top
        height = rng.uniform(0.5, 0.8)
        rad = np.sqrt(x**2 + z**2)
        outer = np.maximum(rad - R, np.abs(y) - height)
        inner = np.maximum(rad - (R - t), -(y - (-height + t)))  # cavity above the bottom
        field = np.maximum(outer, -inner)
    if rng.random() < 0.6:  # handle
        hy = rng.uniform(-0.2, 0.1)
        handle = _sd_torus(x - (R + 0.12), y - hy, z, 0.25, 0.055)
        handle = np.maximum(handle, -(x - R))  # only the outer half
        field = np.minimum(field, handle)
    return _mesh_from_field(field, h, ext)


def _assembly(rng):
    n = int(rng.integers(3, 8))
    parts = []
    for i in range(n):
        kind = rng.choice(["sphere", "box", "cylinder", "capsule", "torus"])
        size = rng.uniform(0.25, 0.6)
        if kind == "sphere":
            m = trimesh.creation.icosphere(subdivisions=4, radius=size * 0.7)
        elif kind == "box":
            m = trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3) * size * 1.6)
            m = m.subdivide().subdivide()
        elif kind == "cylinder":
            m = trimesh.creation.cylinder(radius=size * 0.35, height=size * 2.0, sections=48)
        elif kind == "capsule":
            m = trimesh.creation.capsule(radius=size * 0.3, height=size * 1.5, count=[32, 32])
        else:
            m = trimesh.creation.torus(major_radius=size * 0.7, minor_radius=size * rng.uniform(0.15, 0.3), major_sections=64, minor_sections=24)
        T = np.eye(4)
        T[:3, :3] = random_rotation(rng)
        # first part at the centre; the others overlap a previous one
        if i == 0:
            T[:3, 3] = rng.uniform(-0.1, 0.1, 3)
        else:
            anchor = parts[int(rng.integers(0, len(parts)))]
            c = anchor.vertices.mean(axis=0)
            T[:3, 3] = c + rng.standard_normal(3) / np.sqrt(3) * rng.uniform(0.3, 0.6)
        m.apply_transform(T)
        parts.append(m)
    mesh = trimesh.util.concatenate(parts)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)


def _bumpy(rng):
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = np.asarray(mesh.vertices)
    k = int(rng.integers(6, 14))
    freqs = rng.standard_normal((k, 3)) * rng.uniform(2.0, 5.0, (k, 1))
    phases = rng.uniform(0, 2 * np.pi, k)
    amps = rng.uniform(0.5, 1.0, k) / np.sqrt(k)
    disp = (amps[None, :] * np.sin(v @ freqs.T + phases[None, :])).sum(axis=1)
    disp = disp / (np.abs(disp).max() + 1e-12) * rng.uniform(0.3, 0.45)
    return trimesh.Trimesh(v * (1.0 + disp)[:, None], mesh.faces, process=True)


def _holed(rng):
    x, y, z, h, ext = _grid()
    if rng.random() < 0.3:  # genus-2 "pretzel": two fused tori
        R, r = rng.uniform(0.33, 0.42), rng.uniform(0.1, 0.16)
        a = _sd_torus(x - R, z, y, R, r)
        b = _sd_torus(x + R, z, y, R, r)
        field = _smin(a, b, 0.08)
    else:
        rot = random_rotation(rng)
        px, py, pz = _apply(rot, x, y, z)
        e = rng.uniform(0.5, 0.85, 3)
        if rng.random() < 0.5:  # rounded box
            q = np.stack([np.abs(px) - e[0], np.abs(py) - e[1], np.abs(pz) - e[2]])
            rr = 0.1
            q = q + rr
            field = np.linalg.norm(np.maximum(q, 0), axis=0) + np.minimum(q.max(axis=0), 0) - rr
        else:  # ellipsoid (approximate distance)
            k0 = np.sqrt((px / e[0]) ** 2 + (py / e[1]) ** 2 + (pz / e[2]) ** 2)
            field = (k0 - 1.0) * e.min()
        n_holes = int(rng.integers(1, 4))
        for _ in range(n_holes):
            d = rng.standard_normal(3)
            d /= np.linalg.norm(d)
            c = rng.uniform(-0.25, 0.25, 3)
            rad = rng.uniform(0.15, 0.3)
            # distance to the infinite line through c along d
            qx, qy, qz = x - c[0], y - c[1], z - c[2]
            along = qx * d[0] + qy * d[1] + qz * d[2]
            dist = np.sqrt(np.maximum(qx**2 + qy**2 + qz**2 - along**2, 0))
            field = np.maximum(field, -(dist - rad))
    return _mesh_from_field(field, h, ext)


_MAKERS = {"blob": _blob, "bowl": _bowl, "assembly": _assembly, "bumpy": _bumpy, "holed": _holed}


def make_shape(kind: str, seed: int) -> trimesh.Trimesh:
    """A seeded non-convex shape of ``kind``, centred and scaled into the unit sphere (radius 0.95)."""
    if kind not in _MAKERS:
        raise ConfigError(f"unknown procedural kind {kind!r} (choose from {', '.join(PROCEDURAL_KINDS)})")
    rng = np.random.default_rng([int(seed), PROCEDURAL_KINDS.index(kind)])
    # Redraw (same generator, so still deterministic) while a watertight draw is nearly
    # convex: volume / convex-hull volume above MAX_CONVEXITY.
    for _ in range(MAX_TRIES):
        mesh = _MAKERS[kind](rng)
        if not mesh.is_watertight or len(mesh.split(only_watertight=False)) > 1:
            break  # assemblies: overlapping parts, the volume ratio means nothing
        if mesh.volume / mesh.convex_hull.volume <= MAX_CONVEXITY:
            break
    # keep only components with a real area (marching cubes can leave specks)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        areas = np.array([p.area for p in parts])
        keep = [p for p, a in zip(parts, areas) if a > 0.01 * areas.max()]
        mesh = trimesh.util.concatenate(keep)
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    return normalize_mesh(mesh)
