"""Mesh loading, cleaning, normalising and posing (trimesh), for the meshes stage and the renderer.

- :func:`load_mesh` reads OBJ, PLY, OFF, STL, glTF/GLB with trimesh (scenes merged into
  one mesh), then :func:`clean_mesh` drops degenerate and duplicate faces and
  unreferenced vertices, merges vertices by position (texture seams would otherwise
  break smooth shading), makes the winding consistent and the normals point outward
  (``trimesh.repair``), and :func:`normalize_mesh` centres it on its bounding-box centre
  and scales it so the largest vertex norm is :data:`RADIUS` (0.95: any rotation of the
  mesh then projects inside the orthographic camera's x, y in [-1, 1] with a 2.5 % margin).
- :func:`random_rotation` draws a uniform random rotation (seeded generator);
  :func:`pose_mesh` applies it (vertices ``v @ R.T``; the origin stays fixed, so the posed
  mesh stays inside the sphere of radius :data:`RADIUS`).
- :func:`read_view_mesh` reads back the posed ``mesh.ply`` of a view folder as written
  (no cleaning, no normalising).

Frame: camera frame, x right, y up, z toward the camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from cnnps.infra.errors import InputError

RADIUS = 0.95  # largest vertex norm after normalisation (unit sphere with a margin)
MESH_EXTENSIONS = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def normalize_mesh(mesh: trimesh.Trimesh, radius: float = RADIUS, path=None) -> trimesh.Trimesh:
    """Centre ``mesh`` on its bounding-box centre and scale its largest vertex norm to ``radius``."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if len(vertices) == 0 or len(mesh.faces) == 0:
        raise InputError(path, "mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has non-finite vertex coordinates")
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
    vertices = vertices - centre
    r = float(np.linalg.norm(vertices, axis=1).max())
    if not r > 0:
        raise InputError(path, "mesh is degenerate (all vertices coincide)")
    return trimesh.Trimesh(vertices * (radius / r), np.asarray(mesh.faces), process=False)


def clean_mesh(mesh: trimesh.Trimesh, path=None) -> trimesh.Trimesh:
    """Merge vertices by position, drop degenerate/duplicate faces, fix winding and normals."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        raise InputError(path, "mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has non-finite vertex coordinates")
    # A fresh mesh without visuals: process=True merges vertices by position only.
    m = trimesh.Trimesh(vertices, faces, process=True, validate=False)
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    if len(m.faces) == 0:
        raise InputError(path, "mesh is degenerate (every face has zero area)")
    if not m.area > 0:
        raise InputError(path, "mesh is degenerate (zero surface area)")
    if not m.is_winding_consistent:  # slow on large meshes (graph traversal): only when needed
        trimesh.repair.fix_winding(m)
    trimesh.repair.fix_normals(m, multibody=True)
    return m


def load_mesh(path: str | Path, radius: float = RADIUS) -> trimesh.Trimesh:
    """Read a mesh file, clean it and normalise it into the sphere of radius ``radius``.

    Raises :class:`InputError` naming ``path`` for a missing, unreadable, empty or
    degenerate file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    if path.suffix.lower() not in MESH_EXTENSIONS:
        raise InputError(path, f"unsupported mesh format {path.suffix!r} (use {', '.join(MESH_EXTENSIONS)})")
    if path.stat().st_size == 0:
        raise InputError(path, "mesh file is empty")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for bad files
        raise InputError(path, f"cannot read mesh: {type(exc).__name__}: {exc}".splitlines()[0]) from None
    if isinstance(loaded, trimesh.Scene):  # force='mesh' may still hand back an empty scene
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not geoms:
            raise InputError(path, "mesh file holds no triangles")
        loaded = trimesh.util.concatenate(geoms)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputError(path, "mesh file holds no triangles")
    return normalize_mesh(clean_mesh(loaded, path), radius, path)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix drawn uniformly from SO(3) (normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    while np.linalg.norm(q) < 1e-8:  # pragma: no cover - probability ~0
        q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_mesh(mesh: trimesh.Trimesh, rotation: np.ndarray) -> trimesh.Trimesh:
    """A copy of ``mesh`` rotated about the origin: vertices ``v @ rotation.T``."""
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape != (3, 3):
        raise ValueError(f"rotation must be 3x3, got {rotation.shape}")
    return trimesh.Trimesh(np.asarray(mesh.vertices) @ rotation.T, np.asarray(mesh.faces).copy(), process=False)


def read_view_mesh(view_dir: str | Path) -> trimesh.Trimesh:
    """Read the posed ``mesh.ply`` of a view folder (written by the meshes stage) as it is."""
    path = Path(view_dir) / "mesh.ply"
    if not path.is_file():
        raise InputError(path, "view mesh not found (run the meshes stage)")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:
        raise InputError(path, f"cannot read mesh: {type(exc).__name__}: {exc}".splitlines()[0]) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "view mesh holds no triangles")
    return mesh
