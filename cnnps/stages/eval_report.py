"""The evaluation report: a plain-text table, pictures, ``metrics.json`` and ``report.md``.

Methods are named ``cnn_k<K>`` (CNN-PS with K test-time rotations) and ``lambertian``
(least squares); every method of a capture is scored on the same pixels. Written by the
eval stage (:mod:`cnnps.stages.evaluate`); ``cnnps run-stage eval`` prints the table.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

LAMBERTIAN = "lambertian"
PICTURE_MIN_SIZE = 192  # report pictures of smaller captures are enlarged (nearest neighbour)


def method_name(k: int) -> str:
    return f"cnn_k{k}"


def input_picture(cap) -> np.ndarray:
    """The image lit most frontally, exposed to its 99th percentile, sRGB-ish gamma, uint8
    (read from its file when ``cap`` was scanned, not loaded)."""
    j = int(np.argmax(cap.lights[:, 2]))
    img = cap.read_grey(j)
    vals = img[cap.mask]
    scale = float(np.percentile(vals, 99)) if vals.size else 1.0
    scale = scale if scale > 0 else 1.0
    g = np.clip(img / scale, 0.0, 1.0) ** (1 / 2.2)
    return np.round(g * 255).astype(np.uint8)


def summarize(results: dict[str, dict]) -> dict:
    """Mean of per-capture mean / median errors per method (captures with ground truth)."""
    per_method: dict[str, list[dict]] = {}
    for r in results.values():
        for m, s in r["methods"].items():
            per_method.setdefault(m, []).append(s)
    return {
        m: {
            "mean_deg": float(np.mean([s["mean_deg"] for s in stats])),
            "median_deg": float(np.mean([s["median_deg"] for s in stats])),
            "captures": len(stats),
        }
        for m, stats in per_method.items()
    }


def summarize_by_lights(results: dict[str, dict]) -> dict:
    """Per image count (as a string key): :func:`summarize` of the captures with that many
    images, plus ``<method>_vs_least_squares``, each CNN's mean error over least squares'
    (the ratio the light-count targets are written in)."""
    groups: dict[int, dict[str, dict]] = {}
    for n, r in results.items():
        if r.get("methods"):
            groups.setdefault(int(r["n_images"]), {})[n] = r
    out = {}
    for m in sorted(groups):
        s = summarize(groups[m])
        base = s.get(LAMBERTIAN, {}).get("mean_deg")
        ratios = {f"{k}_vs_least_squares": v["mean_deg"] / base for k, v in s.items() if k != LAMBERTIAN and base}
        out[str(m)] = {**s, **ratios}
    return out


def rig_minus_ortho(results: dict[str, dict]) -> dict:
    """Per method: the mean over rig twins (kind ``rig``, named ``<capture>-<rig>``) of the
    twin's mean error minus its orthographic, distant-light capture's (what the rig costs,
    in degrees); ``captures`` counts the pairs. Empty without twins."""
    pairs = [(r, results[n.rsplit("-fov", 1)[0]]) for n, r in results.items()
             if r.get("kind") == "rig" and r.get("methods") and n.rsplit("-fov", 1)[0] in results]
    out: dict[str, dict] = {}
    for rig, ortho in pairs:
        for m, stats in rig["methods"].items():
            if m in ortho.get("methods", {}):
                out.setdefault(m, []).append(stats["mean_deg"] - ortho["methods"][m]["mean_deg"])
    return {m: {"mean_deg": float(np.mean(d)), "captures": len(d)} for m, d in out.items()}


SHIPPED = "shipped_k10"  # the shipped model with K=10, scored beside the trained one (cnnps demo)


def format_table(metrics: dict, shipped: dict | None = None) -> str:
    """The evaluation table (plain text): mean / median angular error in degrees.

    ``shipped``: ``{"captures": {name: stats}, "summary": stats}`` of another model on the
    same captures (:func:`cnnps.stages.evaluate.score_shipped`), shown as one more column
    before least squares, with a legend saying what each column is.
    """
    captures = metrics.get("captures", {})
    methods = list(metrics.get("methods") or sorted({m for c in captures.values() for m in c.get("methods", {})}))
    if not captures:
        return "(no captures evaluated)"
    if shipped is not None:
        at = methods.index(LAMBERTIAN) if LAMBERTIAN in methods else len(methods)
        methods.insert(at, SHIPPED)
        captures = {n: {**c, "methods": {**c.get("methods", {}),
                                         **({SHIPPED: shipped["captures"][n]} if n in shipped["captures"] else {})}}
                    for n, c in captures.items()}
        metrics = {**metrics, "summary": {**metrics.get("summary", {}), SHIPPED: shipped["summary"]}}
    head = ["capture", "lights"] + [_label(m) for m in methods]
    rows = []
    for name, c in captures.items():
        row = [name, str(c.get("n_images", ""))]
        for m in methods:
            s = c.get("methods", {}).get(m)
            row.append(f"{s['mean_deg']:6.2f} / {s['median_deg']:6.2f}" if s else "no GT")
        rows.append(row)
    means = [("mean over captures", "", metrics.get("summary", {}))]
    if metrics.get("summary_real") or metrics.get("summary_real_subsets"):  # real captures: their own means
        left_out = ", ".join(metrics.get("real_exclude_from_mean") or [])
        label = "mean over real" + (f" (not {left_out})" if left_out else "")
        means = [m for m in means if m[2]] + [(label, "", metrics.get("summary_real", {}))]
        means += [(label, n, s) for n, s in (metrics.get("summary_real_subsets") or {}).items()]
    for label, lights, summary in means:
        if not summary:
            continue
        row = [label, str(lights)]
        for m in methods:
            s = summary.get(m)
            row.append(f"{s['mean_deg']:6.2f} / {s['median_deg']:6.2f}" if s else "")
        rows.append(row)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    fmt = lambda r: "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
    lines = ["angular error in degrees: mean / median", fmt(head), "  ".join("-" * w for w in widths)]
    lines += [fmt(r) for r in rows]
    if shipped is not None:
        ks = ", ".join(_label(m) for m in methods if m.startswith("cnn_k"))
        lines += ["", f"{ks}: the model this run trained, K test-time rotations averaged;",
                  f"shipped K=10: the model cnnps ships ({shipped.get('label', 'cnnps/models/weights')});",
                  "Lambertian LS: least squares. Every column on the same captures and pixels."]
    return "\n".join(lines)


def _label(method: str) -> str:
    if method.startswith("cnn_k"):
        return f"CNN-PS K={method[5:]}"
    if method == LAMBERTIAN:
        return "Lambertian LS"
    if method == SHIPPED:
        return "shipped K=10"
    return method


def write_report(out_dir: Path, results: dict[str, dict], metrics: dict) -> Path:
    """Pictures (``pictures/``), ``metrics.json`` and ``report.md`` under ``out_dir``."""
    from cnnps.infra.atomic import atomic_dir, write_text
    from cnnps.io.images import write_png
    from cnnps.io.visualize import _nice_ceiling, normal_to_rgb, score_picture

    out_dir = Path(out_dir)
    methods = metrics["methods"]
    best_cnn = method_name(max(int(m[5:]) for m in methods if m.startswith("cnn_k")))
    lines = [
        "# CNN-PS evaluation",
        "",
        f"Model: `{metrics['model']}`. Angular error in degrees (mean / median) on mask pixels "
        "with ground truth; every method is scored on the same pixels.",
        "",
        "```",
        format_table(metrics),
        "```",
        "",
    ]
    with atomic_dir(out_dir / "pictures") as tmp:
        for name, r in results.items():
            f = max(1, PICTURE_MIN_SIZE // max(r["mask"].shape))  # small renders: enlarge (nearest)
            up = (lambda a: a) if f == 1 else (lambda a: np.repeat(np.repeat(a, f, axis=0), f, axis=1))
            mask = up(r["mask"])
            files = {"input": f"{name}_input.png"}
            write_png(tmp / files["input"], up(r["input"]))
            for m in (best_cnn, LAMBERTIAN):
                files[f"normal_{m}"] = f"{name}_normal_{m}.png"
                write_png(tmp / files[f"normal_{m}"], normal_to_rgb(up(r["normals"][m]), mask))
            if r["gt"] is not None:
                files["gt"] = f"{name}_normal_gt.png"
                write_png(tmp / files["gt"], normal_to_rgb(up(r["gt"]), mask))
                # one scale for both error pictures of a capture
                shown = [r["scores"][m] for m in (best_cnn, LAMBERTIAN)]
                vmax_src = np.concatenate([sc.errors[sc.scored] for sc in shown])
                vmax = _nice_ceiling(float(np.percentile(vmax_src, 99))) if vmax_src.size else None
                for m, sc in zip((best_cnn, LAMBERTIAN), shown):
                    files[f"error_{m}"] = f"{name}_error_{m}.png"
                    write_png(tmp / files[f"error_{m}"], score_picture(sc, vmax=vmax, enlarge=f))
            c = metrics["captures"][name]
            lines += [f"## {name}", "", f"`{c['capture']}`: {c['n_images']} images, {c['pixels']} mask pixels.", ""]
            if r["gt"] is not None:
                lines += ["| method | mean | median | < 10° |", "| --- | ---: | ---: | ---: |"]
                for m in methods:
                    s = c["methods"][m]
                    lines.append(f"| {_label(m)} | {s['mean_deg']:.2f}° | {s['median_deg']:.2f}° | {100 * s['under_10_deg']:.0f} % |")
                lines.append("")
            cols = [("input", "input"), (f"normal_{best_cnn}", f"{_label(best_cnn)}"), (f"normal_{LAMBERTIAN}", "Lambertian LS")]
            if r["gt"] is not None:
                cols += [("gt", "ground truth"), (f"error_{best_cnn}", f"error {_label(best_cnn)}"), (f"error_{LAMBERTIAN}", "error Lambertian")]
            lines.append("| " + " | ".join(t for _, t in cols) + " |")
            lines.append("|" + " --- |" * len(cols))
            lines.append("| " + " | ".join(f"![{t}](pictures/{files[k]})" for k, t in cols) + " |")
            lines.append("")
    write_text(out_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    report = out_dir / "report.md"
    write_text(report, "\n".join(lines))
    return report
