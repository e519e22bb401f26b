"""Small mesh files for pipeline tests."""

from __future__ import annotations

from pathlib import Path


def write_tiny_mesh(path: Path, subdivisions: int = 2, kind: str = "sphere") -> Path:
    """A small mesh file (an icosphere, or a capsule for a second, different mesh)."""
    import trimesh

    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    else:
        mesh = trimesh.creation.capsule(height=1.0, radius=0.5, count=[16, 16])
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(str(path))
    return path
