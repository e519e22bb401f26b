"""K = 10 rotations on BALL pixels: one-pass map building with and without read-ahead,
the former per-rotation loop, and the network batch size, in one process.

    .venv/bin/python -m benchmarks.predict.rotation_speed [--pixels 4000] [--rounds 3]
        [--out benchmarks/results/predict/rotation_speed.json]

Every variant predicts the same BALL pixels with the shipped model at K = 10 (fast fp32)
and the variants run interleaved, ``--rounds`` times, so the machine's own swings hit
them alike; maps/s per round are recorded (and each variant's median and spread).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, measure_interleaved, result_path, write_result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ball", type=Path, default=ROOT.parent / "shared" / "data" / "diligent" / "ballPNG")
    ap.add_argument("--pixels", type=int, default=4000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()
    from cnnps.io.capture import load_capture
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor, rotated_normals
    from cnnps.models.shipped import shipped_model_path
    from cnnps.ps.obsmap import observation_maps
    from cnnps.ps.rotation import average_rotated_predictions, rotate_z, rotation_angles

    cap = load_capture(args.ball)
    I, L = cap.pixel_intensities()[: args.pixels], cap.lights
    net, _, _ = load_checkpoint(shipped_model_path())
    preds = {bs: MapPredictor(net, device="cpu", precision="fp32", batch_size=bs) for bs in (128, 256, 512)}
    angles = rotation_angles(10)

    def per_rotation_loop(pred):  # the former way: K separate observation_maps calls per chunk
        rot = [rotate_z(L, a) for a in angles]
        out = np.empty((len(I), 3), np.float32)
        for s in range(0, len(I), 4096):
            b = I[s:s + 4096]
            out[s:s + len(b)] = average_rotated_predictions(np.stack([pred(observation_maps(b, lk)) for lk in rot]), angles)
        return out

    runs = {"one_pass_read_ahead_bs256": lambda: rotated_normals(preds[256], I, L, 10, read_ahead=1),
            "one_pass_no_read_ahead_bs256": lambda: rotated_normals(preds[256], I, L, 10, read_ahead=0),
            "per_rotation_loop_bs256": lambda: per_rotation_loop(preds[256]),
            "one_pass_read_ahead_bs128": lambda: rotated_normals(preds[128], I, L, 10),
            "one_pass_read_ahead_bs512": lambda: rotated_normals(preds[512], I, L, 10)}
    ref = runs["per_rotation_loop_bs256"]()
    same = bool(np.array_equal(runs["one_pass_read_ahead_bs256"](), ref))
    timings = measure_interleaved(runs, repeat=args.rounds, warmup=0)  # the reference run above warmed up
    rates = {k: [round(len(I) * 10 / s) for s in t.samples] for k, t in timings.items()}
    print(rates, flush=True)
    res = {"pixels": len(I), "rotations": 10, "load_average_before_end": [round(x, 2) for x in os.getloadavg()],
           "one_pass_equals_per_rotation_loop": same, "maps_per_s_per_round": rates,
           "timings": {k: t.as_dict() for k, t in timings.items()}}
    print(f"identical normals: {same}")
    write_result(args.out, __spec__.name, args, res)


if __name__ == "__main__":
    main()
