"""The mesh a capture is rendered from, as a user names it: a Trimesh, a mesh file or
``procedural:<kind>[:seed]``, with what ``scene.json`` records of it.

Example: ``tm, info = load_mesh_arg("procedural:blob:3")`` (``info == {"mesh": "procedural:blob:3"}``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import file_sha256


def load_mesh_arg(mesh) -> tuple[Any, dict]:
    """A trimesh from a Trimesh, a file path or ``procedural:<kind>[:seed]``."""
    import trimesh

    if isinstance(mesh, trimesh.Trimesh):
        return mesh, {"mesh": "in-memory"}
    text = str(mesh)
    if text.startswith("procedural:"):
        from cnnps.synth.procedural import make_shape

        parts = text.split(":")
        kind = parts[1] if len(parts) > 1 else ""
        try:
            shape_seed = int(parts[2]) if len(parts) > 2 else 0
        except ValueError:
            raise ConfigError(f"procedural mesh seed must be an integer: {text!r}") from None
        return make_shape(kind, shape_seed), {"mesh": text}
    from cnnps.synth.meshes import load_mesh

    path = Path(text)
    return load_mesh(path), {"mesh": str(path), "mesh_sha256": file_sha256(path) if path.is_file() else None}
