"""Point lights near the object: the shipped model on analytic spheres under a pinhole
lens and point lights at 1.5x the sphere's size, with the positions used, with the lights
treated as distant, and against the same sphere seen orthographically under distant lights.

    .venv/bin/python -m benchmarks.predict.near_lights_accuracy [--size 64]
        [--out benchmarks/results/predict/near_lights_accuracy.json]

Each sphere (radius 1) fills 80 % of a 40 degree field of view, or 50 % of a 70 degree one
(so that the camera stays nearer the object than the lights), 64 x 64 pixels. 48
point lights sit on a cap of half-angle 60 degrees around the sphere's axis to the camera,
at 3 (1.5 diameters) from its centre, each of unit radiant intensity (irradiance 1 / r^2).
Materials Lambert + Blinn-Phong (isotropic), near-diffuse to shiny, rendered per pixel
with each pixel's own light directions, view and fall-off (attached shadows only: a
convex object). Columns (mean angular error, degrees, K=1, no sparse fill):

- ``orthographic_distant``: the sphere seen orthographically under distant lights from
  the same directions as seen from its centre (the number to stay within 1.5 deg of);
- ``as_directional``: the near-light images, intrinsics used, the lights taken as
  distant from those directions (what ignoring the positions costs);
- ``point_lights``: ``cnnps.predict(..., light_positions=...)``, started from the plane
  at the true median depth (``--distance``), and ``point_lights_default_start``: started
  from the lights' median distance from the camera;
- ``depth_median_rel_error``: the rounds' depth against the true depth along the optical
  axis, median of |d - d_true| / d_true (the scale fixed by the true median depth), and
  ``depth_median_rel_error_default_start`` (scale from the lights' median distance);
- the rounds and their last median relative depth change.
Also the least-squares baseline on a Lambertian sphere with the same rig (shadow
threshold 0, which is exact there).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import cnnps
from benchmarks.harness import Stopwatch, result_path, write_result
from cnnps.ps import camera

MATERIALS = {"lambertian": (0.0, 1), "near-diffuse": (0.3, 10), "glossy": (2.0, 60), "shiny": (8.0, 60)}


def shade(n, v, dirs, scale, spec, exponent):
    """(P, m) Lambert + Blinn-Phong values: n, v (P, 3), dirs (P, m, 3), scale (P, m)."""
    h = dirs + v[:, None]
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    lobe = np.clip(np.einsum("pk,pmk->pm", n, h), 0, None) ** exponent
    cos = np.clip(np.einsum("pk,pmk->pm", n, dirs), 0, None)
    return (cos * (0.5 + spec * lobe) * scale).astype(np.float32)


def rig(size: int, fov: float, fill: float = 0.8, m: int = 48, seed: int = 0):
    """Camera K, sphere centre, light positions (m, 3), pixels hit (rows, cols), their
    points X, normals, views and true depths."""
    f = size / 2 / np.tan(np.radians(fov / 2))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    centre = np.array([0.0, 0.0, -1.0 / np.sin(np.radians(fov / 2 * fill))])
    rows, cols = (a.ravel().astype(float) for a in np.mgrid[0:size, 0:size])
    d = -camera.view_directions(K, rows, cols)
    b = d @ centre
    disc = b**2 - (centre @ centre - 1.0)
    hit = disc > 0
    X = d[hit] * (b[hit] - np.sqrt(disc[hit]))[:, None]
    rng = np.random.default_rng(seed)
    th = np.arccos(rng.uniform(np.cos(np.radians(60)), 1.0, m))  # uniform on the cap
    ph = rng.uniform(0, 2 * np.pi, m)
    positions = centre + 3.0 * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    mask = hit.reshape(size, size)
    return K, centre, positions, mask, X, X - centre, -d[hit], -X[:, 2]


def images_of(mask, values):
    imgs = np.zeros((values.shape[1],) + mask.shape, np.float32)
    imgs[:, mask] = values.T
    return imgs


def normal_map(mask, n):
    out = np.zeros(mask.shape + (3,))
    out[mask] = n
    return out


def ortho_sphere(size: int, fill: float = 0.8):
    r, c = np.mgrid[0:size, 0:size]
    x, y = (c - (size - 1) / 2) / (size / 2 * fill), -(r - (size - 1) / 2) / (size / 2 * fill)
    mask = x * x + y * y < 1
    n = np.column_stack([x[mask], y[mask], np.sqrt(1 - x[mask] ** 2 - y[mask] ** 2)])
    return mask, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    kw = dict(rotations=1, device="cpu", sparse_fill="off")
    rows = []
    for name, (spec, ex) in MATERIALS.items():
        method = "lambertian" if name == "lambertian" else "cnn"
        extra = {"shadow_threshold": 0.0} if method == "lambertian" else kw
        for fov, fill in ((40, 0.8), (70, 0.5)):
            K, centre, pos, mask, X, n, v, d_true = rig(a.size, fov, fill)
            dirs, scale = camera.point_light_directions(X, pos)
            imgs = images_of(mask, shade(n, v, dirs, scale, spec, ex))
            gt = normal_map(mask, n)
            distant = (pos - centre) / np.linalg.norm(pos - centre, axis=1, keepdims=True)
            m_o, n_o = ortho_sphere(a.size, fill)
            P_o = len(n_o)
            I_o = shade(n_o, np.tile([0.0, 0.0, 1.0], (P_o, 1)), np.broadcast_to(distant, (P_o,) + distant.shape),
                        np.ones((P_o, len(distant))), spec, ex)
            ortho = cnnps.predict(images_of(m_o, I_o), distant, m_o, normal_gt=normal_map(m_o, n_o), method=method,
                                  **extra).stats["mean_deg"]
            as_dir = cnnps.predict(imgs, distant, mask, normal_gt=gt, intrinsics=K, method=method,
                                   **extra).stats["mean_deg"]
            true_median = float(np.median(d_true))
            with Stopwatch() as sw:
                near = cnnps.predict(imgs, None, mask, normal_gt=gt, intrinsics=K, light_positions=pos, method=method,
                                     distance=true_median, **extra)
            seconds = sw.seconds
            near_default = cnnps.predict(imgs, None, mask, normal_gt=gt, intrinsics=K, light_positions=pos,
                                         method=method, **extra)

            def depth_err(pred):
                return float(np.median(np.abs(pred.depth[mask] - d_true) / d_true))

            row = {"material": name, "method": method, "spec": spec, "exponent": ex, "fov_deg": fov, "fill": fill,
                   "pixels": int(mask.sum()), "orthographic_distant": round(ortho, 2),
                   "as_directional": round(as_dir, 2), "point_lights": round(near.stats["mean_deg"], 2),
                   "point_lights_default_start": round(near_default.stats["mean_deg"], 2),
                   "depth_median_rel_error": round(depth_err(near), 5),
                   "depth_median_rel_error_default_start": round(depth_err(near_default), 5),
                   "true_median_depth": round(true_median, 4),
                   "default_start_distance": near_default.record["lights"]["start_distance"],
                   "rounds": near.record["lights"]["rounds"], "depth_changes": near.record["lights"]["depth_changes"],
                   "seconds": round(seconds, 2)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_result(a.out, __spec__.name, a, {"rows": rows})


if __name__ == "__main__":
    main()
