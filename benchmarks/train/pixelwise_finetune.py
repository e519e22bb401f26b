"""Short fine-tunes of the shipped model: Cycles shards only, Cycles + per-pixel maps, per-pixel only.

    .venv/bin/python -m benchmarks.train.pixelwise_finetune --shards data/extract \\
        --testset data/eval/testset [--ball ../shared/data/diligent/ballPNG] [--steps 600]

Each variant starts from ``cnnps/models/weights/cnnps_default.pt`` and trains the same
number of steps (batch 128, lr 1e-4, counter dropout masks) with ``train.pixelwise.share`` 0,
``--mix`` (default 0.25, v4's recipe) and 1 (per-pixel effects: cast shadows 0.3,
inter-reflection 0.3, ambient 0.05, gains 0.05, noise 0.01; sparse share 0.2); its wall
and CPU time are recorded beside it. With ``--cpu-minutes M`` each variant instead
trains until its training loop has used M CPU-minutes (``train.run``'s ``until``, asked
after every step, reads the process's CPU clock; start-up, shard checks and the last
validation are outside the budget): equal CPU time, so a variant whose maps cost more
gets fewer steps. The three variants then run at once, one process and one torch thread
each, so a machine whose load changes slows all three alike. Every model, the
shipped one included, is scored on the same things: the shards' validation maps (K=1,
each map alone), the eval-stage captures under ``--testset`` (K=10, sparse fill auto,
grouped by light count), and DiLiGenT BALL at 96 and 10 images (K=10, ``cnnps.predict``).
Results: ``benchmarks/results/train/pixelwise_finetune.json``. Nothing shipped changes on
this basis: these are minutes of training.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result
from benchmarks.subsets import list_path, read_list
from cnnps.train.openmp import prefer_passive_openmp

prefer_passive_openmp()
import torch  # noqa: E402

EFFECTS = {"cast_shadow": 0.3, "interreflection": 0.3, "ambient": 0.05, "intensity_error": 0.05, "noise": 0.01}
VARIANTS = {"cycles": 0.0, "cycles+pixelwise": 0.5, "pixelwise": 1.0}


class CpuBudget:
    """``until`` for :func:`cnnps.stages.train.run`: true once the process has used
    ``seconds`` of CPU time (all its threads, ``time.process_time``) since the first step
    ended, so start-up and the first step's one-off work are not counted."""

    def __init__(self, seconds: float):
        self.seconds, self.clock, self.steps = seconds, None, 0

    def __call__(self, step: int) -> bool:
        if self.clock is None:
            self.clock, self.first_step = Stopwatch(time.process_time).begin(), step
            return False
        self.steps = step - self.first_step
        return self.clock.elapsed >= self.seconds


def finetune(share: float, shards: Path, steps: int, work: Path, cpu_budget: float = 0.0,
             threads: int = 0) -> tuple[Path, dict]:
    """``steps`` steps from the shipped weights (or, with ``cpu_budget`` seconds, as many as
    fill that much CPU time); the model and its timing."""
    from cnnps.models.shipped import weights_path
    from cnnps.stages import train

    params = train.Params(pixelwise={"share": share, "effects": EFFECTS, "sparse_fraction": 0.2},
                          data={"shards": str(shards), "batch_size": 128}, optimiser={"lr": 1e-4},
                          init=str(weights_path()), max_steps=10**7 if cpu_budget else steps, epochs=1000,
                          val_every=0, checkpoint_every=10**7 if cpu_budget else steps, progress=False,
                          cpu={"threads": threads})
    budget = CpuBudget(cpu_budget) if cpu_budget else None
    with Stopwatch() as wall, Stopwatch(time.process_time) as cpu:
        metrics = train.run(params, work, until=budget)
    run = {"seconds": round(wall.seconds, 1), "cpu_seconds": round(cpu.seconds, 1),
           "samples_per_s": metrics["samples_per_s"], "steps": metrics["steps"]}
    if budget is not None:
        run["budget_cpu_seconds"] = round(budget.seconds, 1)
        run["budget_steps"] = budget.steps  # the steps inside the budget (all but the first)
    return work / "train" / "model.pt", run


def variant(name: str, share: float, a: argparse.Namespace, work: Path) -> dict:
    """Train one variant and score it (in its own process when the variants run at once)."""
    threads = 1 if a.cpu_minutes else 2
    torch.set_num_threads(threads)
    print(f"{name} (pixelwise {share}) ...", flush=True)
    model, run = finetune(share, a.shards, a.steps, work / name, 60 * a.cpu_minutes, threads)
    out = {"pixelwise": share, **run, **score(model, a.shards, a.testset, a.ball)}
    print(name, json.dumps(out), flush=True)
    return out


def score(model_path: Path, shards: Path, testset: Path | None, ball: Path | None) -> dict:
    import cnnps
    from cnnps.io.capture import load_capture
    from cnnps.io.shards import load_manifest, manifest_files
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import predict_normals
    from cnnps.ps.metrics import angular_error_deg
    from cnnps.train.validation import load_val, val_errors

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
        names = read_list(list_path("ballPNG", 10))
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
    ap.add_argument("--ball", type=Path, default=ROOT.parent / "shared/data/diligent/ballPNG")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--cpu-minutes", type=float, default=0.0,
                    help="equal CPU time instead of equal steps: each variant trains until its loop has used "
                         "this many CPU-minutes (the three at once, one thread each)")
    ap.add_argument("--mix", type=float, default=0.25, help="train.pixelwise.share of the mixed variant (v4's: 0.25)")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    from cnnps.models.shipped import weights_path

    torch.set_num_threads(2)
    res = {"steps": a.steps, "batch_size": 128, "effects": EFFECTS, "models": {}}
    print("shipped ...", flush=True)
    res["models"]["shipped"] = score(weights_path(), a.shards, a.testset, a.ball)
    print(json.dumps(res["models"]["shipped"]), flush=True)
    variants = {**VARIANTS, "cycles+pixelwise": a.mix}
    if a.cpu_minutes:
        res["cpu_minutes_each"] = a.cpu_minutes
        res.pop("steps")
    with tempfile.TemporaryDirectory(prefix="bench-px-") as tmp:
        if a.cpu_minutes:  # at once: one process and one thread each
            import concurrent.futures
            import multiprocessing

            with concurrent.futures.ProcessPoolExecutor(len(variants),
                                                        mp_context=multiprocessing.get_context("spawn")) as pool:
                futs = {name: pool.submit(variant, name, share, a, Path(tmp)) for name, share in variants.items()}
                for name, fut in futs.items():
                    res["models"][name] = fut.result()
        else:
            for name, share in variants.items():
                res["models"][name] = variant(name, share, a, Path(tmp))
    write_result(a.out, __spec__.name, a, res)


if __name__ == "__main__":
    main()
