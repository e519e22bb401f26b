"""Which training data pays: fine-tune one model on data variants, score each the same way.

    .venv/bin/python -m benchmarks.train.data_variants VARIANT [VARIANT ...] [--steps 1000] [--lr 1e-4]
        [--init PATH] [--out benchmarks/results/train/data_variants.json]

Every variant starts from the same weights (``--init``, default ``data/variants/init.pt``:
the stage-1 model as shipped at commit 886219e, float16 weights), trains ``--steps`` steps at a constant ``--lr`` on its
own shards with the train stage (batch 128, seed 0), and is then scored on

* the *common* validation set: every map of the held-out view-0 scenes of the first
  cpu-train data (cat_low_resolution, nefertiti_lowres, rocker_arm; 3 categories each),
  each map on its own (K = 1), as the train stage validates;
* DiLiGenT BALL (``../shared/data/diligent/ballPNG``, 96 lights) at K = 1 and K = 10;
* BALL with the observation maps rounded to float16 (how the shards store them), to see
  whether the storage precision matters at all.

Variants (the data each is trained on; ``python -m cnnps run-stage ... --params FILE``
makes them):

* ``init``: no training; the starting model itself.
* ``shipped``: no training; the model now in ``cnnps/models/weights/`` (scored the same way).
* ``same-data``: the first model's data again (cnnps/presets/cpu-train.yaml with
  views_per_mesh 1: 93 scenes, 200 lights, 8 spp), kept as ``data/var-views1/extract``.
  The control: what more steps at a lower rate give without new data.
* ``more-views``: cnnps/presets/cpu-train.yaml (views_per_mesh 2: 186 scenes, 200 lights,
  8 spp): twice the scenes, twice the render time.
* ``ambient-0.10``, ``ambient-0.05``: the more-views renders extracted with
  ``ambient_max`` 0.1 or 0.05 (every light of a pixel gets an offset of U(0, ambient_max)
  x its brightest light: real shadows are not black, see cnnps/stages/extract.py); no new
  renders. cnnps/presets/cpu-train.yaml holds the value the shipped model was trained with.
* ``l400-s4``: benchmarks/variants/l400-s4.yaml (93 scenes, 400 lights, 4 spp, per-pixel
  subsets up to 400 lights): the same scenes with twice the lights at half the samples
  per pixel, about the same render time as the first data.

Results are merged into ``--out`` per variant (each run adds or replaces its variants).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
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

VARIANTS = {
    "init": None,
    "shipped": None,
    "same-data": "data/var-views1/extract",
    "more-views": "data/var-views2/extract",
    "l400-s4": "data/var-l400-s4/extract",
    "ambient-0.10": "data/var-amb10/extract",
    "ambient-0.05": "data/cpu-train/extract",
}
COMMON_VAL = "data/var-views1/extract"  # its val split: the view-0 validation scenes


def common_val(max_rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    from cnnps.io.shards import ShardStream, load_manifest, manifest_files

    d = ROOT / COMMON_VAL
    man = load_manifest(d)
    files = manifest_files(d, man, "val")
    stream = ShardStream(files, int(man["w"]), batch_size=8192, seed=0, buffer_rows=8192, shuffle=False,
                         drop_last=False)
    ms, ns = [], []
    for m, n in stream.iter_epoch(0):
        ms.append(m)
        ns.append(n)
    maps, normals = np.concatenate(ms), np.concatenate(ns)
    return (maps[:max_rows], normals[:max_rows]) if max_rows else (maps, normals)


def score(model_path: Path, val: tuple[np.ndarray, np.ndarray], shared: Path) -> dict:
    from cnnps.io.capture import load_capture
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor, predict_normals
    from cnnps.ps.metrics import angular_error_deg
    from cnnps.ps.obsmap import observation_maps

    net, _, _ = load_checkpoint(model_path, "cpu")
    out: dict = {}
    pred = MapPredictor(net, device="cpu")
    err = angular_error_deg(pred(val[0].astype(np.float32)), val[1])
    out["val"] = {"maps": int(len(err)), "mean_deg": round(float(err.mean()), 3),
                  "median_deg": round(float(np.median(err)), 3)}
    ball = shared / "data" / "diligent" / "ballPNG"
    if ball.is_dir():
        cap = load_capture(ball)
        I = cap.pixel_intensities()  # (P, m)
        gt = cap.normal_gt[cap.mask]
        tilt = np.degrees(np.arccos(np.clip(gt[:, 2], -1, 1)))
        for k in (1, 10):
            with Stopwatch() as sw:
                n = predict_normals(net, I, cap.lights, rotations=k, device="cpu", progress=False)
            e = angular_error_deg(n, gt)
            out[f"ball_k{k}"] = {"mean_deg": round(float(e.mean()), 3), "median_deg": round(float(np.median(e)), 3),
                                 # the rim: normals tilted > 70 deg from the view axis (12 % of BALL's pixels)
                                 "rim_mean_deg": round(float(e[tilt > 70].mean()), 3),
                                 "inner_mean_deg": round(float(e[tilt <= 70].mean()), 3),
                                 "seconds": round(sw.seconds, 1)}
        maps32 = observation_maps(I, cap.lights, w=net.w)
        maps16 = maps32.astype(np.float16).astype(np.float32)
        e32 = angular_error_deg(pred(maps32), gt)
        e16 = angular_error_deg(pred(maps16), gt)
        out["ball_k1_float16_maps_minus_float32_deg"] = round(float(e16.mean() - e32.mean()), 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("variants", nargs="+", choices=sorted(VARIANTS))
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--score-only", action="store_true", help="re-score the variants' existing models")
    ap.add_argument("--init", type=Path, default=ROOT / "data" / "variants" / "init.pt")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()

    from cnnps.stages import train

    if not args.init.is_file() and any(VARIANTS[n] is not None or n == "init" for n in args.variants if n != "shipped"):
        sys.exit(f"{args.init}: not found. The results in benchmarks/results/variants.json started from the "
                 f"stage-1 model shipped at commit 886219e: git show 886219e:models/weights/cnnps_default.pt > {args.init}")
    results = {"variants": {}, **previous_results(args.out)}  # each run adds or replaces its variants
    val = common_val()
    for name in args.variants:
        row: dict = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                     "load_average_before": [round(x, 2) for x in os.getloadavg()]}
        model = args.init
        if name == "shipped":
            from cnnps.models.shipped import shipped_model_path

            model = shipped_model_path()
        elif VARIANTS[name] is not None and args.score_only:
            row = {**results["variants"].get(name, {}), **row}
            model = ROOT / "data" / "variants" / name / "train" / "model.pt"
        elif VARIANTS[name] is not None:
            shards = ROOT / VARIANTS[name]
            man = json.loads((shards / "manifest.json").read_text())
            row["data"] = {"shards": VARIANTS[name], "train_scenes": len(man["train_scenes"]),
                           "train_rows": man["train_rows"], "params": man["params"]}
            params = train.Params(max_steps=args.steps, epochs=1000, optimiser={"lr": args.lr},
                                  data={"batch_size": 128, "shards": str(shards)}, val_every=0, val_max_rows=4096,
                                  checkpoint_every=250, init=str(args.init))
            with Stopwatch() as sw:
                m = train.run(params, ROOT / "data" / "variants" / name)
            row["train"] = {"steps": m["steps"], "lr": args.lr, "seconds": round(sw.seconds, 1),
                            "samples_per_s": m["samples_per_s"]}
            model = ROOT / "data" / "variants" / name / "train" / "model.pt"
        row.update(score(model, val, args.shared))
        print(name, json.dumps(row), flush=True)
        results["variants"][name] = row
        write_result(args.out, __spec__.name, args, results)


if __name__ == "__main__":
    main()
