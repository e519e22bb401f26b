"""Training throughput (samples/s) of CNN-PS on this machine's CPU for several variants.

    .venv/bin/python -m benchmarks.train.step_variants [--seconds 4] [--rounds 3] [--accuracy-steps 300]
        [--only SUBSTRING,...] [--out benchmarks/results/train/step_variants.json]

Each variant trains on in-memory sparse random float16 maps (gathered from a buffer and
decoded to float32 per batch as the loader does). The variants run interleaved: every
round gives each one ``--seconds`` of training, and the best round counts, so a load
change on a shared machine hits all of them alike. ``torch.compile`` variants report
their compile time (first step) separately. ``--accuracy-steps N`` also trains the real
stage for N steps on a tiny synthetic Lambertian dataset (w = 16) in fp32 and in bf16
and reports the validation error of each.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import Phases, Stopwatch, result_path, run_for, write_result
from benchmarks.machine import gemm_peaks
from cnnps.stages.train import Params
from cnnps.train.openmp import prefer_passive_openmp

prefer_passive_openmp()  # as the stage does (before torch loads); OMP_WAIT_POLICY=ACTIVE to compare
import torch  # noqa: E402

from cnnps.train.optimiser import compile_model, make_model, train_step  # noqa: E402


def variant(name: str, batch: int, **params) -> dict:
    """A variant: its name and train params (sections as mappings) at batch size ``batch``."""
    return dict(name=name, data={"batch_size": batch}, **params)


BASELINE = dict(channels_last=False, optimiser={"fused_adam": False})  # the stage's settings before the tuning
ONE_THREAD = {"cpu": {"threads": 1}}
VARIANTS = [
    variant("baseline fp32 bs128 (NCHW, foreach Adam)", 128, **BASELINE),
    variant("fp32 bs256 (NCHW, foreach Adam)", 256, **BASELINE),
    variant("fp32 bs128 channels_last", 128, channels_last=True, optimiser={"fused_adam": False}),
    variant("fp32 bs128 channels_last fused Adam, torch dropout masks (before)", 128,
            cpu={"dropout_masks": "torch"}),
    variant("fp32 bs128 channels_last fused Adam counter masks, reference layers", 128, cpu={"layers": "reference"}),
    variant("fp32 bs128 channels_last fused Adam counter masks fused layers (defaults)", 128),
    variant("fp32 bs64 counter masks", 64),
    variant("fp32 bs256 channels_last fused Adam", 256),
    variant("fp32 bs512 channels_last fused Adam", 512),
    variant("bf16 bs128 channels_last fused Adam", 128, precision="bf16"),
    variant("bf16 bs256 channels_last fused Adam", 256, precision="bf16"),
    variant("compiled fp32 bs128 channels_last fused Adam", 128, compile=True),
    variant("fp32 bs128 defaults, 1 thread", 128, **ONE_THREAD),
    variant("fp32 bs64 defaults, 1 thread", 64, **ONE_THREAD),
    variant("bf16 bs128 defaults, 1 thread", 128, precision="bf16", **ONE_THREAD),
    variant("bf16 bs64 defaults, 1 thread", 64, precision="bf16", **ONE_THREAD),
]


def data(n, w, rng):
    maps = np.zeros((n, w * w), np.float16)
    idx = rng.integers(0, w * w, (n, 80))
    np.put_along_axis(maps, idx, rng.random((n, 80)).astype(np.float16), 1)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    return maps.reshape(n, w, w), normals / np.linalg.norm(normals, axis=1, keepdims=True)


class Runner:
    """One variant: its model, optimiser and a step function over in-memory data."""

    def __init__(self, v: dict, w: int, maps, normals):
        v = dict(v)
        self.name = v.pop("name")
        self.p = Params(**{"precision": "fp32", **v})  # a variant names its precision, else fp32
        self.threads = self.p.cpu.threads or 2
        self.dev = torch.device("cpu")
        torch.set_num_threads(self.threads)
        self.raw, self.opt = make_model(w, self.p, self.dev)
        self.model = compile_model(self.raw, self.p)
        self.maps, self.normals = maps, normals
        self.rng = np.random.default_rng(1)
        self.phases = Phases()  # "load": the batches' gather and decoding
        self.steps = 0
        with Stopwatch() as sw:
            self.step()  # compiles when compiled
        self.first_step_s = sw.seconds
        self.step()

    def step(self):
        B = self.p.data.batch_size
        with self.phases("load"):
            idx = self.rng.choice(len(self.maps), B, replace=False)  # the shuffle buffer's gather
            x = torch.from_numpy(self.maps[idx].astype(np.float32)).unsqueeze(1)
            y = torch.from_numpy(self.normals[idx])
        counter = self.p.cpu.dropout_masks != "torch" and self.model is self.raw  # as the stage does
        self.raw.set_mask_key((self.p.seed, 0, self.steps) if counter else None)
        self.steps += 1
        return train_step(self.model, self.opt, x, y, self.dev, self.p.precision, self.p.channels_last)

    def run_for(self, seconds: float) -> float:
        """Samples per second over ``seconds`` of steps."""
        torch.set_num_threads(self.threads)
        batch = self.p.data.batch_size

        def one() -> int:
            self.step()
            return batch

        return run_for(one, seconds).per_second


def roofline(w: int, samples_per_s: dict[str, float]) -> dict:
    """The floating-point operations of one training sample (forward and backward of the
    network as trained, counted by torch's FlopCounterMode: a multiply-add is 2) against
    the best GEMM rates of this machine's 2 threads (:func:`benchmarks.machine.gemm_peaks`),
    measured now: the share of the peak of its own precision each variant reaches."""
    import torch.nn.functional as F
    from torch.utils.flop_counter import FlopCounterMode

    from cnnps.models.network import CNNPS

    torch.set_num_threads(2)
    model = CNNPS(w=w).train()
    x = torch.rand(64, 1, w, w)
    with FlopCounterMode(display=False) as fc:
        F.mse_loss(model(x), torch.zeros(64, 3)).backward()
    flop = fc.get_total_flops() / len(x)
    peaks = gemm_peaks()
    peak = {p: peaks[p] * 1e9 for p in ("fp32", "bf16")}
    return {"flop_per_sample_train": round(flop), "gemm_fp32_gflop_per_s": peaks["fp32"],
            "gemm_bf16_gflop_per_s": peaks["bf16"], "bf16_kernels": peaks["bf16_kernels"],
            "samples_per_s_at_gemm_peak": round(peak["fp32"] / flop),
            # each variant against the peak of the precision it ran in
            "share_of_gemm_peak": {k: round(v * flop / peak["bf16" if k.startswith("bf16") else "fp32"], 3)
                                   for k, v in samples_per_s.items()}}


def accuracy(steps: int) -> list[dict]:
    """fp32 vs bf16: val error of the real stage after ``steps`` steps on a tiny dataset."""
    from cnnps.stages import extract, train
    from tests.support.renders import make_render_dir

    torch.set_num_threads(2)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "src"
        make_render_dir(src, n_scenes=4, size=24, m=60)
        extract.run(extract.Params(w=16, min_lights=10, max_lights=50, rotations=4, val_fraction=0.25,
                                   rows_per_group=400), src)
        for precision in ("fp32", "bf16"):
            d = Path(tmp) / precision
            shutil.copytree(src / "extract", d / "extract")
            m = train.run(train.Params(max_steps=steps, data={"batch_size": 32, "shuffle_buffer": 1000},
                                       progress=False, val_every=0, cpu={"threads": 1}, precision=precision), d)
            out.append({"precision": precision, "steps": steps, "batch_size": 32, "w": 16,
                        "val_mean_deg": round(m["val_mean_deg"], 3), "val_median_deg": round(m["val_median_deg"], 3),
                        "train_loss": round(m["train_loss"], 5)})
            print(json.dumps(out[-1]), flush=True)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=4)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--w", type=int, default=32)
    ap.add_argument("--only", default="", help="comma-separated substrings of variant names to run")
    ap.add_argument("--accuracy-steps", type=int, default=0)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    ap.add_argument("--keep-freed-memory", action="store_true",
                    help="as the train stage does on a CPU (cnnps.train.allocator), for every variant: it lasts "
                         "for the process, so compare with a run without it")
    a = ap.parse_args()
    if a.keep_freed_memory:
        from cnnps.train.allocator import keep_freed_memory

        keep_freed_memory()
    maps, normals = data(8192, a.w, np.random.default_rng(0))
    chosen = [v for v in VARIANTS if not a.only or any(s in v["name"] for s in a.only.split(","))]
    load_before = os.getloadavg()[0]
    runners = [Runner(v, a.w, maps, normals) for v in chosen]
    rounds: dict[str, list[float]] = {r.name: [] for r in runners}
    for rnd in range(a.rounds):
        for r in runners:
            rounds[r.name].append(r.run_for(a.seconds))
        print(f"round {rnd}: " + json.dumps({k: round(v[-1], 1) for k, v in rounds.items()}), flush=True)
    best = {k: max(v) for k, v in rounds.items()}
    base = best[runners[0].name]
    res = []
    for r in runners:
        res.append({"variant": r.name, "threads": r.threads, "samples_per_s": round(best[r.name], 1),
                    "median_samples_per_s": round(statistics.median(rounds[r.name]), 1),
                    "rounds_samples_per_s": [round(x, 1) for x in rounds[r.name]],
                    "vs_first": round(best[r.name] / base, 2), "first_step_s": round(r.first_step_s, 2),
                    "load_s": round(r.phases.wall.get("load", 0.0), 2)})
        print(json.dumps(res[-1]))
    roof = roofline(a.w, best)
    print(f"roofline: {roof['flop_per_sample_train'] / 1e6:.0f} MFLOP a training sample, GEMM "
          f"{roof['gemm_fp32_gflop_per_s']} GFLOP/s -> at most {roof['samples_per_s_at_gemm_peak']:,} samples/s; "
          + json.dumps(roof["share_of_gemm_peak"]), flush=True)
    acc = accuracy(a.accuracy_steps) if a.accuracy_steps else None
    write_result(a.out, __spec__.name, a, {
        "load_average": {"before": load_before, "after": os.getloadavg()[0]},
        "timing": f"variants interleaved, best of {a.rounds} rounds of {a.seconds:g} s",
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "variants": res,
        "roofline": roof,
        "bf16_accuracy": acc,
    })


if __name__ == "__main__":
    main()
