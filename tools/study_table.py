"""A Markdown table of several long runs side by side, from what git carries of each
(``tools/runs/NAME/``): what the run changed, its CPU-hours, the validation maps, the eval
stage's non-convex captures (CNN K=10 as a multiple of least squares, at each light
count) and the real objects (``long_run.py curve``: BALL, each crop and the dev-real mean,
on the curve's pixel sample).

    .venv/bin/python tools/study_table.py v5-fx-v4 v5-fx-five v5-fx-all --out benchmarks/results/v5_effects.json

A run's row uses its newest curve row; a run without one (e.g. an eval-only run of a
shipped model) takes ``--real NAME=FILE.json``, a ``cnnps score --out`` file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cnnps.infra.atomic import write_text

CARRIED = Path(__file__).resolve().parents[1] / "tools" / "runs"
CROPS = ("cowPNG", "gobletPNG", "pot1PNG", "pot2PNG")
BALL = "ballPNG"


def _read(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def real_columns(score: dict, k: int = 10) -> dict:
    """BALL, the crops and their mean from a ``cnnps score --out`` file."""
    key = f"cnn_k{k}"
    out = {name: round(cap["methods"][key]["mean_deg"], 3) for name, cap in score["captures"].items()
           if name in (BALL, *CROPS)}
    crops = [out[c] for c in CROPS if c in out]
    out["dev_real_mean_deg"] = round(sum(crops) / len(crops), 3) if len(crops) == len(CROPS) else None
    return out


def row_of(folder: Path, real_file: Path | None = None) -> dict:
    """One run's numbers (None where the run has not measured it)."""
    rec = _read(folder / "run.json") or {}
    ledger = _read(folder / "ledger.json") or {"calls": []}
    train_cpu = sum(c["cpu_s"] for c in ledger["calls"] if c["stage"] == "train") / 3600
    row: dict = {"name": folder.name, "changes": rec.get("overrides", []), "train_cpu_hours": round(train_cpu, 3)}
    tm = _read(folder / "train_metrics.json") or {}
    row["val_mean_deg"] = tm.get("val_mean_deg")
    em = _read(folder / "eval_metrics.json") or {}
    for n, group in (em.get("by_lights_nonconvex") or {}).items():
        row[f"eval_{n}_vs_ls"] = group.get("cnn_k10_vs_least_squares")
    if real_file is not None:
        row.update(real_columns(json.loads(real_file.read_text())))
        row["real_source"] = str(real_file)
    else:
        curve = _read(folder / "real_curve.json")
        if curve and curve["rows"]:
            last = curve["rows"][-1]
            row.update({k: last.get(k) for k in (BALL, *CROPS, "dev_real_mean_deg")})
            row["real_source"] = f"curve step {last['step']}, {last['options']['pixels']} pixels"
    return row


def markdown(rows: list[dict]) -> str:
    def f(v, fmt="{:.2f}"):
        return "" if v is None else fmt.format(v)

    head = ("| run | changes | train CPU-h | val (°) | eval 17 / 305 (× LS) | BALL | cow | goblet | pot1 | pot2 "
            "| dev-real |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    lines = [head]
    for r in rows:
        changes = " ".join(f"`{c}`" for c in r["changes"]) or "—"
        ev = f"{f(r.get('eval_17_vs_ls'), '{:.3f}')} / {f(r.get('eval_305_vs_ls'), '{:.3f}')}"
        lines.append(f"| {r['name']} | {changes} | {f(r['train_cpu_hours'])} | {f(r['val_mean_deg'])} | {ev} | "
                     + " | ".join(f(r.get(k)) for k in (BALL, *CROPS, "dev_real_mean_deg")) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="NAME")
    ap.add_argument("--real", action="append", default=[], metavar="NAME=FILE.json")
    ap.add_argument("--carried", type=Path, default=CARRIED)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    real = {}
    for spec in a.real:
        name, _, file = spec.partition("=")
        if not file or not Path(file).is_file():
            raise SystemExit(f"--real {spec!r}: expected NAME=FILE.json of an existing file")
        real[name] = Path(file)
    rows = []
    for name in a.runs:
        folder = a.carried / name
        if not folder.is_dir():
            raise SystemExit(f"{folder}: no such run folder")
        rows.append(row_of(folder, real.get(name)))
    print(markdown(rows))
    if a.out is not None:
        write_text(a.out, json.dumps({"rows": rows}, indent=1) + "\n")
        print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
