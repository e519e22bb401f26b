"""What a real rig costs, measured by the eval stage on its own test set: every capture
rendered orthographically under distant lights and again through a rig (``eval.rig``),
and, for the perspective-only rigs, the intrinsics used against ignored at K = 1 and 10.

    .venv/bin/python -m benchmarks.predict.rig_eval_accuracy [--data DIR]
        [--out benchmarks/results/predict/rig_eval_accuracy.json]

The test set: sphere, bowl and holed shapes, specular and metallic, 40 lights, 64 pixels,
8 samples, the shipped model at K = 1 (``rotations: [1]``). The rigs:

- ``fov40`` and ``fov70``: a pinhole camera of that field of view, distant lights;
- ``fov40-point3``: the 40-degree camera and point lights 3 object radii from the
  object's centre (1.5 object sizes: the issue's "near" rig, the eval stage's default);
- ``fov40-point1.5``: point lights at 1.5 radii, half an object size from its surface.

The twins are rendered so that the object spans as many pixels as in its 64-pixel
orthographic capture (116 pixels at 40 degrees, 224 at 70). Per rig: every method's mean
error on each twin and its orthographic capture, ``rig_minus_ortho``, and the rounds'
depth error. For the distant-light rigs also ``intrinsics_used`` / ``intrinsics_ignored``
(the same twin predicted as if orthographic) at K = 1 and K = 10, with ``cnnps predict``'s
defaults otherwise (the Lambertian fill is on below 50 images, as in the eval stage).

``--data DIR`` keeps the renders there (default a temporary folder): a rerun renders no
orthographic capture again, but each rig's twins again except the last's, since the eval
stage clears the twins of any other rig from its test set.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from benchmarks.harness import ROOT, result_path, write_result

RIGS = {"fov40": (40.0, None), "fov70": (70.0, None), "fov40-point3": (40.0, 3.0), "fov40-point1.5": (40.0, 1.5)}


def eval_params(data: Path, model: Path, fov: float, distance: float | None) -> dict:
    return {"seed": 0, "data_dir": str(data), "meshes": {"procedural": 1},
            "eval": {"test_shapes": ["sphere", "bowl", "holed"], "categories": ["specular", "metallic"],
                     "light_sets": [40], "size": 64, "samples": 8, "rotations": [1], "model": str(model),
                     "rig": {"fov_deg": fov, "light_distance": distance}}}


def used_and_ignored(folder: Path, model, rotations: int) -> dict:
    """Mean error of a perspective, distant-light twin with its intrinsics and without."""
    from cnnps.io.capture import load_capture, read_intrinsics
    from cnnps.models.inference import predict_normals
    from cnnps.ps.camera import view_directions

    kw = dict(device="cpu", precision="fp32", progress=False)  # sparse fill 'auto', as `cnnps predict`
    cap = load_capture(folder)
    rows, cols = np.nonzero(cap.mask)
    views = view_directions(read_intrinsics(cap.root / "intrinsics.txt"), rows.astype(float), cols.astype(float))
    gt = cap.normal_gt[cap.mask].astype(np.float64)
    intensities = cap.pixel_intensities()

    def err(n):
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        return round(float(np.degrees(np.arccos(np.clip((n * gt).sum(1), -1, 1))).mean()), 2)

    return {"intrinsics_used": err(predict_normals(model, intensities, cap.lights, rotations, views=views, **kw)),
            "intrinsics_ignored": err(predict_normals(model, intensities, cap.lights, rotations, **kw))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--model", type=Path, default=ROOT / "cnnps/models/weights/cnnps_default.pt")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    from cnnps.models.checkpoint import load_checkpoint

    model = load_checkpoint(a.model)[0]
    with tempfile.TemporaryDirectory() as tmp:
        data = (a.data or Path(tmp) / "data").resolve()
        data.mkdir(parents=True, exist_ok=True)
        rigs = {}
        for name, (fov, distance) in RIGS.items():
            params = data / f"params-{name}.yaml"
            params.write_text(yaml.safe_dump(eval_params(data, a.model.resolve(), fov, distance)))
            env = dict(os.environ, PYTHONPATH=str(ROOT))
            subprocess.run([sys.executable, "-m", "cnnps", "run-stage", "eval", "--params", str(params)],
                           check=True, env=env, cwd=ROOT)
            metrics = json.loads((data / "eval" / "metrics.json").read_text())
            captures = {}
            for cap, r in metrics["captures"].items():
                if r["kind"] != "rig":
                    continue
                ortho = cap.rsplit("-fov", 1)[0]
                row = {m: {"rig": round(v["mean_deg"], 2),
                           "orthographic": round(metrics["captures"][ortho]["methods"][m]["mean_deg"], 2),
                           **({"depth_median_rel_error": round(v["depth_median_rel_error"], 5)}
                              if "depth_median_rel_error" in v else {})}
                       for m, v in r["methods"].items()}
                if distance is None:
                    folder = data / "eval" / "testset" / cap
                    row["k1"] = used_and_ignored(folder, model, 1)
                    row["k10"] = used_and_ignored(folder, model, 10)
                captures[cap] = row
                print(cap, json.dumps(row), flush=True)
            rigs[name] = {"fov_deg": fov, "light_distance_radii": distance, "captures": captures,
                          "rig_minus_ortho": {m: round(v["mean_deg"], 2) for m, v in metrics["rig_minus_ortho"].items()}}
            for k in ("k1", "k10"):
                if distance is None:
                    for which in ("intrinsics_used", "intrinsics_ignored"):
                        rigs[name][f"{which}_{k}_mean"] = round(float(np.mean([c[k][which] for c in captures.values()])), 2)
            print(name, json.dumps({k: v for k, v in rigs[name].items() if k != "captures"}), flush=True)
    model_name = str(a.model.resolve().relative_to(ROOT)) if a.model.resolve().is_relative_to(ROOT) else str(a.model)
    write_result(a.out, __spec__.name, a, {"model": model_name, "rigs": rigs})


if __name__ == "__main__":
    main()
