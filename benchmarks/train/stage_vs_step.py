"""The train stage against the bare training step, on one device, in one run.

    .venv/bin/python -m benchmarks.train.stage_vs_step [--device auto] [--batch-size 128] [--steps 600]
        [--shards data/cpu-train-v3/extract | --synthetic 12] [--seconds 20] [--out PATH]

Three rates, samples per second, measured one after the other in the same process:

- ``loader``: the stage's loader alone over the same shards (``ShardDataset`` on a CPU,
  float32 tensors; the float16 ``ShardStream`` batches on CUDA), no network;
- ``bare_step``: :func:`cnnps.train.optimiser.train_step` on batches already on the
  device (real maps from the shards, gathered once), nothing else: the network's rate;
- ``stage``: ``cnnps.stages.train.run`` itself for ``--steps`` steps from scratch with
  the stage's defaults (prefetch, channels_last, fused Adam, progress bar, loss log), a
  validation (of as many maps per step as the defaults: 50,000 every 2,000 steps) and a
  checkpoint every ``--steps // 2`` steps; its rate is the one the stage
  reports (the step loop's samples over its wall time) and ``seconds`` is its own split
  (``metrics.json``: data wait, validation, checkpoints).

``stage / bare_step`` is the stage's efficiency. The stage's defaults validate every
2,000 steps (50,000 maps) and checkpoint every 1,000; from the measured cost of one
validation and one checkpoint the benchmark also projects the overhead share at that
cadence: ``(t_val / 2000 + t_ckpt / 1000) / t_step``.

Shards: ``--shards`` (an extract output), else the first of
``data/cpu-train-v3/extract``, ``data/cpu-train/extract`` that exists, else ``--synthetic N``
scenes (default 12) of Lambertian spheres made without Blender and extracted with the
stage's code into a temporary folder (what a GPU machine without the data sets uses).
Results: ``benchmarks/results/train/stage_vs_step_<device kind>.json`` (the device kind:
``cpu-<cpu kind>`` or ``cuda-<GPU name>``).

``--vs-before ROUNDS --shards DIR`` measures only the stage, end to end: with the settings
it had before the fast CPU step (:data:`BEFORE`: torch's dropout masks, torch's layers,
glibc's allocator as it comes) and with today's defaults, each run in its own process,
alternately, ``ROUNDS`` times; it writes ``stage_vs_step_<device kind>-vs-before.json`` with the
medians and the ratio of each round. ``--counter32`` adds today's defaults with the 32-bit
counter masks (``cpu.dropout_masks: counter``, the default before ``counter16``). ``--bf16`` adds today's defaults in bf16 autocast, in
one process and in ``--step-processes``: ``<device kind>-vs-before-bf16.json``. ``--ahead ROUNDS --share S`` does the same for a
stage whose batches are ``S`` per-pixel maps (:data:`PIXELWISE`'s effects), made in the
step's thread against made a step ahead (``pixelwise.ahead`` 0 and 1):
``<device kind>-pixelwise-S-ahead.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
from pathlib import Path

from cnnps.train.openmp import prefer_passive_openmp

prefer_passive_openmp()  # as the stage does, before torch loads
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.harness import (  # noqa: E402  # noqa: E402
    ROOT,
    Stopwatch,
    cpu_info,
    cpu_kind,
    result_path,
    run_for,
    write_result,
)
from benchmarks.train.pixelwise_finetune import EFFECTS as FINETUNE_EFFECTS  # noqa: E402
from cnnps.io.shards import ShardStream, load_manifest, manifest_files  # noqa: E402
from cnnps.train.shard_dataset import ShardDataset  # noqa: E402

CANDIDATES = ("data/cpu-train-v3/extract", "data/cpu-train/extract")
DEFAULT_VAL_EVERY, DEFAULT_CKPT_EVERY, DEFAULT_VAL_ROWS = 2000, 1000, 50000


def synthetic_shards(root: Path, scenes: int) -> Path:
    """Extract shards (w = 32) of ``scenes`` synthetic Lambertian renders, made without Blender."""
    from cnnps.stages import extract
    from tests.support.renders import make_render_dir

    make_render_dir(root, n_scenes=scenes, size=48, m=200)
    extract.run(extract.Params(w=32, min_lights=50, max_lights=200, rotations=10, val_fraction=0.1), root)
    return root / "extract"


def loader_rate(files, w: int, batch: int, device: torch.device, seconds: float) -> dict:
    stream = ShardStream(files, w, batch, seed=0, prefetch=2)
    it = stream.iter_epoch(0) if device.type == "cuda" else iter(ShardDataset(stream))
    got = run_for(lambda: len(next(it)[0]), seconds)
    it.close()
    return {"samples_per_s": round(got.per_second, 1), "samples": int(got.units), "seconds": round(got.seconds, 2),
            "what": "ShardStream float16 batches" if device.type == "cuda" else "ShardDataset float32 tensors"}


def bare_step_rate(files, w: int, batch: int, device: torch.device, seconds: float, masks: str = "counter16") -> dict:
    from cnnps.stages.train import Params
    from cnnps.train.optimiser import make_model, train_step

    p = Params(data={"batch_size": batch}, cpu={"dropout_masks": masks}, precision="fp32")  # the bare fp32 step
    stream = ShardStream(files, w, 4096, seed=0, prefetch=0)
    it = stream.iter_epoch(0)
    maps, normals = next(it)
    it.close()
    maps = torch.from_numpy(np.ascontiguousarray(maps)).unsqueeze(1).to(device)  # float16, as the stage sends it
    maps = maps if device.type == "cuda" else maps.float()
    normals = torch.from_numpy(np.ascontiguousarray(normals)).to(device)
    model, opt = make_model(w, p, device)
    model.train()
    nb = maps.shape[0] // batch

    def step(i):
        s = (i % nb) * batch
        model.set_mask_key((p.seed, 0, i) if masks != "torch" else None)  # as the stage's eager steps
        return train_step(model, opt, maps[s:s + batch], normals[s:s + batch], device, p.precision, p.channels_last)

    for i in range(3):  # warm-up
        step(i)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    done = 0

    def ten_steps() -> int:  # ten steps between looks at the clock (and CUDA synchronisations)
        nonlocal done
        for _ in range(10):
            step(done)
            done += 1
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return 10 * batch

    got = run_for(ten_steps, seconds)
    return {"samples_per_s": round(got.per_second, 1), "steps": done, "seconds": round(got.seconds, 2),
            "step_seconds": got.seconds / done}


# the train stage's CPU settings before the fast step: torch's dropout masks, torch's layers,
# glibc's allocator as it comes (the stage's speed when the work on it began)
BEFORE = {"cpu": dict(dropout_masks="torch", layers="reference", keep_freed_memory=False, step_processes=1)}


def merged(base: dict, settings: dict) -> dict:
    """Train params ``base`` with ``settings`` over them, a section's keys joining base's."""
    return {**base, **{k: {**base.get(k, {}), **v} if isinstance(v, dict) else v for k, v in settings.items()}}


def stage_rate(shards: Path, batch: int, steps: int, device: str, work: Path, masks: str = "counter16",
               **settings) -> dict:
    """The stage for ``steps`` steps; ``settings``: train params (sections as mappings)
    over this benchmark's, e.g. ``cpu={"step_processes": 2}``."""
    from cnnps.stages import train

    every = max(1, steps // 2)
    # as many validation maps per step as the defaults (50,000 every 2,000 steps)
    val_rows = max(1000, round(DEFAULT_VAL_ROWS * every / DEFAULT_VAL_EVERY))
    base = dict(data={"batch_size": batch, "shards": str(shards)}, cpu={"dropout_masks": masks}, max_steps=steps,
                epochs=1000, val_every=every, checkpoint_every=every, val_max_rows=val_rows, device=device,
                progress=True)
    params = train.Params(**merged(base, settings))
    with Stopwatch() as sw:
        m = train.run(params, work)
    wall = sw.seconds
    sec = m["seconds"]
    n_val, n_ckpt = max(1, steps // every - 1), steps // every  # validations inside the loop; checkpoints
    return {"samples_per_s": m["samples_per_s"], "steps": m["steps"], "run_seconds": round(wall, 2),
            "seconds": sec, "validations_in_loop": n_val, "checkpoints": n_ckpt,
            "val_seconds_each": round(sec["validation"] / n_val, 3), "checkpoint_seconds_each": round(sec["checkpoints"] / n_ckpt, 3),
            "val_rows": m["val_rows"], "params": {k: v for k, v in dataclasses.asdict(params).items()
                                                  if k in ("max_steps", "val_every", "checkpoint_every", "val_max_rows",
                                                           "channels_last", "precision", "data", "cpu", "pixelwise")}}


def stage_vs(shards: Path, batch: int, steps: int, device: str, rounds: int, settings: dict[str, dict]) -> dict:
    """The stage under each of the named ``settings`` (train params over the defaults),
    each run in its own process (the allocator setting lasts for a process), alternately
    for ``rounds`` rounds; the ratio is the last one's rate over the first's (with more than
    two settings, ``ratios_vs_first`` has every one's)."""
    import statistics
    import subprocess

    runs: dict[str, list[dict]] = {name: [] for name in settings}
    for rnd in range(rounds):
        for which, values in settings.items():
            cmd = [sys.executable, "-m", __spec__.name, "--one-stage", json.dumps(values), "--shards", str(shards),
                   "--steps", str(steps), "--batch-size", str(batch), "--device", device]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT).stdout
            res = json.loads(out.strip().splitlines()[-1])
            runs[which].append(res)
            print(f"  round {rnd + 1}, {which}: {res['samples_per_s']:,.0f} samples/s over {res['seconds']['loop']:.0f} s",
                  flush=True)
    first, *others = runs.values()
    med = {k: statistics.median(r["samples_per_s"] for r in v) for k, v in runs.items()}
    vs_first = {name: [round(b["samples_per_s"] / a["samples_per_s"], 3) for a, b in zip(first, runs[name])]
                for name in list(runs)[1:]}
    ratios = vs_first[list(runs)[-1]]
    res = {"settings": settings, "runs": runs, "median_samples_per_s": med,
           "ratio_per_round": ratios, "median_ratio": round(statistics.median(ratios), 3)}
    if len(others) > 1:
        res["ratios_vs_first"] = {k: {"per_round": v, "median": round(statistics.median(v), 3)} for k, v in vs_first.items()}
    return res


# per-pixel maps for --ahead: the fine-tune benchmark's effects and sparse share
PIXELWISE = dict(effects=FINETUNE_EFFECTS, sparse_fraction=0.2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="auto")
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--shards", type=Path, default=None)
    ap.add_argument("--synthetic", type=int, default=12, help="scenes of synthetic shards when no --shards exist")
    ap.add_argument("--seconds", type=float, default=20.0, help="for the loader and the bare step each")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--compare-masks", action="store_true",
                    help="also measure the bare step and the stage with torch's dropout masks (the former default), "
                         "first, in the same run")
    ap.add_argument("--vs-before", type=int, default=0, metavar="ROUNDS",
                    help="only the stage: before the fast step (torch masks and layers, glibc's allocator as it "
                         "comes) against today's defaults, each in its own process, alternately, ROUNDS rounds")
    ap.add_argument("--ahead", type=int, default=0, metavar="ROUNDS",
                    help="only the stage with --share per-pixel maps: made in the step's thread "
                         "(pixelwise.ahead 0) against a step ahead (1), each in its own process, alternately")
    ap.add_argument("--share", type=float, default=1.0, help="train.pixelwise.share of --ahead (1: per-pixel maps only)")
    ap.add_argument("--processes", type=int, default=0, metavar="ROUNDS",
                    help="only the stage: one process against --step-processes sharing each step "
                         "(train.cpu.step_processes), each in its own process, alternately, ROUNDS rounds")
    ap.add_argument("--step-processes", type=int, default=2,
                    help="train.cpu.step_processes of --processes and of --vs-before's third setting (today's "
                         "defaults with that many step processes; the second: with one)")
    ap.add_argument("--bf16", action="store_true",
                    help="--vs-before also runs today's defaults in bf16 autocast (train.precision: bf16), in one "
                         "process and in --step-processes")
    ap.add_argument("--counter32", action="store_true",
                    help="--vs-before: also today's defaults with cpu.dropout_masks: counter (32-bit masks)")
    ap.add_argument("--only", default="", help="--vs-before: the comma-separated settings to run, 'before' first "
                                                 "(names as in the results: now_1_process, now_2_processes, ...)")
    ap.add_argument("--one-stage", help=argparse.SUPPRESS)  # a child: the JSON of its train settings
    args = ap.parse_args()

    from cnnps.models.devices import resolve_device

    if args.one_stage:  # a child of --vs-before: one stage run, its result as JSON on the last line
        with tempfile.TemporaryDirectory(prefix="bench-stage-") as tmp:
            res = stage_rate(args.shards, args.batch_size, args.steps, args.device, Path(tmp),
                             **json.loads(args.one_stage))
        print(json.dumps(res))
        return
    if args.vs_before or args.ahead or args.processes:
        shards = args.shards or next((ROOT / c for c in CANDIDATES if (ROOT / c / "manifest.json").is_file()), None)
        if shards is None:
            sys.exit("stage_vs_step: --vs-before and --ahead need --shards (an extract output)")
        info = cpu_info()
        res = {"shards": str(shards), "load_average_before": [round(x, 2) for x in os.getloadavg()]}
        if args.vs_before:
            n = args.step_processes
            settings = {"before": BEFORE, "now_1_process": {"cpu": {"step_processes": 1}},
                        f"now_{n}_processes": {"cpu": {"step_processes": n}}}
            if args.counter32:  # today's defaults with the 32-bit counter masks drawn before counter16
                settings[f"now_{n}_processes_counter32"] = {"cpu": {"step_processes": n, "dropout_masks": "counter"}}
            if args.bf16:
                settings["now_bf16_1_process"] = {"precision": "bf16", "cpu": {"step_processes": 1}}
                settings[f"now_bf16_{n}_processes"] = {"precision": "bf16", "cpu": {"step_processes": n}}
            if args.only:
                keep = args.only.split(",")
                unknown = sorted(set(keep) - set(settings))
                if unknown or "before" not in keep:
                    sys.exit(f"stage_vs_step: --only takes 'before' and any of {', '.join(list(settings)[1:])}")
                settings = {k: v for k, v in settings.items() if k in keep}
        elif args.processes:
            settings = {"one_process": {"cpu": {"step_processes": 1}},
                        f"{args.step_processes}_processes": {"cpu": {"step_processes": args.step_processes}}}
        else:
            px = dict(PIXELWISE, share=args.share)
            settings = {"in_step": {"pixelwise": dict(px, ahead=0)}, "ahead": {"pixelwise": dict(px, ahead=1)}}
        rounds = args.vs_before or args.ahead or args.processes
        res.update(stage_vs(shards, args.batch_size, args.steps, args.device, rounds, settings))
        res["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
        from benchmarks.train.step_variants import roofline

        res["roofline"] = roofline(32, res["median_samples_per_s"])  # this machine's GEMM peak, measured now
        name = (("vs-before-bf16" if args.bf16 else "vs-before") if args.vs_before else f"{args.step_processes}-step-processes" if args.processes
                else f"pixelwise-{args.share:g}-ahead")
        out = args.out or result_path(__spec__.name, f"cpu-{cpu_kind(info)}-{name}")
        print(f"stage: {res['median_samples_per_s']} samples/s (medians), ratio {res['median_ratio']} "
              f"(per round {res['ratio_per_round']})")
        write_result(out, __spec__.name, args, res)
        return

    device = resolve_device(args.device)
    with tempfile.TemporaryDirectory(prefix="bench-stage-") as tmp:
        shards = args.shards or next((ROOT / c for c in CANDIDATES if (ROOT / c / "manifest.json").is_file()), None)
        source = str(shards) if shards else f"synthetic: {args.synthetic} Lambertian sphere scenes"
        if shards is None:
            shards = synthetic_shards(Path(tmp) / "synthetic", args.synthetic)
        man = load_manifest(shards)
        w, files = int(man["w"]), manifest_files(shards, man, "train")
        info = cpu_info()
        res: dict = {"device": str(device), "threads": torch.get_num_threads(),
                     "shards": source, "train_rows": man.get("train_rows"),
                     "load_average_before": [round(x, 2) for x in os.getloadavg()]}
        if device.type == "cuda":
            res["gpu"] = torch.cuda.get_device_name(device)
        if args.compare_masks:
            print(f"torch dropout masks: bare step ({args.seconds:g} s), then the stage ({args.steps} steps) ...",
                  flush=True)
            before = {"bare_step": bare_step_rate(files, w, args.batch_size, device, args.seconds, "torch"),
                      "stage": stage_rate(shards, args.batch_size, args.steps, str(device), Path(tmp) / "torch",
                                          "torch")}
            res["torch_masks"] = before
            print(f"  bare {before['bare_step']['samples_per_s']:,.0f}, stage {before['stage']['samples_per_s']:,.0f}"
                  " samples/s", flush=True)
        print(f"loader alone ({args.seconds:g} s) ...", flush=True)
        res["loader"] = loader_rate(files, w, args.batch_size, device, args.seconds)
        print(f"  {res['loader']['samples_per_s']:,.0f} samples/s\nbare step ({args.seconds:g} s) ...", flush=True)
        res["bare_step"] = bare_step_rate(files, w, args.batch_size, device, args.seconds)
        print(f"  {res['bare_step']['samples_per_s']:,.0f} samples/s\nthe train stage ({args.steps} steps) ...", flush=True)
        res["stage"] = stage_rate(shards, args.batch_size, args.steps, str(device), Path(tmp) / "run")
        res["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    st, bare = res["stage"], res["bare_step"]
    if "torch_masks" in res:
        res["speedup_vs_torch_masks"] = {
            "bare_step": round(bare["samples_per_s"] / res["torch_masks"]["bare_step"]["samples_per_s"], 3),
            "stage": round(st["samples_per_s"] / res["torch_masks"]["stage"]["samples_per_s"], 3)}
    res["stage_over_bare"] = round(st["samples_per_s"] / bare["samples_per_s"], 3)
    sec = st["seconds"]
    steps_only = st["steps"] * args.batch_size / max(1e-9, sec["loop"] - sec["validation"] - sec["checkpoints"])
    res["stage_over_bare_without_extras"] = round(steps_only / bare["samples_per_s"], 3)
    t_step = bare["step_seconds"]
    res["projected_overhead_share_at_defaults"] = round(
        (st["val_seconds_each"] * (50000 / max(1, st["val_rows"])) / DEFAULT_VAL_EVERY
         + st["checkpoint_seconds_each"] / DEFAULT_CKPT_EVERY) / t_step, 4)
    res["note"] = ("projected share: one validation scaled to the default 50,000 maps, every 2,000 steps, and one "
                   "checkpoint every 1,000, over the bare step's time")
    kind = f"cuda-{res['gpu'].lower().replace(' ', '-')}" if device.type == "cuda" else f"cpu-{cpu_kind(info)}"
    out = args.out or result_path(__spec__.name, kind)
    print(f"stage {st['samples_per_s']:,.0f} / bare step {bare['samples_per_s']:,.0f} samples/s = "
          f"{res['stage_over_bare']:.2f}; loop split {st['seconds']}; projected overhead at the defaults "
          f"{100 * res['projected_overhead_share_at_defaults']:.1f} %")
    write_result(out, __spec__.name, args, res)


if __name__ == "__main__":
    main()
