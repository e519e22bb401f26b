"""Observation-map throughput and capture load time.

    .venv/bin/python benchmarks/bench_obsmap.py [--repeat 3] [--out benchmarks/results/obsmap.json]

Measures maps built per second for a 45,000-pixel object under 96 lights (DiLiGenT
size) and under 1,300 lights (CNN-PS training density), the least-squares baseline on the
same object, and (when ../shared is present) the load time of DiLiGenT BALL plus the
whole `predict --method lambertian` path. Target: a 45,000-pixel object at K=1 in under
10 s including image reading. Timings are the best of ``--repeat`` runs (noisy on shared
machines). Results are printed as a table and written as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cnnps.ps.obsmap import observation_maps  # noqa: E402


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _lights(m: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.2
    return L / np.linalg.norm(L, axis=1, keepdims=True)


def bench_maps(P: int, m: int, repeat: int, chunk: int = 8192) -> dict:
    rng = np.random.default_rng(0)
    I = rng.uniform(0, 1, (P, m)).astype(np.float32)
    L = _lights(m, 1)

    def run():  # chunked like inference does, so memory stays bounded
        for s in range(0, P, chunk):
            observation_maps(I[s : s + chunk], L)

    t = _best(run, repeat)
    return {"pixels": P, "lights": m, "seconds": t, "maps_per_s": P / t}


def bench_lambertian(P: int, m: int, repeat: int) -> dict:
    from cnnps.ps.least_squares import least_squares

    rng = np.random.default_rng(0)
    I = rng.uniform(0, 1, (P, m))
    L = _lights(m, 1)
    plain = _best(lambda: least_squares(I, L), repeat)
    thresh = _best(lambda: least_squares(I, L, shadow_threshold=0.05), repeat)
    return {"pixels": P, "lights": m, "plain_s": plain, "threshold_s": thresh}


def bench_ball(repeat: int) -> dict | None:
    ball = Path(os.environ.get("CNNPS_SHARED", REPO.parent / "shared")) / "data" / "diligent" / "ballPNG"
    if not ball.is_dir():
        return None
    from cnnps.api.prediction import predict_folder
    from cnnps.io.capture import load_capture

    load = _best(lambda: load_capture(ball), repeat)
    cap = load_capture(ball)
    I = cap.pixel_intensities()
    maps = _best(lambda: observation_maps(I, cap.lights), repeat)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        res = predict_folder(ball, Path(tmp) / "out", method="lambertian", progress=False)
        predict_s = time.perf_counter() - t
    return {
        "images": cap.n_images,
        "image_size": list(cap.shape),
        "pixels": cap.n_pixels,
        "load_s": load,
        "maps_s": maps,
        "predict_lambertian_s": predict_s,
        "lambertian_mean_deg": res["mean_deg"],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pixels", type=int, default=45000)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "obsmap.json")
    args = ap.parse_args(argv)

    rows = [bench_maps(args.pixels, 96, args.repeat), bench_maps(args.pixels, 1300, args.repeat)]
    lam = bench_lambertian(args.pixels, 96, args.repeat)
    ball = bench_ball(args.repeat)

    print(f"{'what':42s} {'seconds':>9s} {'rate':>16s}")
    for r in rows:
        print(f"{'maps, %d px x %d lights' % (r['pixels'], r['lights']):42s} {r['seconds']:9.3f} {r['maps_per_s']:12,.0f} /s")
    print(f"{'least squares, %d px x 96 (plain)' % lam['pixels']:42s} {lam['plain_s']:9.3f}")
    print(f"{'least squares, %d px x 96 (threshold)' % lam['pixels']:42s} {lam['threshold_s']:9.3f}")
    if ball is None:
        print("DiLiGenT BALL: skipped (../shared not found)")
    else:
        print(f"{'BALL load (96 x 16-bit 612x512 PNG)':42s} {ball['load_s']:9.3f}")
        print(f"{'BALL maps (%d px)' % ball['pixels']:42s} {ball['maps_s']:9.3f}")
        print(f"{'BALL predict --method lambertian (all)':42s} {ball['predict_lambertian_s']:9.3f}   mean {ball['lambertian_mean_deg']:.2f} deg")

    result = {
        "maps": rows,
        "lambertian": lam,
        "ball": ball,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__,
                    "platform": platform.platform()},
        "repeat": args.repeat,
        "note": "best of repeat runs; machine shared with other work, timings noisy",
    }
    from cnnps.infra.atomic import write_text

    write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
