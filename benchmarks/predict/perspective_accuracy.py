"""Perspective cameras: the shipped model on analytic spheres seen through a pinhole lens,
with the intrinsics used, ignored, and against the same sphere seen orthographically.

    .venv/bin/python -m benchmarks.predict.perspective_accuracy [--size 48]
        [--out benchmarks/results/predict/perspective_accuracy.json]

Each sphere fills 90 % of the field of view (40 and 70 degrees), 48 x 48 pixels, under 96
lights on a hemisphere about the optical axis (so off-axis pixels also have lights behind
their view plane); materials Lambert + Blinn-Phong (isotropic), from near-diffuse to
glossy; K=1, no sparse fill. Mean angular error in degrees.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.harness import result_path, write_result
from cnnps.models.checkpoint import load_checkpoint
from cnnps.models.inference import predict_normals
from cnnps.models.shipped import weights_path
from cnnps.ps import camera
from cnnps.ps.metrics import angular_error_deg
from cnnps.synth.lights import hemisphere_lights

MATERIALS = {"near-diffuse": (0.3, 10), "glossy": (2.0, 60), "shiny": (8.0, 60), "near-mirror": (20.0, 200)}


def shade(n, v, lights, spec, exponent):
    h = lights[None] + v[:, None]
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    lobe = np.clip(np.einsum("pk,pmk->pm", n, h), 0, None) ** exponent
    return (np.clip(n @ lights.T, 0, None) * (0.5 + spec * lobe)).astype(np.float32)


def perspective_sphere(size, fov_deg, radius=1.2):
    f = size / 2 / np.tan(np.radians(fov_deg / 2))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    center = np.array([0.0, 0.0, -radius / np.sin(np.radians(fov_deg / 2 * 0.9))])
    rows, cols = (a.ravel().astype(float) for a in np.mgrid[0:size, 0:size])
    d = -camera.view_directions(K, rows, cols)
    b = d @ center
    disc = b**2 - (center @ center - radius**2)
    hit = disc > 0
    X = d[hit] * (b[hit] - np.sqrt(disc[hit]))[:, None]
    return (X - center) / radius, -d[hit]


def ortho_sphere(size):
    r, c = np.mgrid[0:size, 0:size]
    x, y = (c.ravel() - (size - 1) / 2) / (size * 0.45), -(r.ravel() - (size - 1) / 2) / (size * 0.45)
    inside = x * x + y * y < 1
    n = np.column_stack([x[inside], y[inside], np.sqrt(1 - x[inside] ** 2 - y[inside] ** 2)])
    return n, np.tile([0.0, 0.0, 1.0], (len(n), 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    net = load_checkpoint(weights_path())[0]
    lights = hemisphere_lights(96, 3.0, seed=4)
    kw = dict(rotations=1, device="cpu", progress=False, sparse_fill="off")
    rows = []
    for name, (spec, ex) in MATERIALS.items():
        n_o, v_o = ortho_sphere(a.size)
        ortho = angular_error_deg(predict_normals(net, shade(n_o, v_o, lights, spec, ex), lights, **kw), n_o).mean()
        for fov in (40, 70):
            n, v = perspective_sphere(a.size, fov)
            I = shade(n, v, lights, spec, ex)
            ignored = angular_error_deg(predict_normals(net, I, lights, **kw), n).mean()
            used = angular_error_deg(predict_normals(net, I, lights, views=v, **kw), n).mean()
            row = {"material": name, "spec": spec, "exponent": ex, "fov_deg": fov, "orthographic": round(ortho, 2),
                   "intrinsics_ignored": round(ignored, 2), "intrinsics_used": round(used, 2)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_result(a.out, __spec__.name, a, {"rows": rows})


if __name__ == "__main__":
    main()
