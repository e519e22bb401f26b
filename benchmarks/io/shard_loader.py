"""The training loader alone, over real shards: samples per second.

    .venv/bin/python -m benchmarks.io.shard_loader [--shards data/cpu-train-v3/extract]
        [--seconds 15] [--batch-size 256] [--out benchmarks/results/io/shard_loader.json]

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
runs: no network. Results with the load averages go to ``--out``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from benchmarks.harness import ROOT, result_path, run_for, write_result
from cnnps.io.shards import ShardStream, load_manifest, manifest_files
from cnnps.train.shard_dataset import ShardDataset

CANDIDATES = ("data/cpu-train-v3/extract", "data/cpu-train/extract", "data/extract")


def measure(kind: str, files, w: int, batch: int, prefetch: int, seconds: float, epoch: int) -> dict:
    stream = ShardStream(files, w, batch, seed=0, prefetch=prefetch)
    if kind == "dataset":
        ds = ShardDataset(stream)
        ds.set_epoch(epoch)
        it = iter(ds)
    else:
        it = stream.iter_epoch(epoch)
    got = run_for(lambda: len(next(it)[0]), seconds)  # samples a batch, until the time is up
    it.close()  # both are generators: stops the read-ahead thread
    return {"samples": int(got.units), "seconds": round(got.seconds, 3), "samples_per_s": round(got.per_second, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shards", type=Path, default=None)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args(argv)
    shards = args.shards or next((ROOT / c for c in CANDIDATES if (ROOT / c / "manifest.json").is_file()), None)
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
        "shards": str(shards.relative_to(ROOT) if shards.is_relative_to(ROOT) else shards),
        "train_files": len(files),
        "train_rows": sum(s["rows"] for s in manifest["shards"] if s["split"] == "train"),
        "shuffle_buffer_rows": 65536,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "runs": rows,
        "best_samples_per_s": {k: v["samples_per_s"] for k, v in best.items()},
        "target_samples_per_s": 200000,
        "note": "loader alone, no network; best of interleaved rounds on a 2-core machine",
    }
    print(f"best: {result['best_samples_per_s']}")
    write_result(args.out, __spec__.name, args, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
