"""`cnnps predict`'s whole-process time on DiLiGenT BALL: v6's candidate networks
against the shipped model (v4).

    .venv/bin/python -m benchmarks.predict.predict_speed [--repeat 3] [--rotations K]
        [--precision fp32] [--candidates NAME ...] [--ball DIR] [--note TEXT] [--out FILE]

Results go to ``benchmarks/results/predict/predict_speed_<cpu kind>.json``
(:func:`benchmarks.harness.cpu_kind`). BALL absent (``../shared/data/diligent/ballPNG``):
one line, nothing written.

Each candidate is a network of :func:`cnnps.models.model_options.build_model` (see
:data:`CANDIDATES`: CNN-PS with the heat-map head, CNN-PS with a 3 x 3 patch, the U-Net
heat-map network with a 3 x 3 and a 5 x 5 patch) with random weights
(``torch.manual_seed(0)``), saved as a checkpoint (:func:`cnnps.models.checkpoint.save_checkpoint`):
the time does not depend on the weights' values at a fixed precision, so random weights
time what a trained network of that shape will take. ``--precision`` is fixed (fp32 by
default) for every network: ``auto`` chooses by a probe of each network's own answers,
which random weights would decide instead of the architecture.

Runs: ``--warmup`` runs of v4 (default 1: the PNGs into the page cache), then ``--repeat`` rounds of
``v4, candidate 1, v4, candidate 2, ...``, each a fresh ``python -m cnnps predict BALL
--model M --rotations K --device cpu --precision P`` process into a new output folder
(``K`` = ``cnnps predict``'s default, the shipped model's: 10). Each candidate run is
paired with the v4 run just before it, so a change of the machine's load hits both; per
candidate: the median wall seconds, the ratio of the medians to v4's, and each pair's
ratio (median, min, max). Also per run: the children's CPU seconds (user + system), and
from ``prediction.json`` the seconds inside the process and the image reading. The target
is a ratio of at most 1.5 (:data:`TARGET_RATIO`). On a shared machine quote the ratios:
the absolute seconds carry the load (``--note`` records what else ran; the load average
before and after is recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from benchmarks.harness import ROOT, Stopwatch, cpu_info, cpu_kind, result_path, write_result
from cnnps.api.prediction_options import option_default
from cnnps.models.checkpoint import save_checkpoint
from cnnps.models.model_options import build_model
from cnnps.models.shipped import shipped_model_path

TARGET_RATIO = 1.5
REFERENCE = "v4"
CANDIDATES = {  # name -> build_model options
    "cnnps-heatmap": dict(arch="cnnps", head="heatmap", patch=1),
    "cnnps-patch3": dict(arch="cnnps", head="regression", patch=3),
    "unet-heatmap-patch3": dict(arch="unet", head="heatmap", patch=3),
    "unet-heatmap-patch5": dict(arch="unet", head="heatmap", patch=5),
}


def candidate_checkpoint(name: str, folder: Path) -> Path:
    """A checkpoint of candidate ``name``'s network with random weights (seed 0)."""
    torch.manual_seed(0)
    net = build_model(**CANDIDATES[name]).eval()
    return save_checkpoint(folder / f"{name}.pt", net, meta={"note": "random weights: a speed measurement only"})


def children_cpu_seconds() -> float:
    """User + system CPU seconds of this process's finished children so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def predict_once(ball: Path, model: Path, dest: Path, args: argparse.Namespace, env: dict) -> dict:
    """One ``cnnps predict`` process: wall and CPU seconds, and what prediction.json says."""
    cmd = [sys.executable, "-m", "cnnps", "predict", str(ball), "--out", str(dest), "--model", str(model),
           "--rotations", str(args.rotations), "--device", "cpu", "--precision", args.precision, "--no-progress"]
    cpu0 = children_cpu_seconds()
    with Stopwatch() as sw:
        done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"cnnps predict failed for {model.name} (exit {done.returncode}): "
                         f"{done.stderr.strip().splitlines()[-1:] or ''}")
    rec = json.loads((dest / "prediction.json").read_text())
    run = {"wall_s": round(sw.seconds, 2), "cpu_s": round(children_cpu_seconds() - cpu0, 2),
           "in_process_s": round(rec["seconds"], 2), "read_s": round(rec["load_seconds"], 2),
           "precision": rec.get("precision")}
    metrics = dest / "metrics.json"
    if metrics.is_file():
        run["mean_deg"] = round(json.loads(metrics.read_text())["mean_deg"], 3)
    shutil.rmtree(dest)
    return run


def summary(runs: dict[str, list[dict]], names: list[str]) -> dict:
    """Per candidate: median wall (and CPU) seconds, ratio of medians to v4's, the
    pair-by-pair ratios (each candidate run over the v4 run before it)."""
    ref = runs[REFERENCE]
    v4_wall = statistics.median(r["wall_s"] for r in ref)
    out = {REFERENCE: {"median_wall_s": round(v4_wall, 2),
                       "median_cpu_s": round(statistics.median(r["cpu_s"] for r in ref), 2)}}
    for i, name in enumerate(names):
        own = runs[name]
        if not own:  # a run stopped before this candidate's first
            continue
        pairs = [c["wall_s"] / ref[r * len(names) + i]["wall_s"] for r, c in enumerate(own)]
        wall = statistics.median(r["wall_s"] for r in own)
        out[name] = {"median_wall_s": round(wall, 2),
                     "median_cpu_s": round(statistics.median(r["cpu_s"] for r in own), 2),
                     "ratio_of_medians": round(wall / v4_wall, 3),
                     "pair_ratios": [round(p, 3) for p in pairs],
                     "pair_ratio_median": round(statistics.median(pairs), 3),
                     "pair_ratio_min_max": [round(min(pairs), 3), round(max(pairs), 3)],
                     "within_target": statistics.median(pairs) <= TARGET_RATIO}
    return out


def results(args: argparse.Namespace, load_before: list, warmup: list, runs: dict, rounds: int) -> dict:
    """The result record's ``results``: settings that explain the numbers, every run, the summary."""
    return {
        "capture": str(args.ball), "rotations": args.rotations, "precision": args.precision,
        "candidates": {n: CANDIDATES[n] for n in args.candidates},
        "weights": "v4: the shipped cnnps_default.pt; candidates: random weights (seed 0), the time does not "
                   "depend on the weights' values at a fixed precision",
        "command_each_run": f"python -m cnnps predict {args.ball} --out OUT --model M --rotations {args.rotations} "
                            f"--device cpu --precision {args.precision} --no-progress",
        "rounds_started": rounds, "target_ratio": TARGET_RATIO, "note": args.note,
        "load_average_before": load_before, "warmup": warmup, "runs": runs,
        "summary": summary(runs, args.candidates),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="alternated rounds (v4, candidate) per candidate")
    ap.add_argument("--rotations", type=int, default=option_default("rotations"),
                    help="K (default: cnnps predict's, %(default)s)")
    ap.add_argument("--precision", choices=("fp32", "bf16"), default="fp32")
    ap.add_argument("--candidates", nargs="+", choices=sorted(CANDIDATES), default=list(CANDIDATES))
    ap.add_argument("--ball", type=Path, default=ROOT.parent / "shared" / "data" / "diligent" / "ballPNG")
    ap.add_argument("--warmup", type=int, default=1, help="v4 runs first, not counted")
    ap.add_argument("--note", default="", help="what else ran on the machine (recorded with the numbers)")
    ap.add_argument("--out", type=Path, default=None,
                    help="default benchmarks/results/predict/predict_speed_<cpu kind>.json")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat must be at least 1, got {args.repeat}")
    if not (args.ball / "filenames.txt").is_file():
        print(f"skipped: no DiLiGenT BALL at {args.ball}")
        return 0
    info = cpu_info()
    out_path = args.out or result_path(__spec__.name, cpu_kind(info))
    load_before = [round(x, 2) for x in os.getloadavg()]
    runs: dict[str, list[dict]] = {REFERENCE: [], **{n: [] for n in args.candidates}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        models = {REFERENCE: shipped_model_path(), **{n: candidate_checkpoint(n, tmp) for n in args.candidates}}
        env = dict(os.environ, CNNPS_CACHE_DIR=str(tmp / "cache"),
                   PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        warmup = [predict_once(args.ball, models[REFERENCE], tmp / f"warmup-{i}", args, env)
                  for i in range(args.warmup)]
        print(f"warm-up {REFERENCE}: {[w['wall_s'] for w in warmup]} s", flush=True)
        for r in range(args.repeat):
            for name in args.candidates:
                for who in (REFERENCE, name):
                    run = predict_once(args.ball, models[who], tmp / f"{who}-{r}", args, env)
                    runs[who].append(run)
                    print(f"round {r + 1}: {who} {run['wall_s']} s wall, {run['cpu_s']} s CPU", flush=True)
                # the rounds so far, written after each pair: a run stopped early keeps its pairs
                write_result(out_path, __spec__.name, args, results(args, load_before, warmup, runs, r + 1),
                             argv=argv)
    table = summary(runs, args.candidates)
    for name, row in table.items():
        extra = "" if name == REFERENCE else (f", ratio {row['ratio_of_medians']} (pairs: median "
                                              f"{row['pair_ratio_median']}, {row['pair_ratio_min_max']})")
        print(f"{name}: median {row['median_wall_s']} s{extra}")
    write_result(out_path, __spec__.name, args, results(args, load_before, warmup, runs, args.repeat), argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
