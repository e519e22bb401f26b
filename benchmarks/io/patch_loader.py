"""The patch loader alone (spatial context): samples and maps per second for b = 1, 3, 5.

    .venv/bin/python -m benchmarks.io.patch_loader [--lights 400] [--size 128] [--scenes 4]
        [--batch-size 128] [--seconds 10] [--rounds 2] [--out benchmarks/results/io/patch_loader.json]

Writes ``--scenes`` synthetic observation files (:mod:`cnnps.io.observation_store`: a
sphere of ``--size`` x ``--size`` pixels, Lambertian with attached shadows, ``--lights``
lights on the upper hemisphere) into a temporary folder, then times
:class:`cnnps.train.patch_dataset.PatchStream` with the extract stage's default light
subsets (cones of 20-90 degrees, 50 to all lights) and 10 rotation angles (36 degree
steps: bilinear cells) for ``--seconds`` per patch size, the sizes interleaved over
``--rounds`` rounds (best kept: the machine is shared); ``b5_nearest`` is b = 5 with
nearest cells. A sample is one patch (b * b maps). Wall rates and this process's CPU rates
(a steadier estimate of an idle core under load: numpy runs the loader on one thread)
go to ``--out`` with the load averages.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import Phases, result_path, write_result
from cnnps.io.observation_store import observation_path, write_observations
from cnnps.train.patch_dataset import PatchSampling, PatchStream

CASES = {"b1": dict(b=1), "b3": dict(b=3), "b5": dict(b=5), "b5_nearest": dict(b=5, interpolation="nearest")}


def write_scenes(folder: Path, n: int, size: int, m: int) -> list:
    rng = np.random.default_rng(0)
    files = []
    for s in range(n):
        c = (np.arange(size) + 0.5) / size - 0.5
        x, y = np.meshgrid(c - rng.uniform(-0.03, 0.03), -c - rng.uniform(-0.03, 0.03))
        rad = rng.uniform(0.35, 0.48)
        rr = (x**2 + y**2) / rad**2
        mask = rr < 0.97
        normals = np.stack([x / rad, y / rad, np.sqrt(np.clip(1 - rr, 0, None))], -1)[mask]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        z = rng.uniform(0.05, 1, m)
        phi = rng.uniform(0, 2 * np.pi, m)
        L = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
        values = np.clip(normals @ L.T, 0, None) * rng.uniform(0.2, 1.0)
        rows, cols = np.nonzero(mask)
        rec = write_observations(folder, f"s{s}", values, L, normals, rows, cols, mask.shape, scene_key=f"k{s}")
        files.append((observation_path(folder, f"s{s}"), rec))
    return files


def measure(files, case: dict, batch: int, seconds: float, epoch: int) -> dict:
    stream = PatchStream(files, PatchSampling(**case), batch, seed=0)
    it = stream.iter_epoch(epoch)
    phases = Phases()
    samples = batches = 0
    while phases.wall.get("batches", 0.0) < seconds:
        with phases("batches"):
            got = next(it, None)
        if got is None:
            it = stream.iter_epoch(epoch := epoch + 1)
            continue
        samples += len(got[0])
        batches += 1
    cells = case["b"] ** 2
    wall, cpu = phases.wall["batches"], phases.cpu["batches"]
    return {"batches": batches, "samples": samples, "seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
            "samples_per_s": round(samples / wall, 1), "maps_per_s": round(samples * cells / wall, 1),
            "cpu_samples_per_s": round(samples / cpu, 1), "cpu_maps_per_s": round(samples * cells / cpu, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lights", type=int, default=400)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args(argv)
    load_before = os.getloadavg()
    runs: dict[str, list] = {}
    with tempfile.TemporaryDirectory() as d:
        files = write_scenes(Path(d), args.scenes, args.size, args.lights)
        for r in range(args.rounds):
            for name, case in CASES.items():
                res = measure(files, case, args.batch_size, args.seconds, epoch=r)
                runs.setdefault(name, []).append(res)
                print(f"round {r}: {name:11s} {res['samples_per_s']:>8,.0f} samples/s {res['maps_per_s']:>9,.0f} "
                      f"maps/s (CPU {res['cpu_samples_per_s']:>8,.0f} samples/s)", flush=True)
        pixels = sum(rec["rows"] for _, rec in files)
    best = {k: max(v, key=lambda x: x["samples_per_s"]) for k, v in runs.items()}
    result = {
        "pixels": pixels,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "runs": runs,
        "best": best,
        "train_step_samples_per_s": 1000,
        "note": "loader alone (one process, numpy on one thread), no network; best of interleaved rounds",
    }
    write_result(args.out, __spec__.name, args, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
