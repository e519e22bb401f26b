"""Synthetic rendered-scene folders (Lambertian spheres, EXR images) for extract/train tests, no Blender."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cnnps.io.images import write_exr, write_png


def random_lights(rng: np.random.Generator, m: int, min_z: float = 0.05) -> np.ndarray:
    """m unit directions spread over the upper hemisphere (z >= min_z)."""
    z = rng.uniform(min_z, 1.0, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sphere_normals(size: int, radius: float = 0.45, center=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(mask (H,W), normals (H,W,3)) of a sphere; row 0 on top, y up."""
    c = (np.arange(size) + 0.5) / size - 0.5
    x = c[None, :] - center[0]
    y = -c[:, None] - center[1]
    x, y = np.broadcast_arrays(x, y)
    rr = (x**2 + y**2) / radius**2
    mask = rr < 0.97
    z = np.sqrt(np.clip(1 - rr, 0, None))
    n = np.stack([x / radius, y / radius, z], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~mask] = 0
    return mask, n.astype(np.float32)


def make_scene(root: Path, scene_id: str, seed: int, size: int = 24, m: int = 60, view_id: str | None = None) -> Path:
    """Write a rendered-scene folder: Lambertian sphere, m random lights, EXR images."""
    rng = np.random.default_rng(seed)
    d = Path(root) / scene_id
    d.mkdir(parents=True)
    mask, n = sphere_normals(size, radius=rng.uniform(0.3, 0.48), center=rng.uniform(-0.03, 0.03, 2))
    L = random_lights(rng, m)
    albedo = rng.uniform(0.3, 1.0)
    shading = np.clip(np.einsum("hwc,mc->mhw", n, L), 0, None) * albedo
    names = []
    for j in range(m):
        name = f"{j:03d}.exr"
        write_exr(d / name, (shading[j] * mask).astype(np.float32))
        names.append(name)
    (d / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(d / "light_directions.txt", L)
    np.savetxt(d / "light_intensities.txt", np.ones((m, 3)))
    write_png(d / "mask.png", (mask * 255).astype(np.uint8))
    np.save(d / "normal_gt.npy", n)
    meta = {"key": f"{scene_id}-{seed}"}
    if view_id:
        meta["view_id"] = view_id
    (d / "scene.json").write_text(json.dumps(meta))
    return d


def make_render_dir(data_dir: Path, n_scenes: int = 3, size: int = 24, m: int = 60) -> Path:
    for i in range(n_scenes):
        make_scene(data_dir / "render", f"s{i:02d}", seed=100 + i, size=size, m=m)
    return data_dir
