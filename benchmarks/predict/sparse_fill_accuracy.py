"""The Lambertian fill (cnnps.ps.sparse_fill): does it pay, and which residual gate.

    .venv/bin/python -m benchmarks.predict.sparse_fill_accuracy [--model M] [--rotations 1 10]
        [--gates 0.03 0.06 0.1 0.2] [--counts 90] [--testset data/eval-v2/eval/testset]
        [--out benchmarks/results/predict/sparse_fill_accuracy.json]

Scores, per model, on
* the eval stage's synthetic test captures with 10 and 17 lights (``--testset``: an eval
  stage's ``testset`` folder; sphere, bowl, holed x Specular, Metallic), every pixel;
* DiLiGenT BALL from all 96, 40, 30, 20, 10 and 6 of its images (benchmarks/image_lists/), every pixel;

the network alone, and the network with virtual observations for the pixels whose
Lambertian fit residual is below each gate (``--gates``; 1e9 = every well-posed pixel),
the fit without the pixel's brightest observation where the first does not pass
(``--first-fit-only``: without that second chance). A gated pixel's map is exactly the
unfilled one or the one filled from one of the two fits, so each count needs three
network passes, not one per gate. ``--counts 90 1000``
also scores filling every free cell of the cone (there are fewer than 1,000). Least squares on the same
images (lit observations only, as the fill's fit) is listed for reference. The gate was
chosen on the synthetic captures, not on BALL (README, "Sparse images: the Lambertian fill").
Each run adds (or replaces) its model's row in ``--out``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    ROOT,
    Stopwatch,
    previous_results,
    result_path,
    write_result,
)
from benchmarks.subsets import drop_for, list_path, read_list
from cnnps.io.capture import load_capture
from cnnps.models.checkpoint import load_checkpoint
from cnnps.models.inference import predict_normals
from cnnps.ps.least_squares import least_squares_masked
from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.sparse_fill import (
    RESIDUAL_MAX,
    VIRTUAL_LIGHTS,
    lambertian_fits,
    virtual_lights,
)


def _cases(testset: Path, shared: Path):
    """(name, group, intensities, lights, true normals) of every capture scored."""
    for d in sorted(testset.iterdir()) if testset.is_dir() else []:
        if d.name.rsplit("-", 1)[-1] in ("10", "17"):
            cap = load_capture(d)
            yield d.name, f"eval-{d.name.rsplit('-', 1)[-1]}", cap.pixel_intensities(), cap.lights, cap.normal_gt[cap.mask]
    ball = shared / "data" / "diligent" / "ballPNG"
    if ball.is_dir():
        for n in (96, 40, 30, 20, 10, 6):
            drop = None if n == 96 else drop_for(ball, read_list(list_path(ball.name, n)))
            cap = load_capture(ball, drop=drop)
            yield f"ballPNG-{n}", f"ball-{n}", cap.pixel_intensities(), cap.lights, cap.normal_gt[cap.mask]


def _score(net, I, L, N, rotations, gates, counts, second: bool) -> dict:
    N = N / np.linalg.norm(N, axis=1, keepdims=True)
    normals, _, _ = least_squares_masked(I, L, shadow_threshold=0.0, return_valid=True)
    fits = lambertian_fits(I, L)
    if not second:  # the first fit alone (before the second chance existed)
        fits = type(fits)(fits.b, fits.residual, fits.b_second, np.full(len(I), np.inf))
    out = {"pixels": int(len(N)), "least_squares": float(angular_error_deg(normals, N).mean())}

    def run(X, LL, k):
        return predict_normals(net, X, LL, rotations=k, device="cpu", precision="fp32", progress=False, sparse_fill="off")

    for k in rotations:
        plain = run(I, L, k)
        row = {"net": float(angular_error_deg(plain, N).mean())}
        for count in counts:
            V = virtual_lights(L, count, net.w)
            # every pixel filled from each fit: a gated pixel's map is exactly one of these three
            by_fit = [run(np.concatenate([I, np.maximum(b @ V.T, 0).astype(np.float32)], axis=1), np.concatenate([L, V]), k)
                      for b in ((fits.b, fits.b_second) if second else (fits.b,))]
            for g in gates:
                first = fits.residual < g
                pred = np.where(first[:, None], by_fit[0], plain)
                if second:
                    pred = np.where((~first & (fits.residual_second < g))[:, None], by_fit[1], pred)
                _, filled = fits.choose(g)
                row[f"fill{count}_gate{g:g}"] = float(angular_error_deg(pred, N).mean())
                row[f"fill{count}_gate{g:g}_share"] = float(filled.mean())
        out[f"K{k}"] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=ROOT / "cnnps" / "models" / "weights" / "cnnps_default.pt")
    ap.add_argument("--name", default=None, help="key in the results file (default: the model file's name)")
    ap.add_argument("--rotations", type=int, nargs="+", default=[1, 10])
    ap.add_argument("--gates", type=float, nargs="+", default=[0.03, 0.06, RESIDUAL_MAX, 0.2, 1e9])
    ap.add_argument("--counts", type=int, nargs="+", default=[VIRTUAL_LIGHTS])
    ap.add_argument("--first-fit-only", action="store_true",
                    help="no second chance (the fill as first shipped: one fit on every lit observation)")
    ap.add_argument("--cases", nargs="*", default=None, help="only these (e.g. ballPNG-96 bowl-specular-10)")
    ap.add_argument("--testset", type=Path, default=ROOT / "data" / "eval-v2" / "eval" / "testset")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()
    net = load_checkpoint(args.model, "cpu")[0].eval()
    cases = {}
    with Stopwatch() as sw:
        for name, group, I, L, N in _cases(args.testset, args.shared):
            if args.cases is not None and name not in args.cases:
                continue
            cases[name] = {"group": group,
                           **_score(net, I, L, N, args.rotations, args.gates, args.counts, not args.first_fit_only)}
            print(name, json.dumps(cases[name]["K1" if 1 in args.rotations else f"K{args.rotations[0]}"]), flush=True)
    groups: dict = {}
    for c in cases.values():
        for k in args.rotations:
            for key, v in c[f"K{k}"].items():
                groups.setdefault(c["group"], {}).setdefault(f"K{k}", {}).setdefault(key, []).append(v)
            groups[c["group"]].setdefault("least_squares", []).append(c["least_squares"])
    means = {g: {k: ({m: round(float(np.mean(v)), 3) for m, v in d.items()} if isinstance(d, dict)
                     else round(float(np.mean(d)), 3))
                 for k, d in gd.items()} for g, gd in groups.items()}
    for g, gd in sorted(means.items()):
        print(g, json.dumps(gd))
    results = previous_results(args.out)
    results.setdefault("models", {})[args.name or args.model.name] = {  # this run's row beside the earlier ones'
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": shlex.join(["python", "-m", __spec__.name, *sys.argv[1:]]),
        "model": str(args.model), "seconds": round(sw.seconds, 1),
        "note": "mean angular error (deg); groups average their captures (eval: 6 captures each, "
                "sphere/bowl/holed x specular/metallic); gate 1e9 = every well-posed pixel filled",
        "group_means": means, "cases": cases}
    write_result(args.out, __spec__.name, args, results)


if __name__ == "__main__":
    main()
