"""The training loader alone, over real shards: samples per second.

    .venv/bin/python benchmarks/bench_loader.py [--shards data/cpu-train-v3/extract]
        [--seconds 15] [--batch-size 256] [--out benchmarks/results/loader.json]

Reads the training shards an extract stage wrote (default: the first of
``data/cpu-train-v3/extract``, ``data/cpu-train/extract``, ``data/extract`` that exists)
exactly as the train stage does (:class:`cnnps.io.shards.ShardStream`: row groups in
the epoch's seeded order, Parquet decoding, the finiteness check, the 65,536-row shuffle
buffer) and times, for ``--seconds`` each, interleaved over two rounds (best kept):

- ``stream``: the numpy batches (maps float16, normals float32): what a GPU run sends to
  the device (float16 is converted there);
- ``dataset``: :class:`~cnnps.train.shard_dataset.ShardDataset`'s torch tensors, maps converted to
  float32 on the CPU: what a CPU run consumes;

each with ``prefetch`` 0 (row groups decoded in the consuming thread) and 2 (the
default: decoded ahead in a background thread, :mod:`cnnps.infra.prefetch`). Nothing else
runs: no network. Results with the CPU model and load averages go to ``--out``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_info  # noqa: E402
from cnnps.infra.atomic import write_text  # noqa: E402
from cnnps.io.shards import ShardStream, load_manifest, manifest_files  # noqa: E402
from cnnps.train.shard_dataset import ShardDataset  # noqa: E402

CANDIDATES = ("data/cpu-train-v3/extract", "data/cpu-train/extract", "data/extract")


def measure(kind: str, files, w: int, batch: int, prefetch: int, seconds: float, epoch: int) -> dict:
    stream = ShardStream(files, w, batch, seed=0, prefetch=prefetch)
    if kind == "dataset":
        ds = ShardDataset(stream)
        ds.set_epoch(epoch)
        it = iter(ds)
    else:
        it = stream.iter_epoch(epoch)
    n = 0
    t0 = time.perf_counter()
    for maps, _normals in it:
        n += len(maps)
        if time.perf_counter() - t0 >= seconds:
            break
    dt = time.perf_counter() - t0
    it.close()  # both are generators: stops the read-ahead thread
    return {"samples": n, "seconds": round(dt, 3), "samples_per_s": round(n / dt, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shards", type=Path, default=None)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "loader.json")
    args = ap.parse_args(argv)
    shards = args.shards or next((REPO / c for c in CANDIDATES if (REPO / c / "manifest.json").is_file()), None)
    if shards is None:
        print("no shards found: run an extract stage first (e.g. cnnps run-stage extract --preset cpu-train)")
        return 2
    manifest = load_manifest(shards)
    files = manifest_files(shards, manifest, "train")
    w = int(manifest["w"])
    load_before = os.getloadavg()
    rows: dict[str, list] = {}
    for r in range(args.rounds):
        for kind in ("stream", "dataset"):
            for prefetch in (0, 2):
                name = f"{kind}_prefetch{prefetch}"
                res = measure(kind, files, w, args.batch_size, prefetch, args.seconds, epoch=r)
                rows.setdefault(name, []).append(res)
                print(f"round {r}: {name:20s} {res['samples_per_s']:>10,.0f} samples/s", flush=True)
    best = {k: max(v, key=lambda x: x["samples_per_s"]) for k, v in rows.items()}
    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": "benchmarks/bench_loader.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "cpu": cpu_info(),
        "python": platform.python_version(),
        "shards": str(shards.relative_to(REPO) if shards.is_relative_to(REPO) else shards),
        "train_files": len(files),
        "train_rows": sum(s["rows"] for s in manifest["shards"] if s["split"] == "train"),
        "batch_size": args.batch_size,
        "shuffle_buffer_rows": 65536,
        "seconds_per_run": args.seconds,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "runs": rows,
        "best_samples_per_s": {k: v["samples_per_s"] for k, v in best.items()},
        "target_samples_per_s": 200000,
        "note": "loader alone, no network; best of interleaved rounds on a 2-core machine",
    }
    write_text(args.out, json.dumps(result, indent=1) + "\n")
    print(f"best: {result['best_samples_per_s']} -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
