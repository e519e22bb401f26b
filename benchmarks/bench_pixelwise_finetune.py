"""Short fine-tunes of the shipped model: Cycles shards only, Cycles + per-pixel maps, per-pixel only.

    .venv/bin/python benchmarks/bench_pixelwise_finetune.py --shards data/extract \\
        --testset data/eval/testset [--ball ../shared/data/diligent/ballPNG] [--steps 600]

Each variant starts from ``cnnps/models/weights/cnnps_default.pt`` and trains the same
number of steps (batch 128, lr 1e-4, counter dropout masks) with ``train.pixelwise`` 0,
``--mix`` (default 0.25, v4's recipe) and 1 (per-pixel effects: cast shadows 0.3,
inter-reflection 0.3, ambient 0.05, gains 0.05, noise 0.01; sparse share 0.2); its wall
and CPU time are recorded beside it. With ``--cpu-minutes M`` each variant instead
trains as many steps as fill M CPU-minutes of this process (per-step and fixed CPU time
from two pilots of 20 and 60 steps of the same variant): equal CPU time, so a variant whose maps cost more gets fewer
steps. The pilots are short: on a machine whose load changes they misjudge the steps (by
1.4-1.9x in the recorded run), so the JSON keeps each run's actual CPU seconds. Every model, the
shipped one included, is scored on the same things: the shards' validation maps (K=1,
each map alone), the eval-stage captures under ``--testset`` (K=10, sparse fill auto,
grouped by light count), and DiLiGenT BALL at 96 and 10 images (K=10, ``cnnps.predict``).
Results: ``benchmarks/results/pixelwise_finetune.json`` with the CPU model. Nothing
shipped changes on this basis: these are minutes of training.
"""

from __future__ import annotations

import argparse
import datetime
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_info  # noqa: E402
from cnnps.models.openmp import prefer_passive_openmp  # noqa: E402

prefer_passive_openmp()
import torch  # noqa: E402

EFFECTS = {"cast_shadow": 0.3, "interreflection": 0.3, "ambient": 0.05, "intensity_error": 0.05, "noise": 0.01}
VARIANTS = {"cycles": 0.0, "cycles+pixelwise": 0.5, "pixelwise": 1.0}


def cpu_seconds() -> float:
    """This process's CPU time so far (all its threads, user and system)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def finetune(share: float, shards: Path, steps: int, work: Path, init: Path | None = None) -> tuple[Path, dict]:
    """``steps`` steps from ``init`` (default: the shipped weights); the model and its timing."""
    from cnnps.models.shipped import weights_path
    from cnnps.stages import train

    params = train.Params(pixelwise=share, pixelwise_effects=EFFECTS, pixelwise_sparse_fraction=0.2,
                          shards=str(shards), init=str(init or weights_path()), max_steps=steps, epochs=1000, lr=1e-4,
                          batch_size=128, val_every=0, checkpoint_every=steps, progress=False)
    t0, c0 = time.perf_counter(), cpu_seconds()
    metrics = train.run(params, work)
    return work / "train" / "model.pt", {"seconds": round(time.perf_counter() - t0, 1),
                                         "cpu_seconds": round(cpu_seconds() - c0, 1),
                                         "samples_per_s": metrics["samples_per_s"], "steps": metrics["steps"]}


def steps_for(share: float, shards: Path, cpu_budget: float, work: Path, pilots=(20, 60)) -> tuple[int, dict]:
    """The steps that fill ``cpu_budget`` CPU-seconds of a whole run of this variant: the
    CPU time per step and the fixed cost (start-up, shard checks, the last validation)
    from two pilot runs of different lengths."""
    a, b = (finetune(share, shards, n, work / str(n))[1] for n in pilots)
    per_step = (b["cpu_seconds"] - a["cpu_seconds"]) / (pilots[1] - pilots[0])
    fixed = max(0.0, a["cpu_seconds"] - pilots[0] * per_step)
    steps = max(pilots[0], int((cpu_budget - fixed) / per_step))
    return steps, {"cpu_seconds_per_step": round(per_step, 3), "fixed_cpu_seconds": round(fixed, 1)}


def score(model_path: Path, shards: Path, testset: Path | None, ball: Path | None) -> dict:
    import cnnps
    from cnnps.io.capture import load_capture
    from cnnps.io.shards import load_manifest, manifest_files
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import predict_normals
    from cnnps.models.validation import load_val, val_errors
    from cnnps.ps.metrics import angular_error_deg

    net, _config, _meta = load_checkpoint(model_path)
    man = load_manifest(shards)
    maps, normals = load_val(manifest_files(shards, man, "val"), int(man["w"]), 50000, 0)
    out = {"val": val_errors(net, maps, normals, torch.device("cpu"), "fp32")}
    if testset is not None:
        by_lights: dict[int, list[float]] = {}
        for cap_dir in sorted(p for p in testset.iterdir() if (p / "filenames.txt").is_file()):
            cap = load_capture(cap_dir)
            n = predict_normals(net, cap.pixel_intensities(), cap.lights, rotations=10, device="cpu", progress=False)
            err = angular_error_deg(n, cap.normal_gt[cap.mask])
            by_lights.setdefault(cap.n_images, []).append(float(err.mean()))
        out["eval_mean_deg_by_lights"] = {str(k): round(float(np.mean(v)), 3) for k, v in sorted(by_lights.items())}
    if ball is not None and ball.is_dir():
        cap = cnnps.load_capture(ball)
        names = [ln.strip() for ln in (REPO / "benchmarks/image_lists/ballPNG-10.txt").read_text().splitlines()
                 if ln.strip() and not ln.startswith("#")]
        ten = [cap.filenames.index(n) for n in names]
        for name, idx in (("ball_96", list(range(len(cap.images)))), ("ball_10", ten)):
            res = cnnps.predict(cap.images[idx], cap.lights[idx], cap.mask, intensities=cap.intensities[idx],
                                normal_gt=cap.normal_gt, model=model_path, rotations=10, precision="fp32",
                                device="cpu")
            out[name] = round(res.stats["mean_deg"], 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shards", type=Path, required=True)
    ap.add_argument("--testset", type=Path, default=None)
    ap.add_argument("--ball", type=Path, default=REPO.parent / "shared/data/diligent/ballPNG")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--cpu-minutes", type=float, default=0.0,
                    help="equal CPU time instead of equal steps: each variant trains as many steps as fill this "
                         "many CPU-minutes (from two short pilots of it)")
    ap.add_argument("--mix", type=float, default=0.25, help="train.pixelwise of the mixed variant (v4's: 0.25)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/pixelwise_finetune.json")
    a = ap.parse_args()
    from cnnps.models.shipped import weights_path

    torch.set_num_threads(2)
    res = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "command": "benchmarks/bench_pixelwise_finetune.py " + " ".join(sys.argv[1:]), "cpu": cpu_info(),
           "steps": a.steps, "batch_size": 128, "effects": EFFECTS, "models": {}}
    print("shipped ...", flush=True)
    res["models"]["shipped"] = score(weights_path(), a.shards, a.testset, a.ball)
    print(json.dumps(res["models"]["shipped"]), flush=True)
    variants = {**VARIANTS, "cycles+pixelwise": a.mix}
    if a.cpu_minutes:
        res["cpu_minutes_each"] = a.cpu_minutes
        res.pop("steps")
    with tempfile.TemporaryDirectory(prefix="bench-px-") as tmp:
        for name, share in variants.items():
            steps, pilot = a.steps, None
            if a.cpu_minutes:
                steps, pilot = steps_for(share, a.shards, 60 * a.cpu_minutes, Path(tmp) / f"{name}-pilot")
            print(f"{name} (pixelwise {share}, {steps} steps) ...", flush=True)
            model, run = finetune(share, a.shards, steps, Path(tmp) / name)
            res["models"][name] = {"pixelwise": share, **run, **({"pilot": pilot} if pilot else {}),
                                   **score(model, a.shards, a.testset, a.ball)}
            print(json.dumps(res["models"][name]), flush=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
