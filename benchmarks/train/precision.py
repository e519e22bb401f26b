"""float32 against bf16 autocast training: the same runs, their speed and their accuracy.

    .venv/bin/python -m benchmarks.train.precision [--steps 3000] [--bf16-steps N] [--seeds 0,1]
        [--precisions fp32,bf16] [--ball ../shared/data/diligent/ballPNG]
        [--out benchmarks/results/train/precision.json]

For each seed, the train stage runs from scratch on per-pixel maps only
(``train.pixelwise.share: 1``, the per-pixel fine-tune benchmark's effects, sparse share 0.2,
batch 128, the stage's defaults otherwise: step processes auto), once with
``precision: fp32`` and once with ``precision: bf16``, each in its own process, the two
precisions alternating. Every model is scored the same way, in float32: 10,000 per-pixel
maps of one held-out seed (:data:`VAL_SEED`, the same effects), and DiLiGenT BALL at 96
images (K=10) where ``--ball`` exists. The
seed-to-seed spread of one precision is the yardstick for the difference between the
two. ``--bf16-steps`` gives the bf16 runs another step count: the float32 runs' steps
times the measured speed ratio compares the two at equal time. Results: ``--out`` with
each run's samples/s.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import ROOT, result_path, write_result
from benchmarks.train.pixelwise_finetune import EFFECTS

PRECISIONS = ("fp32", "bf16")
VAL_SEED, VAL_MAPS = 20261125, 10000  # the held-out per-pixel maps every model is scored on


def one_run(precision: str, seed: int, steps: int, ball: Path | None, work: Path) -> dict:
    """Train from scratch in ``precision`` and score the model in float32 (in this process)."""
    import torch

    import cnnps
    from cnnps.stages import train
    from cnnps.train.pixelwise_batches import pixelwise_maker

    params = train.Params(pixelwise={"share": 1.0, "effects": EFFECTS, "sparse_fraction": 0.2}, precision=precision,
                          seed=seed, max_steps=steps, data={"batch_size": 128}, val_every=steps,
                          checkpoint_every=steps, progress=False)
    m = train.run(params, work)
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.train.validation import val_errors

    net, _config, _meta = load_checkpoint(work / "train" / "model.pt")
    gen = torch.Generator().manual_seed(VAL_SEED)  # one held-out set for every run
    maps, normals = pixelwise_maker(params)(VAL_MAPS, gen, torch.device("cpu"), 32)
    val = val_errors(net, maps[:, 0].numpy(), normals.numpy(), torch.device("cpu"), "fp32")
    out = {"precision": precision, "seed": seed, "steps": m["steps"], "samples_per_s": m["samples_per_s"],
           "step_processes": m.get("step_processes"), "train_loss": m.get("train_loss"),
           "stage_val_mean_deg": m["val_mean_deg"],  # the stage's own, in the run's precision
           "val_mean_deg": round(val["val_mean_deg"], 3), "val_median_deg": round(val["val_median_deg"], 3)}
    if ball is not None and ball.is_dir():
        torch.set_num_threads(os.cpu_count() or 1)
        cap = cnnps.load_capture(ball)
        res = cnnps.predict(cap.images, cap.lights, cap.mask, intensities=cap.intensities, normal_gt=cap.normal_gt,
                            model=work / "train" / "model.pt", rotations=10, precision="fp32", device="cpu")
        out["ball_96_deg"] = round(res.stats["mean_deg"], 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--bf16-steps", type=int, default=0, help="steps of the bf16 runs (default: --steps)")
    ap.add_argument("--precisions", default="fp32,bf16")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--ball", type=Path, default=ROOT.parent / "shared/data/diligent/ballPNG")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    ap.add_argument("--one", help=argparse.SUPPRESS)  # a child: "precision,seed"
    a = ap.parse_args()
    if a.one:
        precision, seed = a.one.split(",")
        with tempfile.TemporaryDirectory(prefix="bench-precision-") as tmp:
            print(json.dumps(one_run(precision, int(seed), a.steps, a.ball, Path(tmp))))
        return
    seeds = [int(s) for s in a.seeds.split(",")]
    res = {"steps": {"fp32": a.steps, "bf16": a.bf16_steps or a.steps}, "batch_size": 128, "effects": EFFECTS, "runs": []}
    precisions = [q for q in PRECISIONS if q in a.precisions.split(",")]
    for i, seed in enumerate(seeds):
        order = precisions if i % 2 == 0 else precisions[::-1]  # alternate which runs first
        for precision in order:
            steps = res["steps"][precision]
            cmd = [sys.executable, "-m", __spec__.name, "--one", f"{precision},{seed}", "--steps", str(steps),
                   "--ball", str(a.ball)]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT).stdout
            run = json.loads(out.strip().splitlines()[-1])
            res["runs"].append(run)
            print(json.dumps(run), flush=True)
    summary = {}
    for precision in precisions:
        runs = [r for r in res["runs"] if r["precision"] == precision]
        summary[precision] = {k: round(statistics.mean(r[k] for r in runs), 3)
                              for k in ("samples_per_s", "val_mean_deg", "ball_96_deg") if all(k in r for r in runs)}
    res["mean_over_seeds"] = summary
    print(json.dumps(summary))
    write_result(a.out, __spec__.name, a, res)


if __name__ == "__main__":
    main()
