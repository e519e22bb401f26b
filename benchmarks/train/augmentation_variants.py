"""Model v3: which capture augmentations pay. One start, one data set, one change at a time.

    .venv/bin/python -m benchmarks.train.augmentation_variants VARIANT [VARIANT ...] [--steps 1000] [--lr 1e-4]
        [--out benchmarks/results/train/augmentation_variants.json]

Needs the renders and shards of the v2 training data first:

    for s in meshes materials render extract; do cnnps run-stage $s --preset cpu-train; done

Every variant starts from the shipped v2 weights and re-extracts the same 186 renders
(``data/cpu-train/render``) with the preset's extract parameters plus its own overrides
(into ``data/v3var/<name>/extract``), then trains ``--steps`` steps at a constant ``--lr``
(batch 128, seed 0) with the train stage: the method of the v2 variant table
(benchmarks/train/data_variants.py), started from v2 instead of v1. ``base`` changes nothing:
the control for what more steps alone give. Each is scored on

* the validation maps of the v2 data (``data/cpu-train/extract``, split ``val``: 6 held-out
  scenes x 3 categories, 79,050 maps, ambient augmentation only), each map alone (K = 1);
* DiLiGenT BALL, 96 images, K = 1 and K = 10 (mean, median, rim and inner);
* BALL from 20, 10 and 6 of its images (benchmarks/image_lists/, the seeded rule of
  tools/image_subsets.py): K = 1, and K = 10 at 10 images.

Two variants need new renders (``narrow``, ``env-0.5``: see ``RENDER_VARIANTS``); they are
made in ``data/v3src/<name>`` from the v2 meshes and materials, then extracted like the rest.
The eval stage's synthetic test set is run for the final candidates only (its cost).
Results are merged into ``--out`` per variant.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import shutil
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    ROOT,
    Stopwatch,
    previous_results,
    result_path,
    write_result,
)

DATA = ROOT / "data" / "cpu-train"
OUT_ROOT = ROOT / "data" / "v3var"
# extract overrides on top of cnnps/presets/cpu-train.yaml's extract section (ambient 0.05)
VARIANTS: dict[str, dict] = {
    "base": {},
    "sparse-0.3": {"sparse_fraction": 0.3},
    "noise-0.02": {"noise_max": 0.02},
    "direction-1.5": {"direction_error_deg": 1.5},
    "intensity-0.03": {"intensity_error": 0.03},
    "saturation-0.05": {"saturated_fraction_max": 0.05},
    "quantize-8-16": {"quantize_bits": (8, 16)},
    "black-0.02": {"black_level_max": 0.02},
    "all": {"sparse_fraction": 0.3, "noise_max": 0.02, "direction_error_deg": 1.5, "intensity_error": 0.03,
            "saturated_fraction_max": 0.05, "quantize_bits": (8, 16), "black_level_max": 0.02},
}
# variants that need new renders (deliverable 3): built in data/v3src/<name> from the v2 meshes
# and materials (symlinked), then extracted like the others with the preset's extract section.
#   narrow:  the v2 renders plus one narrow-lobe scene per mesh view (materials category
#            ``narrow``: roughness 0.02-0.15, specular 0.5-2, metallic 0), 62 new renders;
#   env-0.5: the v2 renders with a dim white environment light U(0, 0.05) in half the
#            scenes (render.env_fraction 0.5); the other half keep their key, so only the
#            lit half is rendered again.
RENDER_VARIANTS: dict[str, dict] = {
    "narrow": {"materials": {"categories": ("narrow",)}},
    "env-0.5": {"render": {"env_fraction": 0.5, "env_max": 0.05}},
}
SUBSETS = {20: (1,), 10: (1, 10), 6: (1,)}
SRC_ROOT = ROOT / "data" / "v3src"


def _stage_params(stage: str, **overrides):
    from cnnps.pipeline import config as cfg

    conf = cfg.load_config(cfg.preset_path("cpu-train"))
    return dataclasses.replace(cfg.build_params(conf, stage, check_files=False), **overrides)


def _link(target: Path, link: Path) -> None:
    if not link.exists():
        link.symlink_to(target.resolve(), target_is_directory=True)


def render_source(name: str) -> Path:
    """The data folder whose ``render/`` a render variant extracts from (renders what is missing)."""
    from cnnps.stages import materials, render

    spec = RENDER_VARIANTS[name]
    src = SRC_ROOT / name
    src.mkdir(parents=True, exist_ok=True)
    _link(DATA / "meshes", src / "meshes")
    if "materials" in spec:  # new scenes only, rendered here, then shown next to the v2 renders
        materials.run(_stage_params("materials", **spec["materials"]), src)
        render.run(_stage_params("render"), src)
        both = SRC_ROOT / f"{name}-all"
        (both / "render").mkdir(parents=True, exist_ok=True)
        for root in (DATA / "render", src / "render"):
            for scene in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
                _link(scene, both / "render" / scene.name)
        return both
    _link(DATA / "materials", src / "materials")
    if not (src / "render").exists():  # start from a copy: the scenes without the option keep their key
        shutil.copytree(DATA / "render", src / "render")
    render.run(_stage_params("render", **spec["render"]), src)
    return src


def preset_extract_params():
    from cnnps.pipeline import config as cfg

    conf = cfg.load_config(cfg.preset_path("cpu-train"))
    return cfg.build_params(conf, "extract", check_files=False)


def validation_maps() -> tuple[np.ndarray, np.ndarray]:
    from cnnps.io.shards import ShardStream, load_manifest, manifest_files

    d = DATA / "extract"
    man = load_manifest(d)
    stream = ShardStream(manifest_files(d, man, "val"), int(man["w"]), batch_size=8192, seed=0, buffer_rows=8192,
                         shuffle=False, drop_last=False)
    ms, ns = zip(*stream.iter_epoch(0))
    return np.concatenate(ms), np.concatenate(ns)


def _stats(e: np.ndarray) -> dict:
    return {"mean_deg": round(float(e.mean()), 3), "median_deg": round(float(np.median(e)), 3)}


def score(model_path: Path, val: tuple[np.ndarray, np.ndarray], shared: Path) -> dict:
    from benchmarks.subsets import drop_for, list_path, read_list
    from cnnps.io.capture import load_capture
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor, predict_normals
    from cnnps.ps.metrics import angular_error_deg

    net, _, meta = load_checkpoint(model_path, "cpu")
    out: dict = {"val": {"maps": len(val[0]), **_stats(angular_error_deg(MapPredictor(net, device="cpu")(val[0]), val[1]))}}
    ball = shared / "data" / "diligent" / "ballPNG"
    if not ball.is_dir():
        return out
    runs = [(96, None, (1, 10))] + [(n, drop_for(ball, read_list(list_path(ball.name, n))), ks) for n, ks in SUBSETS.items()]
    for n, drop, ks in runs:
        cap = load_capture(ball, drop=drop)
        I, gt = cap.pixel_intensities(), cap.normal_gt[cap.mask]
        tilt = np.degrees(np.arccos(np.clip(gt[:, 2], -1, 1)))
        for k in ks:
            with Stopwatch() as sw:
                e = angular_error_deg(predict_normals(net, I, cap.lights, rotations=k, device="cpu", progress=False,
                                                      sparse_fill="off"), gt)  # the network alone
            out[f"ball{n}_k{k}"] = {**_stats(e), "rim_mean_deg": round(float(e[tilt > 70].mean()), 3),
                                   "inner_mean_deg": round(float(e[tilt <= 70].mean()), 3),
                                   "seconds": round(sw.seconds, 1)}
            print(f"  BALL {n} images K={k}: {out[f'ball{n}_k{k}']}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    names = ["shipped", *VARIANTS, *RENDER_VARIANTS]
    ap.add_argument("variants", nargs="*", help=f"any of: {', '.join(names)}")
    ap.add_argument("--score", nargs=2, action="append", default=[], metavar=("NAME", "CHECKPOINT"),
                    help="also score a trained checkpoint (e.g. v3 data/cpu-train-v3/train/model.pt) under NAME")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()
    unknown = [v for v in args.variants if v not in names]
    if unknown or not (args.variants or args.score):
        ap.error(f"choose variants from {', '.join(names)} and/or --score NAME CHECKPOINT (unknown: {unknown})")

    from cnnps.models.shipped import shipped_model_path
    from cnnps.stages import extract, train

    results = {"variants": {}, **previous_results(args.out)}  # each run adds or replaces its variants
    results["method"] = (f"from the shipped v2 weights, {args.steps} steps x 128 at lr {args.lr} on the v2 renders "
                         "re-extracted with each variant's overrides; scored as the module docstring says")
    val = validation_maps()
    base = preset_extract_params()
    init = shipped_model_path()
    for name, checkpoint in args.score:
        row = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
               "load_average_before": [round(x, 2) for x in os.getloadavg()], "checkpoint": checkpoint}
        print(name, flush=True)
        row.update(score(Path(checkpoint), val, args.shared))
        results["variants"][name] = row
        write_result(args.out, __spec__.name, args, results)
    for name in args.variants:
        row: dict = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                     "load_average_before": [round(x, 2) for x in os.getloadavg()]}
        model = init
        if name != "shipped":
            overrides, source = VARIANTS.get(name, {}), DATA
            if name in RENDER_VARIANTS:
                with Stopwatch() as sw:
                    source = render_source(name)
                row["render_overrides"] = RENDER_VARIANTS[name]
                row["render_seconds"] = round(sw.seconds, 1)
            row["extract_overrides"] = {k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()}
            shards = OUT_ROOT / name / "extract"
            with Stopwatch() as sw:
                extract.run(dataclasses.replace(base, **overrides, output=str(shards)), source)
            man = json.loads((shards / "manifest.json").read_text())
            row["data"] = {"train_rows": man["train_rows"], "extract_seconds": round(sw.seconds, 1)}
            params = train.Params(max_steps=args.steps, epochs=1000, optimiser={"lr": args.lr},
                                  data={"batch_size": 128, "shards": str(shards)}, val_every=0, val_max_rows=4096,
                                  checkpoint_every=250, init=str(init), progress=False)
            with Stopwatch() as sw:
                m = train.run(params, OUT_ROOT / name)
            row["train"] = {"steps": m["steps"], "lr": args.lr, "seconds": round(sw.seconds, 1),
                            "samples_per_s": m["samples_per_s"]}
            model = OUT_ROOT / name / "train" / "model.pt"
        print(name, flush=True)
        row.update(score(model, val, args.shared))
        results["variants"][name] = row
        write_result(args.out, __spec__.name, args, results)
        print(name, json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
