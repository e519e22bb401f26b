"""Observation-map throughput and capture load time.

    .venv/bin/python -m benchmarks.predict.obsmap_speed [--repeat 3] [--pixels 45000] [--no-ball]
        [--out benchmarks/results/predict/obsmap_speed.json]

Measures maps built per second for a 45,000-pixel object under 96 lights (DiLiGenT
size) and under 1,300 lights (CNN-PS training density), the least-squares baseline on the
same object, and (when ../shared is present) the load time of DiLiGenT BALL plus the
whole `predict --method lambertian` path. Target: a 45,000-pixel object at K=1 in under
10 s including image reading. Timings: ``--repeat`` runs after one warm-up, the best in the
table (noisy on shared machines), median and spread in the JSON.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, measure, result_path, write_result
from cnnps.ps.obsmap import observation_maps


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

    t = measure(run, repeat=repeat)
    return {"pixels": P, "lights": m, "seconds": t.min, "maps_per_s": P / t.min, "timing": t.as_dict()}


def bench_lambertian(P: int, m: int, repeat: int) -> dict:
    from cnnps.ps.least_squares import least_squares

    rng = np.random.default_rng(0)
    I = rng.uniform(0, 1, (P, m))
    L = _lights(m, 1)
    plain = measure(lambda: least_squares(I, L), repeat=repeat)
    thresh = measure(lambda: least_squares(I, L, shadow_threshold=0.05), repeat=repeat)
    return {"pixels": P, "lights": m, "plain_s": plain.min, "threshold_s": thresh.min,
            "timings": {"plain": plain.as_dict(), "threshold": thresh.as_dict()}}


def bench_ball(repeat: int) -> dict | None:
    ball = Path(os.environ.get("CNNPS_SHARED", ROOT.parent / "shared")) / "data" / "diligent" / "ballPNG"
    if not ball.is_dir():
        return None
    from cnnps.api.prediction import predict_folder
    from cnnps.io.capture import load_capture

    load = measure(lambda: load_capture(ball), repeat=repeat, warmup=0)
    cap = load_capture(ball)
    I = cap.pixel_intensities()
    maps = measure(lambda: observation_maps(I, cap.lights), repeat=repeat)
    with tempfile.TemporaryDirectory() as tmp:
        with Stopwatch() as sw:
            res = predict_folder(ball, Path(tmp) / "out", method="lambertian", progress=False)
        predict_s = sw.seconds
    return {
        "images": cap.n_images,
        "image_size": list(cap.shape),
        "pixels": cap.n_pixels,
        "load_s": load.min,
        "maps_s": maps.min,
        "timings": {"load": load.as_dict(), "maps": maps.as_dict()},
        "predict_lambertian_s": predict_s,
        "lambertian_mean_deg": res["mean_deg"],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pixels", type=int, default=45000)
    ap.add_argument("--no-ball", action="store_true", help="skip DiLiGenT BALL")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args(argv)

    rows = [bench_maps(args.pixels, 96, args.repeat), bench_maps(args.pixels, 1300, args.repeat)]
    lam = bench_lambertian(args.pixels, 96, args.repeat)
    ball = None if args.no_ball else bench_ball(args.repeat)

    print(f"{'what':42s} {'seconds':>9s} {'rate':>16s}")
    for r in rows:
        print(f"{'maps, %d px x %d lights' % (r['pixels'], r['lights']):42s} {r['seconds']:9.3f} {r['maps_per_s']:12,.0f} /s")
    print(f"{'least squares, %d px x 96 (plain)' % lam['pixels']:42s} {lam['plain_s']:9.3f}")
    print(f"{'least squares, %d px x 96 (threshold)' % lam['pixels']:42s} {lam['threshold_s']:9.3f}")
    if ball is None:
        print("DiLiGenT BALL: skipped (--no-ball, or ../shared not found)")
    else:
        print(f"{'BALL load (96 x 16-bit 612x512 PNG)':42s} {ball['load_s']:9.3f}")
        print(f"{'BALL maps (%d px)' % ball['pixels']:42s} {ball['maps_s']:9.3f}")
        print(f"{'BALL predict --method lambertian (all)':42s} {ball['predict_lambertian_s']:9.3f}   mean {ball['lambertian_mean_deg']:.2f} deg")

    result = {
        "maps": rows,
        "lambertian": lam,
        "ball": ball,
        "numpy": np.__version__,
        "note": "seconds: the best of --repeat runs (timings: median and spread); machine shared, timings noisy",
    }
    write_result(args.out, __spec__.name, args, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
