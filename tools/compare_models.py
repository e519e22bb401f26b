"""v2, v3, v3.1 and v3.1 with the Lambertian fill (cnnps.ps.sparse_fill), side by side: the README's model table, from measured results only.

    .venv/bin/python tools/compare_models.py --eval v2=data/eval-v2/eval/metrics.json \
        --eval v3=data/cpu-train-v3-polish/eval/metrics.json --eval v3.1=data/eval-v3.1/eval/metrics.json \
        --eval v3.1+fill=data/eval-v3.1-fill/eval/metrics.json \
        [--out benchmarks/results/v2_v3.json]

Reads ``benchmarks/results/variants_v3.json`` (the validation maps and BALL with rim
errors: rows ``shipped`` = v2, ``v3`` and ``v3.1``), ``benchmarks/results/model_v2.json`` /
``model_v3.json`` / ``model.json`` (v3.1; BALL at 96, 20, 10, 6 images against least squares on the same images,
written by ``python -m benchmarks.predict.model_accuracy``) and the eval stage's ``metrics.json`` of each
model (the synthetic test set, per light count; non-convex = every test shape but the sphere).
A results file is read in either layout: the benchmarks' schema (its ``results``) or the
earlier one. Prints Markdown rows and writes the numbers to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from cnnps.infra.atomic import write_text

REPO = Path(__file__).resolve().parents[1]


def measured(path: str | Path) -> dict:
    """A results file's numbers: its ``results`` in the benchmarks' schema, else the file."""
    data = json.loads(Path(path).read_text())
    return data["results"] if isinstance(data, dict) and {"benchmark", "results"} <= data.keys() else data


def eval_summary(metrics: dict) -> dict:
    """Per light count: mean error of each method over the non-convex and over all captures."""
    out: dict = {}
    for name, cap in metrics.get("captures", {}).items():
        n = str(cap.get("n_images"))
        groups = ["all"] + ([] if name.startswith("sphere") else ["nonconvex"])
        for g in groups:
            for m, s in cap.get("methods", {}).items():
                out.setdefault(n, {}).setdefault(g, {}).setdefault(m, []).append(s["mean_deg"])
    return {n: {g: {m: round(float(np.mean(v)), 3) for m, v in ms.items()} for g, ms in gs.items()}
            for n, gs in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--eval", action="append", default=[], metavar="NAME=METRICS_JSON")
    ap.add_argument("--variants", type=Path, default=REPO / "benchmarks" / "results" / "variants_v3.json")
    ap.add_argument("--ball", action="append", default=[], metavar="NAME=MODEL_JSON",
                    help="model_accuracy results per model (default v2=model_v2.json, v3=model.json)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "v2_v3.json")
    args = ap.parse_args()
    res = REPO / "benchmarks" / "results"
    balls = dict(a.split("=", 1) for a in args.ball) or {"v2": str(res / "model_v2.json"), "v3": str(res / "model_v3.json"),
                                                         "v3.1": str(res / "model.json"),
                                                         "v3.1+fill": str(res / "model.json")}
    evals = dict(a.split("=", 1) for a in args.eval)
    variants = measured(args.variants)["variants"]
    table: dict = {"models": {}}
    models = (("v2", variants.get("shipped")), ("v3", variants.get("v3")), ("v3.1", variants.get("v3.1")),
              ("v3.1+fill", variants.get("v3.1")))  # the same weights, with the Lambertian fill below 50 images
    for name, row in models:
        fill = name.endswith("+fill")
        entry: dict = {"val_mean_deg": row["val"]["mean_deg"] if row else None}
        if row:
            entry["ball96_k10_rim_deg"] = row["ball96_k10"]["rim_mean_deg"]
        m = measured(balls[name]) if Path(balls.get(name, "")).is_file() else {}
        ball = m.get("ball", {})
        entry["ball96"] = {k: ball[k]["mean_deg"] for k in ("lambertian", "cnn_k1_fp32", "cnn_k10_fp32") if k in ball}
        for n, r in m.get("ball_subsets", {}).items():
            if isinstance(r, dict) and "lambertian" in r:
                entry[f"ball{n}"] = {k: r[k + ("_fill" if fill and k != "lambertian" else "")]["mean_deg"]
                                     for k in ("lambertian", "cnn_k1_fp32", "cnn_k10_fp32")
                                     if k + ("_fill" if fill and k != "lambertian" else "") in r}
        if name in evals:
            entry["eval"] = eval_summary(json.loads(Path(evals[name]).read_text()))
        if m.get("fossil"):
            entry["fossil_picture"] = m["fossil"].get("picture")
        table["models"][name] = entry
    write_text(args.out, json.dumps(table, indent=2) + "\n")

    names = list(table["models"])
    cols = [table["models"][n] for n in names]

    def cell(e, key, meth):
        x = e.get(key, {}).get(meth)
        return "–" if x is None else f"{x:.2f}°"

    print("| measure | " + " | ".join(names) + " | least squares |\n|" + " --- |" * (len(names) + 2))
    for key, label in (("ball96", "BALL, 96 images"), ("ball20", "BALL, 20 images"), ("ball10", "BALL, 10 images"),
                       ("ball6", "BALL, 6 images")):
        for meth, k in (("cnn_k1_fp32", "K=1"), ("cnn_k10_fp32", "K=10")):
            print(f"| {label}, {k} | " + " | ".join(cell(c, key, meth) for c in cols) + f" | {cell(cols[0], key, 'lambertian')} |")
    print("| BALL 96, K=10, rim (tilt > 70°) | " + " | ".join(f"{c.get('ball96_k10_rim_deg')}°" for c in cols) + " | |")
    print("| validation maps (v2's 79,050, K=1) | " + " | ".join(f"{c['val_mean_deg']}°" for c in cols) + " | |")
    last = cols[-1].get("eval", {})
    for n in sorted(last, key=int):
        for g in ("nonconvex", "all"):
            ls = last[n].get(g, {}).get("lambertian")
            for meth in ("cnn_k1", "cnn_k10"):
                parts = []
                for c in cols:
                    x = c.get("eval", {}).get(n, {}).get(g, {}).get(meth)
                    parts.append("–" if x is None else f"{x:.2f}°" + (f" ({x / ls:.2f}× LS)" if ls else ""))
                print(f"| eval stage, {n} lights, {g}, {meth.replace('cnn_k', 'K=')} | " + " | ".join(parts) + f" | {ls:.2f}° |")

if __name__ == "__main__":
    main()
