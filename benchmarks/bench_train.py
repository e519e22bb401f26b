"""Training throughput (samples/s) of CNN-PS on this machine's CPU for several variants.

    .venv/bin/python benchmarks/bench_train.py [--seconds 15] [--out benchmarks/results/train.json]

Each variant trains on in-memory sparse random float16 maps (decoded to float32 per batch
as the loader does) for a fixed wall time after 3 warm-up steps.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from stages.train import Params, make_model, train_step

VARIANTS = [
    dict(name="fp32 bs128", batch_size=128),
    dict(name="fp32 bs256", batch_size=256),
    dict(name="fp32 bs256 channels_last", batch_size=256, channels_last=True),
    dict(name="bf16 bs256", batch_size=256, precision="bf16"),
    dict(name="fp32 bs256 1 thread", batch_size=256, threads=1),
]


def data(n, w, rng):
    maps = np.zeros((n, w * w), np.float16)
    idx = rng.integers(0, w * w, (n, 80))
    np.put_along_axis(maps, idx, rng.random((n, 80)).astype(np.float16), 1)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    return maps.reshape(n, w, w), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def bench(v: dict, seconds: float, w: int) -> dict:
    v = dict(v)
    name = v.pop("name")
    threads = v.pop("threads", 0)
    torch.set_num_threads(threads or 2)
    p = Params(**v)
    dev = torch.device("cpu")
    model, opt = make_model(w, p, dev)
    maps, normals = data(4096, w, np.random.default_rng(0))
    B = p.batch_size
    steps, t0, i = 0, None, 0
    while True:
        s = (i * B) % (len(maps) - B)
        x = torch.from_numpy(maps[s : s + B]).float().unsqueeze(1)
        y = torch.from_numpy(normals[s : s + B])
        train_step(model, opt, x, y, dev, p.precision, p.channels_last)
        i += 1
        if i == 3:
            t0 = time.perf_counter()
        elif i > 3:
            steps += 1
            if time.perf_counter() - t0 > seconds:
                break
    dt = time.perf_counter() - t0
    return {"variant": name, "threads": torch.get_num_threads(), "samples_per_s": round(steps * B / dt, 1), "steps": steps}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=15)
    ap.add_argument("--w", type=int, default=32)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/train.json"))
    a = ap.parse_args()
    res = []
    for v in VARIANTS:
        r = bench(v, a.seconds, a.w)
        print(json.dumps(r), flush=True)
        res.append(r)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({
        "command": f"benchmarks/bench_train.py --seconds {a.seconds} --w {a.w}",
        "machine": "2 CPU cores shared with other jobs (load average 5-7 while measured: noisy)",
        "torch": torch.__version__,
        "results": res,
    }, indent=1))


if __name__ == "__main__":
    main()
