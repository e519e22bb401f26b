"""Extract throughput (maps/s) and the error of storing maps as float16.

    .venv/bin/python benchmarks/bench_extract.py [--pixels 8192] [--out benchmarks/results/extract.json]

Synthetic Lambertian pixels (random normals, albedo, lights on the upper hemisphere),
no file reading: measures light sampling + observation maps for 10 rotations
(``build_rows``) and the Parquet encoding + zstd writing, for several light counts m.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from cnnps.obsmap import observation_maps
from cnnps.rotation import rotation_angles
from stages.extract import Params, build_rows, sample_light_masks
from stages.shards import SceneShardWriter, make_batch, shard_schema


def lambertian(rng, P, m):
    z = rng.uniform(0.05, 1, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    L = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
    n = rng.normal(size=(P, 3))
    n[:, 2] = np.abs(n[:, 2])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    I = (np.clip(n @ L.T, 0, None) * rng.uniform(0.2, 1, (P, 1))).astype(np.float32)
    return I, n, L


def bench(m: int, P: int, p: Params) -> dict:
    rng = np.random.default_rng(0)
    I, n, L = lambertian(rng, P, m)
    angles = rotation_angles(p.rotations)
    schema = shard_schema(p.w)
    t_sample = t_maps = t_write = 0.0
    with tempfile.TemporaryDirectory() as d:
        with SceneShardWriter(Path(d), "shard-bench", schema, p.rows_per_group, p.rows_per_shard) as wr:
            for s in range(0, P, p.chunk_pixels):
                sl = slice(s, s + p.chunk_pixels)
                k = I[sl].shape[0]
                t = time.perf_counter()
                mask, cone, nl = sample_light_masks(rng, L, k, p.min_lights, p.max_lights, p.cone_min_deg, p.cone_max_deg)
                t_sample += time.perf_counter() - t
                t = time.perf_counter()
                maps, rn = build_rows(I[sl], n[sl], L, mask, angles, p.w)
                t_maps += time.perf_counter() - t
                t = time.perf_counter()
                R = len(angles)
                z = np.zeros(R * k)
                wr.write(make_batch(schema, maps.reshape(-1, p.w, p.w), rn.reshape(-1, 3), "bench", z, z, z, z, z, z))
                t_write += time.perf_counter() - t
            t = time.perf_counter()
        t_write += time.perf_counter() - t
        size = sum(f.stat().st_size for f in Path(d).glob("*.parquet"))
    rows = P * len(angles)
    total = t_sample + t_maps + t_write
    # float16 storage error on this data
    mask, _, _ = sample_light_masks(np.random.default_rng(1), L, 2000, p.min_lights, p.max_lights, p.cone_min_deg, p.cone_max_deg)
    m32 = observation_maps(I[:2000], L, p.w, light_mask=mask)
    err = np.abs(m32.astype(np.float16).astype(np.float32) - m32)
    return {
        "lights": m,
        "pixels": P,
        "rows": rows,
        "maps_per_s_total": round(rows / total),
        "maps_per_s_sampling_and_maps": round(rows / (t_sample + t_maps)),
        "maps_per_s_writing": round(rows / t_write),
        "seconds": {"sample": round(t_sample, 3), "maps": round(t_maps, 3), "write": round(t_write, 3)},
        "bytes_per_row": round(size / rows, 1),
        "float16_abs_error": {"max": float(err.max()), "mean_nonzero": float(err[m32 > 0].mean())},
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pixels", type=int, default=8192)
    ap.add_argument("--lights", type=int, nargs="+", default=[96, 300, 1300])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/extract.json"))
    a = ap.parse_args()
    p = Params()
    results = [bench(m, a.pixels, p) for m in a.lights]
    for r in results:
        print(json.dumps(r))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({
        "command": "benchmarks/bench_extract.py " + " ".join(f"--{k} {v}" for k, v in vars(a).items() if k != "out"),
        "machine": f"{platform.processor() or platform.machine()}, 2 cores shared with other jobs (noisy)",
        "params": {"w": p.w, "rotations": p.rotations, "min_lights": p.min_lights, "max_lights": p.max_lights,
                   "chunk_pixels": p.chunk_pixels},
        "results": results,
    }, indent=1))


if __name__ == "__main__":
    main()
