"""Which per-pixel measures predict the network's angular error on real objects.

    .venv/bin/python -m benchmarks.predict.confidence_measures [--pixels 3000] [--rotations 10]
        [--captures DIR ...] [--model WEIGHTS] [--out FILE]

For each real capture with ground truth (default: DiLiGenT BALL and the four 8-bit crops
in ``../shared``), a seeded sample of ``--pixels`` mask pixels is predicted by the shipped
model (or ``--model``, a weights file) with K rotations (``cnnps predict``'s network path: ``MapPredictor``, maps of the
rotated lights), keeping each rotation's answer. Candidate measures of how far to trust a
pixel, each oriented so that larger means less trust:

- ``rotation_spread``: the mean angle between the K back-rotated answers and their
  normalised mean (what test-time rotation averaging already computes);
- ``ls_residual``: least squares' relative residual, |I - L n rho| / |I| over the lit
  observations (the Lambertian model's misfit: shadows, specularities, inter-reflection);
- ``ls_disagreement``: the angle between the network's normal and least squares';
- ``dark_lights``: the share of the pixel's lights that read under 2 % of its brightest
  (shadowed or facing away);
- ``grazing``: 1 - n_z of the network's normal;
- ``spread_per_lit_share``: the rotation spread divided by the share of lit lights (what
  :func:`cnnps.ps.confidence.network_confidence` ranks by);
- a heat-map model only: ``heatmap_spread``, its heat-map's windowed second moment in
  degrees (:func:`cnnps.models.heatmap.heatmap_spread_deg`) averaged over the K rotations,
  and ``heatmap_spread_per_lit_share`` (what :func:`cnnps.ps.confidence.heatmap_confidence`
  ranks by, the heat-map model's confidence map).

For each measure: Spearman's rank correlation with the network's angular error, and the
mean error of the half of the pixels it trusts most against the other half. Results go to
``benchmarks/results/predict/confidence_measures_<cpu kind>.json`` (with ``--model``,
``confidence_measures_<weights file stem>_<cpu kind>.json``; the harness's record: the CPU
model, the command, the commit).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.harness import cpu_kind, result_path, write_result
from benchmarks.predict.bf16_agreement import DEFAULT_CAPTURES, SEED

DARK = 0.02  # a light reading under this share of the pixel's brightest counts as dark


def measures(capture: Path, predictor, pixels: int, rotations: int) -> dict:
    """The candidate measures and the network's error on one capture's sampled pixels."""
    from scipy.stats import spearmanr

    from cnnps.io.capture import load_capture
    from cnnps.models.heads import is_heatmap
    from cnnps.ps.least_squares import least_squares
    from cnnps.ps.metrics import angular_error_deg
    from cnnps.ps.obsmap import observation_maps_multi
    from cnnps.ps.rotation import normalize, rotate_z, rotation_angles

    cap = load_capture(capture)
    I_all = cap.pixel_intensities()
    gt_all = cap.normal_gt[cap.mask]
    ok = np.linalg.norm(gt_all, axis=1) > 0.5  # pixels with a ground-truth normal
    idx = np.flatnonzero(ok)
    if pixels and pixels < len(idx):
        idx = np.sort(np.random.default_rng([SEED, len(idx)]).choice(idx, pixels, replace=False))
    I, gt = I_all[idx], gt_all[idx].astype(np.float64)
    angles = rotation_angles(rotations)
    rotated = np.stack([rotate_z(cap.lights, a) for a in angles])
    maps = observation_maps_multi(I, rotated, w=predictor.w)  # (K, P, w, w)
    K, P = maps.shape[:2]
    hm = np.empty(K * P, np.float32) if is_heatmap(predictor.head) else None
    preds = predictor(maps.reshape(K * P, predictor.w, predictor.w), spread=hm).reshape(K, P, 3).astype(np.float64)
    back = np.stack([rotate_z(p, -a) for p, a in zip(preds, angles)])
    n = normalize(back.mean(axis=0))
    err = angular_error_deg(n, gt)
    spread = np.mean([angular_error_deg(b, n) for b in back], axis=0)
    n_ls, rho = least_squares(I, cap.lights)
    lit = I > DARK * I.max(axis=1, keepdims=True)
    fit = rho[:, None] * np.clip(n_ls @ cap.lights.T, 0, None)
    resid = np.linalg.norm((I - fit) * lit, axis=1) / np.maximum(np.linalg.norm(I * lit, axis=1), 1e-12)
    cand = {
        "rotation_spread": spread,
        "ls_residual": resid,
        "ls_disagreement": angular_error_deg(n, n_ls),
        "dark_lights": 1.0 - lit.mean(axis=1),
        "grazing": 1.0 - n[:, 2],
        "spread_per_lit_share": spread / np.maximum(lit.mean(axis=1), 0.05),  # what the confidence map uses
    }
    if hm is not None:  # a heat-map model: its own spread, the mean over the K rotations
        cand["heatmap_spread"] = hm.reshape(K, P).mean(axis=0)
        cand["heatmap_spread_per_lit_share"] = cand["heatmap_spread"] / np.maximum(lit.mean(axis=1), 0.05)
    out = {"pixels": int(P), "rotations": rotations, "mean_error_deg": round(float(err.mean()), 3), "measures": {}}
    for name, m in cand.items():
        order = np.argsort(m, kind="stable")
        half = len(order) // 2
        rho_s = spearmanr(m, err).statistic
        out["measures"][name] = {
            "spearman": round(float(rho_s), 3),
            "mean_error_trusted_half_deg": round(float(err[order[:half]].mean()), 3),
            "mean_error_other_half_deg": round(float(err[order[half:]].mean()), 3),
        }
    return out


def main(argv=None) -> int:
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor
    from cnnps.models.shipped import shipped_model_path

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pixels", type=int, default=3000, help="sampled pixels with ground truth per capture (0: all)")
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--captures", type=Path, nargs="*", default=None)
    ap.add_argument("--model", type=Path, default=None, help="a weights file (default: the shipped model)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    captures = args.captures or [c for c in DEFAULT_CAPTURES if c.is_dir()]
    if not captures:
        print("no captures (../shared/data absent): nothing to measure")
        return 0
    predictor = MapPredictor(load_checkpoint(args.model or shipped_model_path(), "cpu")[0], device="cpu",
                             precision="fp32")
    rows = {}
    for c in captures:
        rows[c.name] = measures(c, predictor, args.pixels, args.rotations)
        print(c.name, json.dumps(rows[c.name]), flush=True)
    name = __spec__.name if args.model is None else f"{__spec__.name}_{args.model.stem}"
    out = args.out or result_path(name, cpu_kind())
    write_result(out, __spec__.name, args, {"captures": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
