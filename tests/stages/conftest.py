"""Fixtures shared by the stage tests (tests/stages/). ``shared_meshes`` lives in tests/conftest.py."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sphere_mesh():
    """A well-tessellated sphere of radius 0.9 at the origin (icosphere, 20480 faces)."""
    import trimesh

    return trimesh.creation.icosphere(subdivisions=5, radius=0.9)


@pytest.fixture(scope="session")
def views_data_dir(tmp_path_factory) -> Path:
    """A data dir whose ``meshes/`` holds 2 procedural views (a bowl and a holed shape, seed 0),
    written by the meshes stage. Read-only for tests: copy it before running other stages in it."""
    from cnnps.stages import meshes

    data = tmp_path_factory.mktemp("views") / "data"
    meshes.run(meshes.Params(procedural=2, procedural_kinds=("bowl", "holed"), views_per_mesh=1, seed=0), data)
    return data
