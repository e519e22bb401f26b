"""Near point lights on Cycles renders of non-convex objects (cast shadows and
interreflections, full GI): the shipped model with the light positions, with the lights
taken as distant, and on the same object rendered orthographically under distant lights.

    .venv/bin/python -m benchmarks.predict.rig_render_accuracy [--size 96]
        [--out benchmarks/results/predict/rig_render_accuracy.json]

Per object (procedural shapes, one of the materials stage's categories drawn on 20
superpixels with seed 0): 48 lights from the same directions (hemisphere spiral, seed 0),
16 samples, 8 bounces, rendered three ways with `cnnps.render`:

- ``orthographic_distant``: the orthographic camera under suns (the reference);
- ``perspective_distant``: a 40 degree pinhole at distance 5 under suns, predicted with K;
- ``point_lights``: the same pinhole, point lights at 3 from the object's centre (1.5
  object sizes), predicted with the positions, started at the true median depth; and
  ``as_directional``: the same images with the lights taken as distant from the centre.

Mean angular error in degrees (K=1, no sparse fill), and the rounds' depth against
``depth_gt.npy`` (median relative error).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

import cnnps
from benchmarks.harness import result_path, write_result

OBJECTS = (("procedural:bowl", "specular"), ("procedural:holed", "diffuse"), ("procedural:assembly", "metallic"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    kw = dict(lights=48, size=a.size, samples=16, seed=0, progress=False)
    pk = dict(rotations=1, device="cpu", precision="fp32", sparse_fill="off", progress=False)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for mesh, material in OBJECTS:
            name = mesh.split(":")[1]
            ortho = cnnps.render(mesh, tmp / f"{name}-o", material=material, **kw)
            persp = cnnps.render(mesh, tmp / f"{name}-p", material=material, fov_deg=40, **kw)
            near = cnnps.render(mesh, tmp / f"{name}-n", material=material, fov_deg=40, light_distance=3.0, **kw)
            depth = np.load(near / "depth_gt.npy")
            mask = np.isfinite(depth)
            r_o = cnnps.predict_folder(ortho, tmp / f"{name}-o-out", **pk)
            r_p = cnnps.predict_folder(persp, tmp / f"{name}-p-out", **pk)
            r_n = cnnps.predict_folder(near, tmp / f"{name}-n-out", distance=float(np.median(depth[mask])),
                                       depth=True, **pk)
            flat = tmp / f"{name}-flat"
            shutil.copytree(near, flat)
            shutil.copy(persp / "light_directions.txt", flat / "light_directions.txt")
            (flat / "light_positions.txt").unlink()
            r_d = cnnps.predict_folder(flat, tmp / f"{name}-d-out", **pk)
            got = np.load(tmp / f"{name}-n-out" / "depth.npy")
            row = {"object": mesh, "material": material, "pixels_orthographic": r_o["pixels"],
                   "pixels_perspective": r_n["pixels"],
                   "orthographic_distant": round(r_o["mean_deg"], 2), "perspective_distant": round(r_p["mean_deg"], 2),
                   "point_lights": round(r_n["mean_deg"], 2), "as_directional": round(r_d["mean_deg"], 2),
                   "depth_median_rel_error": round(float(np.median(np.abs(got[mask] - depth[mask]) / depth[mask])), 5),
                   "rounds": r_n["lights"]["rounds"], "depth_changes": r_n["lights"]["depth_changes"]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_result(a.out, __spec__.name, a, {"rows": rows})


if __name__ == "__main__":
    main()
