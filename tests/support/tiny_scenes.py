"""Tiny Cycles scenes for the renderer tests: 32 x 32 pixels, 2 threads, a sphere."""

from __future__ import annotations

S = 32  # image size in pixels
THREADS = 2


def sphere(radius: float = 0.9):
    """A smooth icosphere (5120 faces) centred at the origin."""
    import trimesh

    return trimesh.creation.icosphere(subdivisions=4, radius=radius)
