"""Fixtures shared by the whole suite, and the skip rule for tests that need Blender."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("CNNPS_SHARED", REPO.parent / "shared"))
HAVE_BPY = importlib.util.find_spec("bpy") is not None  # without importing it (slow)


def pytest_configure(config):
    """The suite never writes the user's cache folder (``--precision auto``'s probe answers,
    :mod:`cnnps.models.precision_probe`): one temporary folder per run, inherited by the
    ``cnnps`` processes the tests start."""
    if "CNNPS_CACHE_DIR" not in os.environ:
        import tempfile

        os.environ["CNNPS_CACHE_DIR"] = tempfile.mkdtemp(prefix="cnnps-test-cache-")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``blender`` skip in an install without bpy (``pip install .``, no
    ``[render]`` extra: what ``make test-core`` checks); every other test must pass there."""
    if HAVE_BPY:
        return
    skip = pytest.mark.skip(reason="needs Blender: bpy is not installed (pip install '.[render]')")
    for item in items:
        if item.get_closest_marker("blender") is not None:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """../shared (test data); tests using it skip cleanly when it is absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"shared test data not found at {SHARED} (set CNNPS_SHARED)")
    return SHARED


@pytest.fixture(scope="session")
def ball_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "diligent" / "ballPNG"
    if not path.is_dir():
        pytest.skip(f"DiLiGenT BALL not found at {path}")
    return path


@pytest.fixture(scope="session")
def shared_meshes(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "meshes"
    if not path.is_dir():
        pytest.skip(f"shared meshes not found at {path}")
    return path
