"""Fixtures shared by the whole suite."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("CNNPS_SHARED", REPO.parent / "shared"))


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
