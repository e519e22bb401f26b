"""Time and disk of ``presets/full.yaml`` (the paper's scale) from the measured rates.

    .venv/bin/python tools/estimate_full.py [--meshes 25] [--gpus 1 8] [--out benchmarks/results/full_estimate.json]

Nothing is run: this multiplies the preset's sizes by rates measured elsewhere and says
where each rate comes from (docs/cluster.md, "The paper's scale on paper", shows the
table). Inputs:

- scenes: (``--meshes`` + the preset's procedural shapes) x views x categories;
- mask pixels per scene: the preset's image size squared x the object's share of the
  image, measured on the v3 training renders (rows / (scenes x rotations x size^2));
- render: path samples = images x pixels x samples per pixel, at the in-process rate of
  ``benchmarks/results/render.json`` (Cycles on this machine's CPU); no GPU rate has been
  measured here (the device machines have no bpy), so GPU rendering is left as a formula;
- render disk: bytes per rendered pixel of the v3 training renders (EXR as written);
- extract: maps/s and bytes per Parquet row at 1,300 lights, ``benchmarks/results/extract.json``;
- train: samples = epochs x maps; the rates are the train stage's and the bare step's from
  ``benchmarks/results/stage/*.json`` on CPU and, on an H100, the figures measured when
  the loader was reworked (stage 25,000 samples/s at batch 256 before that work; bare step
  120,000 / 144,000 at batch 4,096 in fp32 / bf16). N GPUs: DDP at N x one GPU's rate,
  which holds only while each rank's loader keeps up (loader alone: ``loader.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
RES = REPO / "benchmarks" / "results"

# measured on the v3 training data (data/cpu-train-v3: 248 scenes of 48 x 48, 200 lights,
# 10 rotations): 1,439,910 maps -> 580 mask pixels a scene, 23.6 % of the image; render
# folder 436 MiB for 248 x 200 images of 48 x 48 -> 4.0 bytes per rendered pixel
MASK_SHARE = 1_439_910 / (248 * 10 * 48 * 48)
RENDER_BYTES_PER_PIXEL = 436 * 2**20 / (248 * 200 * 48 * 48)
H100 = {"stage_bs256_before": 25_000, "bare_bs4096_fp32": 120_000, "bare_bs4096_bf16": 144_000}


def _hours(seconds: float) -> float:
    return round(seconds / 3600, 2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", type=int, default=25, help="meshes in meshes.mesh_dir (../shared has 25)")
    ap.add_argument("--gpus", type=int, nargs="*", default=[1, 8])
    ap.add_argument("--out", type=Path, default=RES / "full_estimate.json")
    args = ap.parse_args()
    preset = yaml.safe_load((REPO / "cnnps" / "presets" / "full.yaml").read_text())
    mat, ren, ext, tr = preset["materials"], preset["render"], preset["extract"], preset["train"]
    scenes = (args.meshes + preset["meshes"]["procedural"]) * preset["meshes"]["views_per_mesh"] * len(mat["categories"])
    images = scenes * ren["lights"]
    pixels = ren["size"] ** 2
    maps = round(scenes * pixels * MASK_SHARE * ext["rotations"])
    samples = tr["epochs"] * maps

    render = json.loads((RES / "render.json").read_text())["results"]["in_process"]["path_samples_per_s"]
    row = next(r for r in json.loads((RES / "extract.json").read_text())["results"] if r["lights"] == ext["max_lights"])
    loader = json.loads((RES / "loader.json").read_text())
    stage_files = sorted((RES / "stage").glob("cpu-*.json"))
    cpu_stage = json.loads(stage_files[0].read_text()) if stage_files else None

    est: dict = {
        "preset": "cnnps/presets/full.yaml",
        "meshes": args.meshes,
        "scenes": scenes,
        "images": images,
        "maps": maps,
        "train_samples": samples,
        "render": {
            "path_samples": images * pixels * ren["samples"],
            "cpu_2_cores_hours": _hours(images * pixels * ren["samples"] / render),
            "cpu_rate_path_samples_per_s": round(render),
            "gpu": "not measured here: hours = path_samples / (GPU path samples per second) / 3600",
            "disk_gb": round(images * pixels * RENDER_BYTES_PER_PIXEL / 1e9, 1),
        },
        "extract": {
            "cpu_2_cores_hours": _hours(maps / row["maps_per_s_total"]),
            "maps_per_s": row["maps_per_s_total"],
            "bytes_per_map": row["bytes_per_row"],
            "disk_gb": round(maps * row["bytes_per_row"] / 1e9, 1),
        },
        "train": {},
        "loader_alone_samples_per_s_2_cores": loader["best_samples_per_s"],
    }
    if cpu_stage:
        rate = cpu_stage["stage"]["samples_per_s"]
        est["train"]["cpu_2_cores"] = {"samples_per_s": rate, "hours": _hours(samples / rate), "source": stage_files[0].name}
    for n in args.gpus:
        for name, rate in H100.items():
            est["train"][f"h100_x{n}_{name}"] = {"samples_per_s": rate * n, "hours": _hours(samples / (rate * n))}
    est["paper_scale_note"] = ("the paper trained on ~75 M maps for 10 epochs (750 M samples): "
                               f"{_hours(750e6 / H100['bare_bs4096_fp32'])} h at one H100's bare fp32 step, "
                               f"{_hours(750e6 / H100['stage_bs256_before'])} h at the stage's rate before the loader work")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(est, indent=2) + "\n")
    print(json.dumps(est, indent=2))


if __name__ == "__main__":
    main()
