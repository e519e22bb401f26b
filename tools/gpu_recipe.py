"""Train CNN-PS on a lent GPU from per-pixel maps alone, within 10-minute calls.

A GPU machine gets only the checkout (no renders, no shards, nothing downloadable), so
it trains on maps made on the device by :mod:`cnnps.synth.pixelwise` (preset
``gpu-train-pixelwise``). Two steps::

    # 1. measure there: per-pixel generation (maps/s), the train step (samples/s) by batch
    #    size and precision, and a short learning-rate probe; writes measure.json
    PYTHONPATH=$PWD python3 tools/gpu_recipe.py measure --out $OUT

    # 2. train, resuming from the folder's newest checkpoint; stops cleanly before
    #    --seconds (every chunk ends with a checkpoint), so a call never loses work
    PYTHONPATH=$PWD python3 tools/gpu_recipe.py train --data-dir /root/gpu-run --seconds 540 \\
        --measure $OUT/measure.json --budget-seconds 1200 --pack $OUT

The first ``train`` call fixes the plan (batch size, learning rate, precision from
``measure.json``, and the total steps = the measured rate x ``--budget-seconds``) in
``DATA_DIR/plan.json``; later calls read it, so every call continues the same run (the
train stage's resume key holds them). ``--pack DIR`` copies the plan, the metrics, the
model and the newest checkpoint (in pieces under 15 MiB) to DIR; ``--restore DIR`` puts
them back into an empty data folder, for a machine that went cold between calls.

    # 3. here, from the files the call returned: what the run's folder in git keeps
    .venv/bin/python tools/gpu_recipe.py keep FILES_AT tools/runs/NAME

``keep`` copies the plan, progress, metrics and measurement and, while the run is in
progress, the float16 weights (``intermediate.pt``) that ``--restore`` continues from;
once its plan is spent, only their record (``intermediate.json``: bytes, SHA-256, steps;
``tools/run_weights.py``).

Without a GPU both steps run on the CPU (``--device cpu``, a few steps; tests/tools run
them so). ``PYTHONPATH=$PWD`` (in the checkout) puts ``cnnps`` on the path of a python3 that
has no install of it; ``.venv/bin/python tools/gpu_recipe.py`` needs none.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

from cnnps.train.openmp import prefer_passive_openmp

try:
    from tools import run_weights  # imported as tools.gpu_recipe (the tests)
except ImportError:  # run as a script: its own folder is on the path
    import run_weights

PRESET = "gpu-train-pixelwise"  # --preset: another one (gpu-train-v5: model v5's maps)
PIECE = 15 * 2**20  # bytes per piece of a packed checkpoint (a returned file may hold 16 MiB)


def machine() -> dict:
    import torch

    from cnnps.infra.machine import cpu_model_and_flags, logical_cpus

    model, flags = cpu_model_and_flags()
    info = {"cpu": {"model": model, "logical_cpus": logical_cpus(), "flags": flags,
                    "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()},
            "torch": torch.__version__}
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info["gpu"] = {"name": p.name, "memory_gib": round(p.total_memory / 2**30, 1),
                       "multiprocessors": p.multi_processor_count}
    return info


def with_params(p, **overrides):
    """Train params ``p`` with ``overrides``; a section's are a mapping of its keys
    (``optimiser={"lr": 1e-3}``), the rest of the section kept."""
    return dataclasses.replace(p, **{k: dataclasses.replace(getattr(p, k), **v) if isinstance(v, dict) else v
                                     for k, v in overrides.items()})


def preset_params(preset: str = PRESET, **overrides):
    """The train section of ``preset`` (a name in cnnps/presets), with ``overrides`` (:func:`with_params`)."""
    from cnnps.pipeline.config import build_params, load_config, preset_path

    return with_params(build_params(load_config(preset_path(preset)), "train", check_files=False), **overrides)


def segment_schedule(plan: dict, gamma: float) -> tuple[float, tuple[int, ...]]:
    """The learning rate and milestones of the train stage's run that continues ``plan``
    from its ``offset`` (steps done before carried weights restarted it; Adam starts
    afresh there): the rate reached at ``offset``, the milestones ahead counted from it.

    >>> segment_schedule({"lr": 1e-3, "lr_milestones": [70, 90], "offset": 80}, 0.2)
    (0.0002, (10,))
    """
    from types import SimpleNamespace

    from cnnps.train.optimiser import lr_at

    offset, ms = int(plan.get("offset", 0)), tuple(int(m) for m in plan["lr_milestones"])
    lr = lr_at(SimpleNamespace(lr=plan["lr"], lr_gamma=gamma, lr_milestones=ms), offset)
    return round(lr, 12), tuple(m - offset for m in ms if m > offset)


def _sync(device):
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize()


def _generator(device, seed: int):
    """A generator on the device that makes the maps, as the train stage uses."""
    import torch

    return torch.Generator(device=device if device.type == "cuda" else "cpu").manual_seed(seed)


def generation_rate(device, batch: int, seconds: float, params) -> dict:
    """Per-pixel maps/s of the preset's draws (effects, sparse share) at ``batch``."""
    from cnnps.train.pixelwise_batches import pixelwise_maker

    make, w = pixelwise_maker(params), params.pixelwise.w
    g = _generator(device, 0)
    make(batch, g, device, w)
    _sync(device)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or n == 0:
        make(batch, g, device, w)
        n += 1
    _sync(device)
    return {"batch": batch, "maps_per_s": round(n * batch / (time.perf_counter() - t0))}


def step_rate(device, params, seconds: float) -> dict:
    """Bare train-step samples/s (random sparse maps already on the device)."""
    import torch

    from cnnps.train.pixelwise_batches import input_channels
    from cnnps.train.optimiser import compile_model, make_model, train_step

    B, w, C = params.data.batch_size, params.pixelwise.w, input_channels(params)
    model, opt = make_model(w, params, device, in_channels=C)
    step_model = compile_model(model, params)
    g = torch.Generator(device=device).manual_seed(0)
    maps = (torch.rand(B, C, w, w, device=device, generator=g) > 0.9).float()
    normals = torch.nn.functional.normalize(torch.randn(B, 3, device=device, generator=g), dim=1)
    t0 = time.perf_counter()
    for _ in range(3):
        train_step(step_model, opt, maps, normals, device, params.precision, params.channels_last)
    _sync(device)
    first = time.perf_counter() - t0
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or n < 3:
        train_step(step_model, opt, maps, normals, device, params.precision, params.channels_last)
        n += 1
    _sync(device)
    return {"batch_size": B, "precision": params.precision, "compile": params.compile,
            "samples_per_s": round(n * B / (time.perf_counter() - t0)), "warmup_s": round(first, 1)}


def lr_probe(device, params, steps: int, val_n: int = 4096) -> dict:
    """Train ``steps`` steps from scratch on per-pixel maps at ``params.optimiser.lr``; the mean
    angular error (deg) on ``val_n`` held per-pixel maps, and the last 20 steps' loss."""
    import torch

    from cnnps.train.pixelwise_batches import input_channels, pixelwise_maker
    from cnnps.train.optimiser import make_model, train_step

    make, w = pixelwise_maker(params), params.pixelwise.w
    model, opt = make_model(w, params, device, in_channels=input_channels(params))
    losses = []
    t0 = time.perf_counter()
    for s in range(steps):
        maps, normals = make(params.data.batch_size, _generator(device, 1000 + s), device, w)
        losses.append(train_step(model, opt, maps, normals, device, params.precision, params.channels_last))
    vm, vn = make(val_n, _generator(device, 7), device, w)
    model.eval()
    with torch.no_grad():
        pred = torch.nn.functional.normalize(model(vm.contiguous(memory_format=torch.channels_last)).float(), dim=1)
    err = torch.rad2deg(torch.acos((pred * vn).sum(1).clamp(-1, 1))).mean()
    return {"lr": params.optimiser.lr, "steps": steps, "loss_last20": round(float(torch.stack(losses[-20:]).mean()), 5),
            "val_mean_deg": round(float(err), 2), "seconds": round(time.perf_counter() - t0, 1)}


def measure(args) -> dict:
    import torch

    device = torch.device(args.device)
    res = {"command": " ".join(sys.argv), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine(),
           "device": str(device)}
    base = preset_params(args.preset, device=device.type)
    res["preset"] = args.preset
    res["generation"] = [generation_rate(device, b, args.seconds, base) for b in args.batches]
    print("generation", res["generation"], flush=True)
    steps = []
    for b in args.batches:
        for prec in args.precisions:
            r = step_rate(device, with_params(base, data={"batch_size": b}, precision=prec), args.seconds)
            steps.append(r)
            print("step", r, flush=True)
    if args.compile:
        best = max(steps, key=lambda r: r["samples_per_s"])
        try:
            r = step_rate(device, with_params(base, data={"batch_size": best["batch_size"]},
                                              precision=best["precision"], compile=True), args.seconds)
            steps.append(r)
            print("step", r, flush=True)
        except Exception as exc:  # compile is optional: record why it failed
            steps.append({"compile": True, "error": f"{type(exc).__name__}: {exc}"[:300]})
    res["step"] = steps
    ok = [r for r in steps if "samples_per_s" in r]
    # the fastest setting, unless the generator cannot keep up with it at that batch
    best = max(ok, key=lambda r: r["samples_per_s"])
    gen = {g["batch"]: g["maps_per_s"] for g in res["generation"]}
    res["chosen"] = {"batch_size": best["batch_size"], "precision": best["precision"], "compile": best["compile"],
                     "step_samples_per_s": best["samples_per_s"],
                     "generation_maps_per_s": gen.get(best["batch_size"])}
    if args.lr_steps:
        probes = [lr_probe(device, with_params(base, data={"batch_size": best["batch_size"]},
                                               precision=best["precision"], optimiser={"lr": lr}),
                           args.lr_steps, args.probe_maps) for lr in args.lrs]
        for p in probes:
            print("lr", p, flush=True)
        res["lr_probe"] = probes
        res["chosen"]["lr"] = min(probes, key=lambda p: p["val_mean_deg"])["lr"]
    else:
        res["chosen"]["lr"] = base.optimiser.lr
    # samples/s of the whole loop (generation + step), what the plan budgets with
    g = res["chosen"]["generation_maps_per_s"] or math.inf
    res["chosen"]["loop_samples_per_s_est"] = round(1 / (1 / best["samples_per_s"] + 1 / g))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "measure.json").write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res["chosen"]), flush=True)
    return res


def make_plan(args, data_dir: Path) -> dict:
    plan_file = data_dir / "plan.json"
    if plan_file.is_file():
        plan = json.loads(plan_file.read_text())
        if args.preset not in (None, plan.get("preset", PRESET)):
            raise SystemExit(f"{plan_file}: this run's preset is {plan.get('preset', PRESET)}, not {args.preset}")
        return plan
    preset = args.preset
    if args.measure:
        measured = json.loads(Path(args.measure).read_text())
        chosen, preset = measured["chosen"], preset or measured.get("preset")
    else:
        chosen = {"batch_size": args.batch_size, "precision": args.precision, "lr": args.lr, "compile": False,
                  "loop_samples_per_s_est": None}
    rate = chosen.get("loop_samples_per_s_est")
    total = args.total_steps or max(1, int(args.budget_seconds * rate / chosen["batch_size"]))
    plan = {"preset": preset or PRESET, "batch_size": chosen["batch_size"], "precision": chosen["precision"], "lr": chosen["lr"],
            "compile": bool(chosen.get("compile")), "total_steps": total,
            "lr_milestones": sorted({max(1, int(total * 0.7)), max(2, int(total * 0.9))}),
            "budget_seconds": args.budget_seconds, "loop_samples_per_s_est": rate, "device": args.device}
    data_dir.mkdir(parents=True, exist_ok=True)
    plan_file.write_text(json.dumps(plan, indent=1) + "\n")
    return plan


def newest_checkpoint(data_dir: Path) -> Path | None:
    cks = sorted((data_dir / "train" / "checkpoints").glob("step-*.pt"))
    return cks[-1] if cks else None


def train(args) -> dict:
    prefer_passive_openmp()
    from cnnps.stages import train as train_stage

    data_dir = Path(args.data_dir)
    if args.restore:
        restore(Path(args.restore), data_dir)
    plan = make_plan(args, data_dir)
    preset = plan.get("preset", PRESET)
    deadline = time.monotonic() + args.seconds
    ck = newest_checkpoint(data_dir)
    # a run restored from carried weights counts its steps on from plan["offset"]
    offset = int(plan.get("offset", 0))
    done = offset + (int(ck.stem.split("-")[1]) if ck else 0)
    lr, milestones = segment_schedule(plan, preset_params(preset).optimiser.lr_gamma)
    init = str(data_dir / plan["init"]) if plan.get("init") else None
    chunk_t = None
    stop = min(plan["total_steps"], args.stop_at_step or plan["total_steps"])
    while done < stop:
        left = deadline - time.monotonic()
        # steps per chunk: about --chunk-seconds at the rate seen so far
        rate = (plan["loop_samples_per_s_est"] or 1000) / plan["batch_size"] if chunk_t is None else chunk_t
        steps = max(1, min(stop - done, int(rate * min(args.chunk_seconds, left - 25))))
        if left < 40 or steps < 1:
            break
        p = preset_params(preset, device=args.device, data={"batch_size": plan["batch_size"]},
                          precision=plan["precision"], optimiser={"lr": lr, "lr_milestones": milestones},
                          compile=plan["compile"], max_steps=done + steps - offset, checkpoint_every=max(1, steps),
                          val_every=0, val_max_rows=args.val_rows, progress=args.progress,
                          **({"init": init} if init else {}))
        t0 = time.monotonic()
        metrics = train_stage.run(p, data_dir)
        chunk_t = steps / max(1e-6, time.monotonic() - t0)
        done += steps
        print(f"steps {done}/{plan['total_steps']}  {chunk_t * plan['batch_size']:.0f} samples/s in this chunk  "
              f"val {metrics.get('val_mean_deg')}", flush=True)
    summary = {"steps_done": done, "total_steps": plan["total_steps"], "plan": plan}
    (data_dir / "progress.json").write_text(json.dumps(summary, indent=1) + "\n")
    if args.pack:
        pack(data_dir, Path(args.pack), done)
    return summary


def pack(data_dir: Path, out: Path, done: int | None = None) -> None:
    """plan, progress, metrics, model and the newest checkpoint into ``out``: in pieces
    (the whole training state, for the next call on the same machine) and, with ``done`` (the
    run's steps), as ``intermediate.pt``: its weights in float16 with ``meta["steps"]``,
    the file a run's folder in git carries to the next GPU machine (:func:`restore`)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in ("plan.json", "progress.json", "train/metrics.json", "train/model.pt"):
        if (data_dir / name).is_file():
            shutil.copy(data_dir / name, out / Path(name).name)
    ck = newest_checkpoint(data_dir)
    if ck is None:
        return
    blob = ck.read_bytes()
    for i in range(0, len(blob), PIECE):
        (out / f"{ck.stem}.part{i // PIECE:02d}").write_bytes(blob[i:i + PIECE])
    if done is not None:
        preset = json.loads((data_dir / "plan.json").read_text()).get("preset", PRESET)
        export_half(ck, out / "intermediate.pt", preset_params(preset), {"steps": done, "preset": preset})


def export_half(checkpoint: Path, out: Path, params, meta: dict) -> Path:
    """A train stage checkpoint's network (of train params ``params``: map width, dropout)
    as a float16 cnnps weights file."""
    import torch

    from cnnps.models.checkpoint import save_checkpoint
    from cnnps.models.network import CNNPS

    state = torch.load(checkpoint, map_location="cpu", weights_only=True)["model"]
    net = CNNPS(w=params.pixelwise.w, dropout=params.dropout, in_channels=int(state["conv0.weight"].shape[1]))
    net.load_state_dict(state)
    return save_checkpoint(out, net, meta=meta, half=True)


def restore(src: Path, data_dir: Path) -> None:
    """The inverse of :func:`pack` into ``data_dir`` (only where it has no checkpoint and
    no plan): from the pieces, the whole training state; without pieces, from ``src``'s
    ``intermediate.pt``, ``plan.json`` and ``progress.json`` (a run's folder in git), the
    weights as ``init.pt`` and the plan with ``offset`` = the steps done, so the run goes on
    from there with a fresh Adam (the one thing the carried file loses). A folder whose run
    has made all its planned steps stops the call with one line (SystemExit), as does one
    whose weights are only recorded or are not the ones recorded
    (:func:`tools.run_weights.carried_weights`)."""
    if newest_checkpoint(data_dir) is not None or not src.is_dir():
        return
    parts = sorted(src.glob("step-*.part*"))
    if not parts:
        carried = (src / run_weights.WEIGHTS).is_file() or (src / run_weights.RECORD).is_file()
        if carried and not (data_dir / "plan.json").is_file():
            plan = json.loads((src / "plan.json").read_text())
            done = int(json.loads((src / "progress.json").read_text())["steps_done"])
            if done >= int(plan["total_steps"]):
                raise SystemExit(f"{src}: this run has spent its plan ({done} of {plan['total_steps']} steps); "
                                 "a new run takes a new folder")
            weights = run_weights.carried_weights(src)
            data_dir.mkdir(parents=True, exist_ok=True)
            shutil.copy(weights, data_dir / "init.pt")
            (data_dir / "plan.json").write_text(json.dumps({**plan, "offset": done, "init": "init.pt"}, indent=1) + "\n")
        return
    ckdir = data_dir / "train" / "checkpoints"
    ckdir.mkdir(parents=True, exist_ok=True)
    stem = parts[0].name.split(".part")[0]
    tmp = ckdir / f".{stem}.tmp"
    with open(tmp, "wb") as f:
        for part in parts:
            f.write(part.read_bytes())
    os.replace(tmp, ckdir / f"{stem}.pt")
    if (src / "plan.json").is_file():
        shutil.copy(src / "plan.json", data_dir / "plan.json")


KEPT = ("plan.json", "progress.json", "metrics.json", "measure.json", "gpu.txt", "train.log")


def keep(src: Path, run: Path) -> Path | None:
    """What the run's folder in git (``run``) keeps of the files a call returned
    (``src``, what ``--pack`` and tools/gpu_v5.sh leave): the plan, progress, metrics,
    measurement, GPU name and log, and the weights by :func:`tools.run_weights.carry`:
    ``intermediate.pt`` while the run is in progress, their record alone once its plan is
    spent. Returns the weights file in ``run``, or None."""
    progress = json.loads((src / "progress.json").read_text())
    run.mkdir(parents=True, exist_ok=True)
    for name in KEPT:
        if (src / name).is_file():
            shutil.copy(src / name, run / name)
    if not (src / run_weights.WEIGHTS).is_file():
        return None
    done, total = int(progress["steps_done"]), int(progress["total_steps"])
    return run_weights.carry(run, src / run_weights.WEIGHTS, steps=done, planned=total, finished=done >= total)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("measure")
    m.add_argument("--out", default=".")
    m.add_argument("--preset", default=PRESET, help="the train section to measure (a name in cnnps/presets)")
    m.add_argument("--device", default="cuda")
    m.add_argument("--seconds", type=float, default=4.0)
    m.add_argument("--batches", type=int, nargs="+", default=[512, 2048, 8192])
    m.add_argument("--precisions", nargs="+", default=["fp32", "bf16"])
    m.add_argument("--compile", action="store_true")
    m.add_argument("--lrs", type=float, nargs="+", default=[5e-4, 1e-3, 2e-3, 4e-3])
    m.add_argument("--lr-steps", type=int, default=200)
    m.add_argument("--probe-maps", type=int, default=4096, help="per-pixel maps that score each learning rate")
    t = sub.add_parser("train")
    t.add_argument("--data-dir", required=True)
    t.add_argument("--preset", help=f"the run's train section (first call; default {PRESET}); later calls: the plan's")
    t.add_argument("--device", default="cuda")
    t.add_argument("--seconds", type=float, default=540)
    t.add_argument("--chunk-seconds", type=float, default=120)
    t.add_argument("--measure", help="measure.json: the batch size, precision and lr it chose")
    t.add_argument("--budget-seconds", type=float, default=1200, help="the run's planned training time (all calls)")
    t.add_argument("--total-steps", type=int, default=0, help="instead of the budget")
    t.add_argument("--batch-size", type=int, default=2048)
    t.add_argument("--precision", default="bf16")
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--val-rows", type=int, default=10000, help="per-pixel validation maps (at each chunk's end)")
    t.add_argument("--stop-at-step", type=int, default=0, help="end this call there (the plan stays)")
    t.add_argument("--pack")
    t.add_argument("--restore")
    t.add_argument("--progress", action="store_true")
    k = sub.add_parser("keep", help="copy what the run's folder in git keeps from the files a call returned")
    k.add_argument("src", type=Path, help="the returned files (the call's OUT)")
    k.add_argument("run", type=Path, help="the run's folder in git (tools/runs/NAME)")
    args = ap.parse_args(argv)
    if args.cmd == "measure":
        measure(args)
    elif args.cmd == "keep":
        returned = (args.src / run_weights.WEIGHTS).is_file()
        weights = keep(args.src, args.run)
        print(f"{args.run}: " + ("no weights returned" if not returned else
                                 f"in progress: {weights} and {run_weights.RECORD}" if weights else
                                 f"plan spent: {run_weights.RECORD} only (the weights stay in {args.src})"))
    else:
        print(json.dumps(train(args)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
