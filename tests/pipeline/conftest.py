"""Fixtures of the pipeline tests: a tiny params.yaml that runs every stage in seconds."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.meshes import write_tiny_mesh


def tiny_params(mesh_dir: Path) -> dict:
    """Every stage at the smallest useful size: 16x16 images, 12 lights, 1 sample."""
    return {
        "seed": 0,
        "data_dir": "data",
        "executor": {"kind": "local", "workers": 1},
        "meshes": {"mesh_dir": str(mesh_dir), "procedural": 0, "views_per_mesh": 1},
        "materials": {"size": 16, "superpixels": 8, "categories": ["diffuse", "specular"], "ranges": {}, "workers": 1},
        "render": {"size": 16, "samples": 1, "lights": 12, "max_bounces": 2, "workers": 1},
        # every key dvc.yaml's stages list is written (DVC refuses a listed key a params file leaves out)
        "extract": {"w": 32, "min_lights": 6, "max_lights": 12, "cone_min_deg": 20.0, "cone_max_deg": 90.0,
                    "sparse_min_lights": 6, "rotations": 1, "val_fraction": 0.5},
        "train": {"epochs": 1, "max_steps": 4, "val_every": 0, "val_max_rows": 200, "checkpoint_every": 2,
                  "log_every": 1, "progress": False, "data": {"batch_size": 16, "shuffle_buffer": 256}},
        "eval": {"test_shapes": ["sphere"], "superpixels": 4, "categories": ["specular"], "light_sets": [8],
                 "size": 16, "samples": 1, "rotations": [1, 2]},
    }


@pytest.fixture
def tiny_setup(tmp_path):
    """(params dict, folder) with one tiny mesh in ``folder/meshes_in``."""
    mesh_dir = tmp_path / "meshes_in"
    write_tiny_mesh(mesh_dir / "ball.obj")
    return tiny_params(mesh_dir), tmp_path
