"""How far the bf16 inference path moves the normals of real objects from fp32's.

    .venv/bin/python -m benchmarks.predict.bf16_agreement [--pixels 2000] [--rotations K]
        [--captures DIR ...] [--out FILE]

For each real capture (default: DiLiGenT BALL and the four 8-bit crops in ``../shared``)
a seeded sample of ``--pixels`` mask pixels (all of them with ``--pixels 0``) is predicted
with the shipped model by ``predict_normals`` in fp32 and in bf16 (``FastCNNPS`` with bf16
weights, what ``--precision bf16`` runs on a CPU), K rotations each (``--rotations``;
default 10 where oneDNN has bf16 kernels, 1 where bf16 runs on torch's reference kernels,
which are too slow for K=10 on whole objects). Reported per capture: the mean angular
error against the ground truth of each precision on the same pixels, its change (bf16
minus fp32: what the probe's 0.05° tolerance bounds on its own maps), and the angle
between the two precisions' normals (mean, 99th percentile, max). Results go to
``benchmarks/results/predict/bf16_agreement_<cpu kind>.json`` (the harness's record: the
CPU model and flags, the command, the commit).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, cpu_kind, result_path, write_result

SHARED = ROOT.parent / "shared" / "data"
DEFAULT_CAPTURES = [SHARED / "diligent" / "ballPNG"] + [SHARED / "diligent-crop8" / f"{n}PNG"
                                                        for n in ("cow", "goblet", "pot1", "pot2")]
SEED = 20261127


def agreement(capture: Path, net, pixels: int, rotations: int) -> dict:
    """The two precisions on one capture's sampled pixels (see the module docstring)."""
    from cnnps.io.capture import load_capture
    from cnnps.models.inference import predict_normals
    from cnnps.ps.metrics import angular_error_deg

    cap = load_capture(capture)
    I = cap.pixel_intensities()
    gt = cap.normal_gt[cap.mask] if cap.normal_gt is not None else None
    idx = np.arange(len(I))
    if pixels and pixels < len(I):
        idx = np.sort(np.random.default_rng([SEED, len(I)]).choice(len(I), pixels, replace=False))
    out, seconds = {}, {}
    for precision in ("fp32", "bf16"):
        with Stopwatch() as sw:
            out[precision] = predict_normals(net, I[idx], cap.lights, rotations=rotations, device="cpu",
                                             precision=precision, progress=False)
        seconds[precision] = round(sw.seconds, 2)
    dev = angular_error_deg(out["bf16"], out["fp32"])
    row = {"pixels": int(len(idx)), "of_pixels": int(len(I)), "rotations": rotations, "seconds": seconds,
           "deviation_mean_deg": round(float(dev.mean()), 4),
           "deviation_p99_deg": round(float(np.percentile(dev, 99)), 4),
           "deviation_max_deg": round(float(dev.max()), 4)}
    if gt is not None:
        err = {p: float(angular_error_deg(n, gt[idx]).mean()) for p, n in out.items()}
        row.update({"mean_error_fp32_deg": round(err["fp32"], 4), "mean_error_bf16_deg": round(err["bf16"], 4),
                    "error_change_deg": round(err["bf16"] - err["fp32"], 4)})
    return row


def main(argv=None) -> int:
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.shipped import shipped_model_path
    from cnnps.models.train_layers import mkldnn_bf16_available

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pixels", type=int, default=2000, help="sampled mask pixels per capture (0: all)")
    ap.add_argument("--rotations", type=int, default=None)
    ap.add_argument("--captures", type=Path, nargs="*", default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    captures = args.captures or [c for c in DEFAULT_CAPTURES if c.is_dir()]
    if not captures:
        print("no captures (../shared/data absent): nothing to measure")
        return 0
    kernels = mkldnn_bf16_available()
    rotations = args.rotations or (10 if kernels else 1)
    net = load_checkpoint(shipped_model_path(), "cpu")[0]
    rows = {}
    for c in captures:
        rows[c.name] = agreement(c, net, args.pixels, rotations)
        print(c.name, rows[c.name], flush=True)
    out = args.out or result_path(__spec__.name, cpu_kind())
    write_result(out, __spec__.name, {**vars(args), "rotations": rotations},
                 {"bf16_kernels": kernels, "captures": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
