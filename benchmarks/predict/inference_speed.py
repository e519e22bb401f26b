"""CNN-PS inference throughput on this machine.

    .venv/bin/python -m benchmarks.predict.inference_speed [--repeat 5] [--pixels 45000] [--no-k10]
        [--ball DIR | --no-ball] [--out FILE]

Results go to ``benchmarks/results/predict/inference_speed_<cpu kind>.json``
(:func:`benchmarks.machine.cpu_kind`: the CPU model and its widest vector extension, e.g.
``amd-epyc_avx2``), so one kind's numbers never overwrite another's.

Measures network inferences per second (maps prebuilt) for
  * eager fp32: the trained ``CNNPS`` as is (NCHW, batch 256) - the naive baseline;
  * fast fp32: what ``predict_normals`` runs on CPU (``FastCNNPS``, channels_last, batch 256),
    with all threads and with one thread (that one also in thread CPU time, which other
    processes on a shared machine disturb much less than wall time);
  * fast bf16: ``FastCNNPS`` with bf16 weights (what precision="bf16" runs on a CPU), where
    oneDNN has bf16 kernels (on AVX2 alone it runs on reference kernels and is skipped);
and the wall time of ``predict_normals`` for a whole object (``--pixels``, 96 lights,
observation maps included) at K = 1 (best of ``--repeat``) and K = 10 (one run).
``--precision auto``: the probe's choice on this machine for the shipped model
(:func:`cnnps.models.precision_probe.probe`, uncached), and DiLiGenT BALL at K=10 end to
end (``predict_folder`` in this process: images read, maps, network, rotations, outputs
written) with ``auto`` and with ``fp32``, against the naive eager forward pass of the same
network (``CNNPS`` as trained, fp32, NCHW, batch 256) over the same number of maps, timed
on 4,096 of BALL's own maps in the same run and scaled to all of them (the maps' values do
not change the time).

It also reports how far bf16 and the fast path move the predicted normals from the
eager fp32 network, in degrees (random he-initialised weights: a proxy until a trained
model exists). Speed does not depend on the weights' values.

Timings are ``--repeat`` runs, interleaved (best and median reported, with the spread in
``timings``); on a shared machine they are noisy, so the load average before and after is
recorded too.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import (
    ROOT,
    Stopwatch,
    cpu_info,
    cpu_kind,
    measure,
    measure_interleaved,
    result_path,
    write_result,
)
from benchmarks.machine import gemm_peaks
from cnnps.models.inference import MapPredictor, predict_normals
from cnnps.models.network import CNNPS
from cnnps.models.train_layers import mkldnn_bf16_available
from cnnps.ps.obsmap import observation_maps


def _scene(P: int, m: int = 96, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian pixels with cast-shadow-like dropouts under DiLiGenT-like lights."""
    rng = np.random.default_rng(seed)
    tilt = np.arccos(rng.uniform(np.cos(np.deg2rad(50)), 1.0, m))
    az = rng.uniform(0, 2 * np.pi, m)
    L = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)
    n = rng.normal(size=(P, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    I = rng.uniform(0.2, 1.0, (P, 1)) * np.maximum(n @ L.T, 0.0)
    I *= rng.uniform(size=I.shape) > 0.05  # a few cast shadows
    I += rng.normal(0, 0.002, I.shape)
    return np.maximum(I, 0).astype(np.float32), L


def ball_k10(ball: Path, repeat: int) -> dict:
    """BALL at K=10 end to end (``cnnps predict`` processes, auto and fp32) and the naive
    eager pass over the same number of maps, plus where the time goes."""
    import subprocess
    import tempfile

    from cnnps.io.capture import load_capture
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.precision_probe import probe
    from cnnps.models.shipped import weights_path
    from cnnps.ps.rotation import rotate_z, rotation_angles

    net, _, _ = load_checkpoint(weights_path(), "cpu")
    choice = probe(net, torch.device("cpu"))
    out = {"probe": choice.as_dict()}
    runs: dict[str, list] = {"auto": [], "fp32": []}
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, CNNPS_CACHE_DIR=str(Path(tmp) / "cache"),  # the first auto run probes
                   PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        for r in range(repeat):
            for precision in runs:
                dest = Path(tmp) / f"{precision}{r}"
                cmd = [sys.executable, "-m", "cnnps", "predict", str(ball), "--out", str(dest), "--rotations", "10",
                       "--device", "cpu", "--precision", precision, "--saturated", "keep", "--no-progress"]
                with Stopwatch() as sw:
                    subprocess.run(cmd, env=env, check=True, capture_output=True)
                wall = sw.seconds
                res = json.loads((dest / "prediction.json").read_text())
                res["mean_deg"] = json.loads((dest / "metrics.json").read_text())["mean_deg"]
                how = res.get("precision_choice") or {}
                runs[precision].append({
                    "seconds": round(wall, 2), "mean_deg": res["mean_deg"], "precision": res["precision"],
                    "probed": how.get("requested") == "auto" and not how.get("cached"),
                    "read_seconds": res["load_seconds"], "in_process_seconds": res["seconds"],
                })
    cap = load_capture(ball)
    I = cap.pixel_intensities()  # (P, m), intensities already divided out
    pixels = int(cap.mask.sum())
    with Stopwatch() as sw:
        for lk in (rotate_z(cap.lights, a) for a in rotation_angles(10)):
            for s in range(0, pixels, 4096):
                observation_maps(I[s:s + 4096], lk)
    maps_s = sw.seconds
    sample = observation_maps(I[:4096], cap.lights)
    x = torch.from_numpy(sample).unsqueeze(1)

    @torch.inference_mode()
    def eager():
        for s in range(0, len(x), 256):
            net(x[s:s + 256])

    eager_rate = len(x) / measure(eager, repeat=1, warmup=1).min
    naive = pixels * 10 / eager_rate
    best = {k: min(v, key=lambda r: r["seconds"]) for k, v in runs.items()}
    fp32 = best["fp32"]
    out.update({
        "command": "cnnps predict BALL --rotations 10 --device cpu --precision auto|fp32 --saturated keep",
        "pixels": pixels, "maps": pixels * 10, "runs": runs,
        "naive_eager_maps_per_s": round(eager_rate, 1), "naive_eager_seconds": round(naive, 1),
        "speedup_vs_naive": {k: round(naive / v["seconds"], 2) for k, v in best.items()},
        "target_speedup": 5.0,
        "where_the_time_goes_fp32": {
            "process_start_and_imports_s": round(fp32["seconds"] - fp32["in_process_seconds"], 2),
            "read_images_s": round(fp32["read_seconds"], 2),
            "observation_maps_all_rotations_s": round(maps_s, 2),
            "network_rotations_outputs_s": round(fp32["in_process_seconds"] - fp32["read_seconds"] - maps_s, 2),
        },
    })
    return out


def roofline(model, fast_maps_per_s: float, naive_maps_per_s: float | None, repeat: int = 3) -> dict:
    """What the CPU could do at best: the network's floating-point operations per map (the
    folded network the fast path runs, counted by torch's FlopCounterMode: a multiply-add
    is 2) against the best GEMM rates of this machine's threads in float32 and bf16
    (:func:`benchmarks.machine.gemm_peaks`), i.e. the rates a perfectly efficient network
    would reach in each precision."""
    from torch.utils.flop_counter import FlopCounterMode

    from cnnps.models.network import fold_for_inference

    folded = fold_for_inference(model).eval()
    x = torch.rand(64, 1, model.w, model.w)
    with torch.inference_mode():
        with FlopCounterMode(display=False) as fc:
            folded(x)
        with FlopCounterMode(display=False) as fc_trained:
            model(x)
    flop_per_map = fc.get_total_flops() / len(x)
    peaks = gemm_peaks(repeat=max(3, repeat))
    gemm = peaks["fp32"] * 1e9
    bound = gemm / flop_per_map
    out = {"flop_per_map_folded": round(flop_per_map), "flop_per_map_trained": round(fc_trained.get_total_flops() / len(x)),
           "gemm_fp32_gflop_per_s": peaks["fp32"], "gemm_bf16_gflop_per_s": peaks["bf16"],
           "bf16_kernels": peaks["bf16_kernels"], "maps_per_s_at_gemm_peak": round(bound),
           "maps_per_s_at_bf16_gemm_peak": round(peaks["bf16"] * 1e9 / flop_per_map),
           "fast_fp32_share_of_gemm_peak": round(fast_maps_per_s / bound, 3)}
    if naive_maps_per_s:
        out["best_possible_speedup_vs_naive"] = round(bound / naive_maps_per_s, 2)
    return out


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1, 1)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--pixels", type=int, default=45000)
    ap.add_argument("--maps", type=int, default=2048, help="maps per throughput run")
    ap.add_argument("--no-k10", action="store_true", help="skip the (long) K=10 whole-object run")
    ap.add_argument("--k10-pixels", type=int, default=None,
                    help="pixels for the K=10 run (default --pixels); fewer are scaled up to --pixels and marked so")
    ap.add_argument("--ball", type=Path, default=ROOT.parent / "shared" / "data" / "diligent" / "ballPNG",
                    help="DiLiGenT BALL for the end-to-end K=10 runs (skipped when absent)")
    ap.add_argument("--no-ball", action="store_true", help="skip the BALL runs")
    ap.add_argument("--ball-repeat", type=int, default=2)
    ap.add_argument("--no-throughput", action="store_true", help="only the probe and BALL")
    ap.add_argument("--out", type=Path, default=None,
                    help="default benchmarks/results/predict/inference_speed_<cpu kind>.json")
    args = ap.parse_args(argv)
    info = cpu_info()
    out_path = args.out or result_path(__spec__.name, cpu_kind(info))
    ball = None
    if not args.no_ball and args.ball.is_dir():
        ball = ball_k10(args.ball, args.ball_repeat)
        print(f"probe: {ball['probe']['precision']} ({ball['probe']['reason']}; {ball['probe']['probe_seconds']} s)")
        for k, v in ball["runs"].items():
            print(f"BALL K=10 --precision {k}: " + ", ".join(f"{r['seconds']} s ({r['precision']}, {r['mean_deg']:.3f} deg)" for r in v))
        print(f"naive eager: {ball['naive_eager_maps_per_s']:.0f} maps/s -> {ball['naive_eager_seconds']} s; "
              f"speedup {ball['speedup_vs_naive']}")
    if args.no_throughput:
        write_result(out_path, __spec__.name, args, {"ball_k10": ball}, argv=argv)
        return 0

    threads = torch.get_num_threads()
    load_before = os.getloadavg()
    torch.manual_seed(0)
    model = CNNPS().eval()
    I, L = _scene(max(args.pixels, args.maps))
    maps = observation_maps(I[: args.maps], L)
    x_nchw = torch.from_numpy(maps).unsqueeze(1)

    @torch.inference_mode()
    def eager():
        for s in range(0, len(x_nchw), 256):
            model(x_nchw[s:s + 256])

    fast = MapPredictor(model, device="cpu", precision="fp32")
    runs = {"eager_fp32": eager, "fast_fp32": lambda: fast(maps)}
    bf16 = None
    if mkldnn_bf16_available():
        bf16 = MapPredictor(model, device="cpu", precision="bf16")
        runs["fast_bf16"] = lambda: bf16(maps)
    # warmed up first (oneDNN primitive caches), then interleaved
    wall = measure_interleaved(runs, repeat=args.repeat, warmup=1)
    # one thread: wall and thread CPU time
    torch.set_num_threads(1)
    fast(maps[:256])
    one_wall = measure(lambda: fast(maps), repeat=args.repeat, warmup=0)
    one_cpu = measure(lambda: fast(maps), repeat=args.repeat, warmup=0, clock=time.thread_time)
    torch.set_num_threads(threads)

    n = len(maps)
    throughput = {
        name: {"threads": threads, "best_maps_per_s": n / t.min, "median_maps_per_s": n / t.median}
        for name, t in wall.items()
    }
    throughput["fast_fp32_1thread"] = {
        "threads": 1, "best_maps_per_s": n / one_wall.min, "median_maps_per_s": n / one_wall.median,
        "cpu_time_maps_per_s": n / one_cpu.min,
    }
    timings = {**{name: t.as_dict() for name, t in wall.items()}, "fast_fp32_1thread": one_wall.as_dict(),
               "fast_fp32_1thread_cpu_time": one_cpu.as_dict()}

    # agreement with the eager fp32 network (degrees)
    with torch.inference_mode():
        ref = model(x_nchw).numpy()
    agreement = {}
    for name, pred in (("fast_fp32", fast(maps)),) + ((("fast_bf16", bf16(maps)),) if bf16 else ()):
        err = _angles(ref, pred)
        agreement[name] = {"mean_deg": float(err.mean()), "p99_deg": float(np.percentile(err, 99)),
                           "max_deg": float(err.max())}

    naive = (ball or {}).get("naive_eager_maps_per_s") or throughput["eager_fp32"]["best_maps_per_s"]
    roof = roofline(model, throughput["fast_fp32"]["best_maps_per_s"], naive, args.repeat)

    # whole object, maps included
    P = args.pixels
    obj = {}
    k1 = measure(lambda: predict_normals(model, I[:P], L, rotations=1, device="cpu", progress=False),
                 repeat=max(1, min(args.repeat, 3)), warmup=0)
    obj["k1"] = {"pixels": P, "lights": L.shape[0], "best_s": k1.min, "median_s": k1.median, "runs_s": list(k1.samples)}
    if not args.no_k10:
        p10 = min(P, args.k10_pixels or P)
        with Stopwatch() as sw:
            predict_normals(model, I[:p10], L, rotations=10, device="cpu", progress=False)
        sec = sw.seconds
        obj["k10"] = {"pixels": P, "lights": L.shape[0], "seconds": sec * P / p10, "runs": 1,
                      "measured_pixels": p10, "extrapolated": p10 != P}

    result = {
        "threads": threads,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "maps_per_run": n,
        "repeat": args.repeat,
        "throughput": throughput,
        "timings": timings,
        "agreement_with_eager_fp32_random_weights": agreement,
        "roofline": roof,
        "whole_object": obj,
        "ball_k10": ball,
        "note": "interleaved repeats, best and median; shared machine, see load averages",
    }

    print(f"{info['model']}, {threads} threads, torch {torch.__version__}, "
          f"load {load_before[0]:.2f} -> {result['load_average_after'][0]:.2f}")
    print(f"{'path':22s} {'best maps/s':>12s} {'median':>10s}")
    for name, row in throughput.items():
        print(f"{name:22s} {row['best_maps_per_s']:12.0f} {row['median_maps_per_s']:10.0f}")
    print(f"{'fast_fp32 1 thread, CPU time':30s} {throughput['fast_fp32_1thread']['cpu_time_maps_per_s']:.0f} maps/s")
    for name, row in agreement.items():
        print(f"{name} vs eager fp32: mean {row['mean_deg']:.4f} deg, p99 {row['p99_deg']:.4f}, max {row['max_deg']:.4f}")
    print(f"roofline: {roof['flop_per_map_folded'] / 1e6:.1f} MFLOP a map, GEMM {roof['gemm_fp32_gflop_per_s']} GFLOP/s "
          f"-> at most {roof['maps_per_s_at_gemm_peak']:,} maps/s; fast fp32 at {roof['fast_fp32_share_of_gemm_peak']:.0%} of it; "
          f"best possible {roof.get('best_possible_speedup_vs_naive')}x the naive pass")
    print(f"whole object {P} px, K=1: {obj['k1']['best_s']:.2f} s (maps included)")
    if "k10" in obj:
        k10 = obj["k10"]
        how = f" (scaled from {k10['measured_pixels']} px)" if k10["extrapolated"] else ""
        print(f"whole object {P} px, K=10: {k10['seconds']:.2f} s{how}")
    write_result(out_path, __spec__.name, args, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
