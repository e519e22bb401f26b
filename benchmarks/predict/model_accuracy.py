"""The shipped (or a given) model against the published CNN-PS numbers, and its speed.

    .venv/bin/python -m benchmarks.predict.model_accuracy [--model PATH] [--shared ../shared]
        [--out benchmarks/results/predict/model_accuracy.json]

Measures, with `cnnps predict` (images read included):
  * DiLiGenT BALL (../shared/data/diligent/ballPNG): mean / median angular error at K=1 and
    K=10, fp32 and bf16, next to least squares on the same pixels;
  * the whole-object time for BALL;
  * the fossil capture (../shared/data/captures/fossil, no ground truth; K=1: 307,000 pixels): writes the predicted
    normal picture to docs/images/fossil_normals.png (shown in the README);
  * time for a 45,000-pixel object (96 lights) at K=1 and K=10, fp32 and bf16;
  * with ``--subsets 20 10 6``: BALL from n of its 96 images (the lists in
    benchmarks/image_lists/, drawn by tools/image_subsets.py's seeded rule), CNN K=1
    and K=10 against least squares on the same images and pixels, each with the network
    alone (``cnn_k*_fp32``) and with the Lambertian fill (``cnn_k*_fp32_fill``, what
    ``cnnps predict`` does below 50 images; cnnps.ps.sparse_fill). ``--only-subsets``
    measures just that (results under ``ball_subsets``, merged into an existing --out file).
Skips the parts whose data is absent. Published on BALL: least squares 4.10°, PS-FCN 2.82°,
CNN-PS 2.7° (K=1) / 2.2° (K=10).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
from pathlib import Path

from benchmarks.harness import (
    ROOT,
    Stopwatch,
    previous_results,
    result_path,
    write_result,
)
from cnnps.api.prediction import predict_folder


def _predict(capture: Path, tmp: Path, **kw) -> tuple[dict, float, Path]:
    out = tmp / f"out-{len(list(tmp.iterdir()))}"
    with Stopwatch() as sw:
        # saturated observations kept, as published methods score DiLiGenT (and as v2 was measured)
        result = predict_folder(capture, out, progress=False, saturated="keep", **kw)
    return result, sw.seconds, out


def _metric(result: dict) -> dict:
    return {"mean_deg": result.get("mean_deg"), "median_deg": result.get("median_deg")}


def _ball_subsets(args, tmp: Path) -> dict:
    """BALL from each of the image lists benchmarks/image_lists/ballPNG-<n>.txt."""
    from benchmarks.subsets import drop_for, list_path, read_list

    ball = args.shared / "data" / "diligent" / "ballPNG"
    out = {}
    if not ball.is_dir():
        return out
    for n in args.subsets:
        names = read_list(list_path(ball.name, n))
        drop = drop_for(ball, names)
        rows = {"images": names}
        r, t, _ = _predict(ball, tmp, method="lambertian", drop=drop)
        rows["lambertian"] = {**_metric(r), "seconds": round(t, 2)}
        for k in (1, 10):  # the network alone, then with the Lambertian fill (what `cnnps predict` does below 50)
            for key, fill in ((f"cnn_k{k}_fp32", "off"), (f"cnn_k{k}_fp32_fill", "on")):
                r, t, _ = _predict(ball, tmp, method="cnn", model=args.model, rotations=k, drop=drop, sparse_fill=fill)
                rows[key] = {**_metric(r), "seconds": round(t, 2)}
        print(f"BALL {n} images: LS {rows['lambertian']['mean_deg']:.2f}, CNN K=1 {rows['cnn_k1_fp32']['mean_deg']:.2f} "
              f"(fill {rows['cnn_k1_fp32_fill']['mean_deg']:.2f}), K=10 {rows['cnn_k10_fp32']['mean_deg']:.2f} "
              f"(fill {rows['cnn_k10_fp32_fill']['mean_deg']:.2f})", flush=True)
        out[str(n)] = rows
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--pixels", type=int, default=45000)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    ap.add_argument("--picture", type=Path, default=ROOT / "docs" / "images" / "fossil_normals.png")
    ap.add_argument("--subsets", type=int, nargs="*", default=[], help="BALL image counts to measure (lists in benchmarks/image_lists/)")
    ap.add_argument("--only-subsets", action="store_true", help="measure only --subsets; merge into --out")
    ap.add_argument("--no-speed", action="store_true", help="accuracy only: no bf16 runs, no 45,000-pixel timing")
    args = ap.parse_args()
    if args.only_subsets:
        result = previous_results(args.out)
        with tempfile.TemporaryDirectory() as tmp_name:
            result["ball_subsets"] = {"load_average_before": list(os.getloadavg()),
                                      **_ball_subsets(args, Path(tmp_name))}
        write_result(args.out, __spec__.name, args, result)
        print(json.dumps(result["ball_subsets"], indent=2))
        return

    result: dict = {"model": str(args.model or "shipped"), "load_average_before": list(os.getloadavg())}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        ball = args.shared / "data" / "diligent" / "ballPNG"
        if ball.is_dir():
            rows = {}
            r, t, _ = _predict(ball, tmp, method="lambertian")
            rows["lambertian"] = {**_metric(r), "seconds": round(t, 2)}
            for precision in ("fp32",) if args.no_speed else ("fp32", "bf16"):
                for k in (1, 10):
                    r, t, _ = _predict(ball, tmp, method="cnn", model=args.model, rotations=k, precision=precision)
                    rows[f"cnn_k{k}_{precision}"] = {**_metric(r), "seconds": round(t, 2)}
                    print(f"BALL cnn K={k} {precision}: {rows[f'cnn_k{k}_{precision}']}", flush=True)
            if not args.no_speed:
                rows["bf16_minus_fp32_k10_deg"] = rows["cnn_k10_bf16"]["mean_deg"] - rows["cnn_k10_fp32"]["mean_deg"]
                rows["bf16_minus_fp32_k1_deg"] = rows["cnn_k1_bf16"]["mean_deg"] - rows["cnn_k1_fp32"]["mean_deg"]
            result["ball"] = rows
        if args.subsets:
            result["ball_subsets"] = _ball_subsets(args, tmp)
        fossil = args.shared / "data" / "captures" / "fossil"
        if fossil.is_dir():
            r, t, out = _predict(fossil, tmp, method="cnn", model=args.model, rotations=1)
            args.picture.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out / "normal.png", args.picture)
            result["fossil"] = {"rotations": 1, "pixels": r.get("pixels"), "seconds": round(t, 2), "picture": str(args.picture.relative_to(ROOT))}

        if args.no_speed:
            args.pixels = 0
    if args.pixels:
        # a 45,000-pixel object: speed only (synthetic Lambertian pixels, 96 lights)
        import torch  # noqa: F401

        from benchmarks.predict.inference_speed import _scene
        from cnnps.models.checkpoint import load_checkpoint
        from cnnps.models.inference import predict_normals
        from cnnps.models.shipped import shipped_model_path

        net, _, _ = load_checkpoint(args.model or shipped_model_path(), "cpu")
        I, L = _scene(args.pixels)
        speed = {}
        for precision in ("fp32", "bf16"):
            for k in (1, 10):
                with Stopwatch() as sw:
                    predict_normals(net, I, L, rotations=k, device="cpu", precision=precision, progress=False)
                speed[f"k{k}_{precision}_s"] = round(sw.seconds, 2)
                print(f"{args.pixels} px K={k} {precision}: {speed[f'k{k}_{precision}_s']} s", flush=True)
        result["object_45k"] = {"pixels": args.pixels, "lights": 96, **speed}
    result["load_average_after"] = list(os.getloadavg())
    write_result(args.out, __spec__.name, args, result)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
