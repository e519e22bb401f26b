"""How well the confidence map that ``cnnps predict`` writes ranks pixels by their error.

    .venv/bin/python -m benchmarks.predict.confidence_map [--rotations 10] [--captures DIR ...] [--out FILE]

For each real capture with ground truth (default: DiLiGenT BALL and the four 8-bit crops
in ``../shared``), :func:`cnnps.predict` runs with the shipped model (K rotations, fp32,
defaults otherwise) and with least squares, on every mask pixel with a ground-truth
normal, and each returned ``Prediction.confidence`` is judged against that method's
angular error: Spearman's rank correlation of (1 - confidence) with the error, and the
mean error of the most confident half of the pixels against the other half; for least
squares also the condition of the lit lights (:func:`cnnps.ps.confidence.lit_condition`),
the alternative it was measured against. Results:
``benchmarks/results/predict/confidence_map_<cpu kind>.json`` (with ``--methods``, the
methods in the name).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.harness import Stopwatch, cpu_kind, result_path, write_result
from benchmarks.predict.bf16_agreement import DEFAULT_CAPTURES


def judge(confidence: np.ndarray, err: np.ndarray) -> dict:
    """Spearman of (1 - confidence) with ``err``, and the halves' mean errors."""
    from scipy.stats import spearmanr

    order = np.argsort(-confidence, kind="stable")
    half = len(order) // 2
    return {"spearman": round(float(spearmanr(-confidence, err).statistic), 3),
            "mean_error_deg": round(float(err.mean()), 3),
            "mean_error_confident_half_deg": round(float(err[order[:half]].mean()), 3),
            "mean_error_other_half_deg": round(float(err[order[half:]].mean()), 3)}


def score(capture: Path, rotations: int, methods: tuple[str, ...] = ("cnn", "lambertian")) -> dict:
    import cnnps
    from cnnps.io.capture import DILIGENT_RULES, benchmark_drop, load_capture
    from cnnps.ps.confidence import lit, lit_condition
    from cnnps.ps.metrics import angular_error_deg

    cap = load_capture(capture, drop=benchmark_drop(capture, DILIGENT_RULES))
    gt = cap.normal_gt
    scored = cap.mask & (np.linalg.norm(gt, axis=2) > 0.5)
    out = {"pixels": int(scored.sum())}
    options = {"cnn": {"rotations": rotations, "precision": "fp32"}, "lambertian": {}}
    for method in methods:
        with Stopwatch() as sw:
            res = cnnps.predict(cap.images, cap.lights, cap.mask, intensities=cap.intensities, method=method,
                                **options[method])
        err = angular_error_deg(res.normals[scored], gt[scored])
        out[method] = {**judge(res.confidence[scored], err), "seconds": round(sw.seconds, 1),
                       "measure": res.record["confidence"]["measure"]}
        if method == "lambertian":  # the alternative measured beside it: the condition of the lit lights
            I = cap.pixel_intensities()[scored[cap.mask]]
            out[method]["lit_condition"] = judge(lit_condition(cap.lights, lit(I, None)), err)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=["cnn", "lambertian"], choices=["cnn", "lambertian"])
    ap.add_argument("--captures", type=Path, nargs="*", default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    captures = args.captures or [c for c in DEFAULT_CAPTURES if c.is_dir()]
    if not captures:
        print("no captures (../shared/data absent): nothing to measure")
        return 0
    rows = {}
    for c in captures:
        rows[c.name] = score(c, args.rotations, tuple(args.methods))
        print(c.name, json.dumps(rows[c.name]), flush=True)
    suffix = cpu_kind() if len(args.methods) == 2 else f"{'-'.join(args.methods)}_{cpu_kind()}"
    out = args.out or result_path(__spec__.name, suffix)
    write_result(out, __spec__.name, args, {"captures": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
