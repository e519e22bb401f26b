"""A tiny extract output of ``layout: observations`` (per-pixel observation files and their
manifest) from synthetic rendered scenes, for the train stage's patch path."""

from __future__ import annotations

import json
from pathlib import Path

from cnnps.io.capture import load_capture
from cnnps.io.observation_store import write_capture_observations
from tests.support.renders import make_render_dir


def make_observation_extract(root: Path, n_scenes: int = 4, size: int = 20, m: int = 40, val_scenes: int = 1,
                             w: int = 16, **params) -> Path:
    """``root`` with ``render/`` (synthetic Lambertian spheres) and ``extract/``: one
    observation file a scene (the last ``val_scenes`` in the val split) and a
    ``manifest.json`` of layout ``observations`` recording ``w`` and the extract
    ``params`` given (the patch loader's settings: min_lights, rotations, ...)."""
    root = Path(root)
    make_render_dir(root, n_scenes=n_scenes, size=size, m=m)
    out = root / "extract"
    shards = []
    folders = sorted((root / "render").iterdir())
    for i, folder in enumerate(folders):
        rec = write_capture_observations(out, folder.name, load_capture(folder), scene_key=f"key-{folder.name}")
        split = "val" if i >= len(folders) - val_scenes else "train"
        shards.append({**rec, "scene": folder.name, "split": split})
    manifest = {"layout": "observations", "w": w, "params": {"w": w, **params}, "shards": shards,
                "train_rows": sum(s["rows"] for s in shards if s["split"] == "train"),
                "val_rows": sum(s["rows"] for s in shards if s["split"] == "val")}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return root
