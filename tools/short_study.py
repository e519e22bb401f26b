"""Short runs from random weights, their weight averages, scored on the fast proxy and on
real objects: the cheap part of a model study (docs/models.md, "Model v7: the cheap study").

    .venv/bin/python tools/short_study.py averages v7-base-s1 [--swa-from 1750] [--ema-half-life 500]
    .venv/bin/python tools/short_study.py score v7-base-s1 [--pixels 2000] [--rotations 10] [--variants last swa]
    .venv/bin/python tools/short_study.py score v7-renders-s1 --variants blend   # ROOT/RUN/variants/blend.pt
    .venv/bin/python tools/short_study.py reference v7 [--pixels 2000]   # the shipped model, scored alike
    .venv/bin/python tools/short_study.py table v7 --arm base=v7-base-s1,v7-base-s2 --arm cone50=...

Each run is a ``tools/long_run.py`` run (``ROOT/NAME``) whose train stage kept its
checkpoints (``train.keep_checkpoints`` at least the run's checkpoints).

- ``averages``: three weight files in ``ROOT/NAME/variants/``, made from the kept
  checkpoints: ``last`` (the newest), ``swa`` (the plain mean of the checkpoints from
  ``--swa-from`` on; default the run's first learning-rate milestone: the low-rate tail) and
  ``ema`` (every checkpoint weighted by 0.5 ** (age in steps / ``--ema-half-life``): an
  exponential moving average sampled at the checkpoints, a coarse stand-in for one kept
  every step).
- ``score``: each variant on the fast proxy, a Lambertian sphere with BALL's normals under
  BALL's 96 lights (``benchmarks.predict.tilt_bias --inputs lambert_ball_lights``: mean and
  lean per band of true tilt), and on real objects (``cnnps score``: BALL and the four
  DiLiGenT crops; dev-real is the crops' mean, BALL left out), both on a seeded sample of
  ``--pixels`` mask pixels per capture, K = ``--rotations``, this work tree's code. Rows go
  to ``tools/runs/NAME/short_scores.json``; the time of each call to the run's ledger
  (stage ``study``), so diagnostics count in the budget.
- ``reference``: the shipped model scored the same way, into ``tools/runs/STUDY/``
  (``reference.json`` and the calls in ``ledger.json``).
- ``table``: per arm (``--arm NAME=RUN,RUN``: one run per seed) and variant, the mean over
  the seeds and the spread (half the range) of every measure, the reference's row, and how
  well each cheap measure ranks dev-real over every scored (run, variant): Spearman's rho
  and Pearson's r. Printed, and kept in ``tools/runs/STUDY/short.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

try:
    from tools.longrun.paths import CARRIED, REPO, write_json
    from tools.longrun.run import Run
except ImportError:  # run as a script: its own folder is on the path
    from longrun.paths import CARRIED, REPO, write_json
    from longrun.run import Run

VARIANTS = ("last", "swa", "ema")
CAPTURES = ("diligent/ballPNG", "diligent-crop8/cowPNG", "diligent-crop8/gobletPNG", "diligent-crop8/pot1PNG",
            "diligent-crop8/pot2PNG")
BALL = "ballPNG"
PROXY = "lambert_ball_lights"
MEASURES = ("proxy_mean", "lean_20-40", "lean_40-55", "lean_55-70", "ball", "cowPNG", "gobletPNG", "pot1PNG",
            "pot2PNG", "dev_real")


# --------------------------------------------------------------------------- averages


def checkpoints(run: Run) -> dict[int, Path]:
    """The run's kept train-stage checkpoints by step."""
    found = {int(p.stem.split("-")[1]): p for p in (run.data / "train" / "checkpoints").glob("step-*.pt")}
    if not found:
        raise SystemExit(f"{run.data / 'train' / 'checkpoints'}: no checkpoint")
    return dict(sorted(found.items()))


def average_weights(steps: list[int], weights: list[float], load) -> dict:
    """sum_i weights_i * state_i / sum(weights) of the states ``load(step)`` gives, in float64."""
    total = float(sum(weights))
    mean = None
    for step, wgt in zip(steps, weights):
        state = load(step)
        if mean is None:
            mean = {k: v.double() * (wgt / total) for k, v in state.items()}
        else:
            for k, v in state.items():
                mean[k] += v.double() * (wgt / total)
    return mean


def variant_weights(steps: list[int], swa_from: int, half_life: float) -> dict[str, dict[int, float]]:
    """Each variant's weight per checkpoint step (those with weight 0 left out)."""
    last = steps[-1]
    swa = [s for s in steps if s >= swa_from] or [last]
    return {"last": {last: 1.0}, "swa": {s: 1.0 for s in swa},
            "ema": {s: 0.5 ** ((last - s) / half_life) for s in steps}}


def make_averages(run: Run, swa_from: int | None, half_life: float) -> dict:
    import torch

    cks = checkpoints(run)
    train = (yaml.safe_load(run.params.read_text()).get("train") or {})
    milestones = (train.get("optimiser") or {}).get("lr_milestones") or []
    swa_from = int(swa_from if swa_from is not None else (milestones[0] if milestones else max(cks)))
    out_dir = run.dir / "variants"
    out_dir.mkdir(exist_ok=True)
    cache: dict[int, dict] = {}

    def load(step):
        if step not in cache:
            cache[step] = torch.load(cks[step], map_location="cpu", weights_only=True)["model"]
        return cache[step]

    made = {}
    for name, by_step in variant_weights(list(cks), swa_from, half_life).items():
        state = average_weights(list(by_step), list(by_step.values()), load)
        like = load(max(cks))
        state = {k: v.to(like[k].dtype) for k, v in state.items()}
        with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
            src = Path(tmp) / "state.pt"
            torch.save({"model": state}, src)
            meta = {"run": run.name, "variant": name, "steps": {str(s): round(w, 6) for s, w in by_step.items()}}
            run.export(src, out_dir / f"{name}.pt", meta=meta)
        made[name] = {"steps": sorted(by_step), "weights": [round(by_step[s], 6) for s in sorted(by_step)]}
        print(f"{run.name}: {name} <- steps {sorted(by_step)}", flush=True)
    write_json(out_dir / "variants.json", {"swa_from": swa_from, "ema_half_life": half_life, "variants": made})
    return made


# --------------------------------------------------------------------------- scoring


def timed(cmd: list[str], book) -> int:
    """Run ``cmd`` here (this work tree's code); ``book(wall_s, cpu_s, rc)`` records its time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.time()
    rc = subprocess.run(cmd, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO))).returncode
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    book(time.time() - t0, cpu, rc)
    return rc


def ledger_entry(stage: str, commit: str, wall: float, cpu: float, rc: int, **extra) -> dict:
    from cnnps.infra.machine import cpu_model_and_flags

    return {"stage": stage, **extra, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(time.time() - wall)),
            "cpu": cpu_model_and_flags()[0], "logical_cpus": os.cpu_count(), "commit": commit[:12],
            "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "finished": rc == 0, "exit": rc,
            "id": f"{os.getpid()}-{time.time():.3f}"}


def score_weights(weights: Path, label: str, shared: Path, pixels: int, rotations: int, book) -> dict:
    """The proxy's and the real objects' row of one weights file."""
    with tempfile.TemporaryDirectory() as tmp:
        proxy_out, real_out = Path(tmp) / "proxy.json", Path(tmp) / "real.json"
        cmd = [sys.executable, "-m", "benchmarks.predict.tilt_bias", f"{label}={weights}", "--inputs", PROXY,
               "--pixels", str(pixels), "--rotations", str(rotations), "--out", str(proxy_out)]
        if timed(cmd, lambda w, c, rc: book(w, c, rc, what="proxy")):
            raise SystemExit(f"the proxy exited with an error on {weights}")
        caps = [str(shared / c) for c in CAPTURES]
        cmd = [sys.executable, "-m", "cnnps", "score", str(weights), *caps, "--pixels", str(pixels),
               "--rotations", str(rotations), "--exclude-from-mean", BALL, "--precision", "fp32", "--out", str(real_out)]
        if timed(cmd, lambda w, c, rc: book(w, c, rc, what="real")):
            raise SystemExit(f"cnnps score exited with an error on {weights}")
        proxy = json.loads(proxy_out.read_text())["results"]["models"][label][PROXY]
        real = json.loads(real_out.read_text())
    k = f"cnn_k{rotations}"
    row = {"proxy_mean": proxy["mean_deg"], **{f"lean_{b}": v for b, v in proxy["tilt_bias_deg"].items()}}
    for name, cap in real["captures"].items():
        row["ball" if name == BALL else name] = round(cap["methods"][k]["mean_deg"], 3)
    row["dev_real"] = round(real["summary_real"][k]["mean_deg"], 3)
    row["model_sha256"] = real.get("model_sha256")
    return row


def score_run(run: Run, shared: Path, pixels: int, rotations: int, variants=VARIANTS) -> dict:
    folder = run.dir / "variants"
    if not (folder / "variants.json").is_file():
        raise SystemExit(f"{folder}: no weight variants yet (run `averages {run.name}` first)")
    record = run.carried / "short_scores.json"
    old = json.loads(record.read_text()) if record.is_file() else {"rows": {}}
    options = {"pixels": pixels, "rotations": rotations}
    rows = old["rows"] if old.get("options") == options else {}
    commit = run.record()["commit"]
    missing = [n for n in variants if not (folder / f"{n}.pt").is_file()]
    if missing:
        raise SystemExit(f"{folder / (missing[0] + '.pt')}: no such variant (averages makes last, swa, ema; "
                         "put any other weights file there by that name)")
    for name in variants:
        if name in rows:
            continue

        def book(wall, cpu, rc, **extra):
            run._record_call(ledger_entry("study", commit, wall, cpu, rc, variant=name, **extra))

        print(f"{run.name}: scoring {name}", flush=True)
        rows[name] = score_weights(folder / f"{name}.pt", name, shared, pixels, rotations, book)
        print(f"{run.name} {name}: {rows[name]}", flush=True)
        write_json(record, {"run": run.name, "options": options, "scorer_commit": _head(),
                             "variants": json.loads((folder / "variants.json").read_text()), "rows": rows})
    return rows


def score_reference(study: Path, shared: Path, pixels: int, rotations: int) -> dict:
    from cnnps.models.shipped import shipped_model_path

    study.mkdir(parents=True, exist_ok=True)
    ledger = study / "ledger.json"

    def book(wall, cpu, rc, **extra):
        calls = json.loads(ledger.read_text())["calls"] if ledger.is_file() else []
        calls.append(ledger_entry("study", _head(), wall, cpu, rc, variant="reference", **extra))
        write_json(ledger, {"calls": calls})

    row = score_weights(shipped_model_path(), "shipped", shared, pixels, rotations, book)
    write_json(study / "reference.json", {"options": {"pixels": pixels, "rotations": rotations},
                                           "scorer_commit": _head(), "row": row})
    return row


def _head() -> str:
    return subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()


# --------------------------------------------------------------------------- table


def spearman(x, y) -> float:
    """Spearman's rank correlation (average ranks for ties)."""
    from scipy.stats import spearmanr

    return float(spearmanr(x, y).statistic)


def arm_table(arms: dict[str, list[str]], carried: Path) -> dict:
    """Per arm and variant the mean and spread over its runs; missing runs are listed."""
    out, points, missing = {}, [], []
    for arm, runs in arms.items():
        rows = {}
        for name in runs:
            f = carried / name / "short_scores.json"
            if not f.is_file():
                missing.append(name)
                continue
            for variant, row in json.loads(f.read_text())["rows"].items():
                rows.setdefault(variant, []).append(row)
                points.append(row)
        out[arm] = {v: {m: (round(float(np.mean([r[m] for r in rs])), 3),
                            round(float((max(r[m] for r in rs) - min(r[m] for r in rs)) / 2), 3), len(rs))
                        for m in MEASURES if all(m in r for r in rs)}
                    for v, rs in rows.items()}
    ranks = {}
    if len(points) >= 3:
        dev = [p["dev_real"] for p in points]
        for m in ("proxy_mean", "ball", "lean_40-55"):
            xs = [p[m] for p in points if m in p]
            if len(xs) < len(points) or len(set(xs)) < 2 or len(set(dev)) < 2:
                continue  # a measure some rows lack, or a constant: no correlation to speak of
            ranks[m] = {"spearman": round(spearman(xs, dev), 3), "pearson": round(float(np.corrcoef(xs, dev)[0, 1]), 3),
                        "points": len(points)}
    return {"arms": out, "predicts_dev_real": ranks, "missing": missing}


def print_table(table: dict, reference: dict | None) -> None:
    cols = ("proxy_mean", "lean_20-40", "lean_40-55", "lean_55-70", "ball", "dev_real", "cowPNG", "gobletPNG",
            "pot1PNG", "pot2PNG")
    print("| arm | variant | seeds | " + " | ".join(cols) + " |")
    print("|" + " --- |" * (len(cols) + 3))
    for arm, variants in table["arms"].items():
        for v in VARIANTS:
            if v not in variants:
                continue
            cells = variants[v]
            n = next(iter(cells.values()))[2]
            print(f"| {arm} | {v} | {n} | " + " | ".join(
                f"{cells[c][0]:.2f} ± {cells[c][1]:.2f}" if c in cells else "" for c in cols) + " |")
    if reference:
        print("| v4 (shipped) | | | " + " | ".join(f"{reference[c]:.2f}" if c in reference else "" for c in cols) + " |")
    for m, r in table["predicts_dev_real"].items():
        print(f"{m} against dev-real over {r['points']} (run, variant) points: Spearman {r['spearman']}, "
              f"Pearson {r['pearson']}")
    if table["missing"]:
        print("not scored yet:", ", ".join(table["missing"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cmd", choices=["averages", "score", "reference", "table"])
    ap.add_argument("names", nargs="+", help="runs (averages, score) or the study's name (reference, table)")
    ap.add_argument("--root", type=Path, default=Path("/work/runs"))
    ap.add_argument("--carried", type=Path, default=CARRIED)
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--swa-from", type=int, default=None)
    ap.add_argument("--ema-half-life", type=float, default=500.0)
    ap.add_argument("--pixels", type=int, default=2000)
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--arm", action="append", default=[], metavar="NAME=RUN[,RUN...]")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS),
                    help="score: these variants only (last, swa, ema, or NAME for any weights file put in "
                         "ROOT/RUN/variants/NAME.pt, e.g. a blend made by python -m cnnps.models.interpolate)")
    a = ap.parse_args(argv)
    if a.cmd in ("score", "reference") and not (a.shared / CAPTURES[0]).is_dir():
        raise SystemExit(f"{a.shared / CAPTURES[0]}: not a capture folder (--shared)")
    if a.cmd == "averages":
        for name in a.names:
            make_averages(Run(name, a.root, a.carried), a.swa_from, a.ema_half_life)
    elif a.cmd == "score":
        for name in a.names:
            score_run(Run(name, a.root, a.carried), a.shared, a.pixels, a.rotations, a.variants)
    elif a.cmd == "reference":
        print(score_reference(a.carried / a.names[0], a.shared, a.pixels, a.rotations))
    else:
        arms = {}
        for item in a.arm:
            arm, sep, runs = item.partition("=")
            if not sep or not runs:
                raise SystemExit(f"--arm {item}: expected NAME=RUN[,RUN...]")
            arms[arm] = runs.split(",")
        table = arm_table(arms, a.carried)
        ref_file = a.carried / a.names[0] / "reference.json"
        reference = json.loads(ref_file.read_text())["row"] if ref_file.is_file() else None
        table["reference"] = reference
        write_json(a.carried / a.names[0] / "short.json", table)
        print_table(table, reference)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
