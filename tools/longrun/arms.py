"""The arms of a study (runs of one recipe, one per seed): their table, the selection
rule's verdicts and the ship gates against a reference run (``long_run.py arms``)."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from .paths import CARRIED, write_json
from .real_scores import BALL
from .run import Run
from .variant_study import metric_columns

ARM_CROPS = ("cowPNG", "gobletPNG", "pot1PNG", "pot2PNG")  # dev-real: their mean at all images
ARM_LIGHTS = ("10", "17", "305")
ARM_COLUMNS = ("dev_real", *ARM_CROPS, BALL, "crops_10", *(f"nonconvex_{n}" for n in ARM_LIGHTS), "cpu_hours")
# the ship gates of docs/models.md, "Model v6: the plan and the selection rule"
GATE_DEV_REAL, GATE_GOBLET, GATE_BALL, GATE_CROPS_10_UNDER = 6.0, 6.5, 2.0, 1.0
GATES = {"dev_real": "dev-real <= 6.0", "crops": "no crop worse than ref.", "goblet": "goblet <= 6.5",
         "ball": "BALL <= 2.0", "nonconvex": "non-convex 17 / 305 no worse than ref.",
         "crops_10": "crops @10 >= 1 deg under ref."}
# eval keys that change where or how fast a model is scored, not its numbers
_EVAL_MACHINE_KEYS = ("model", "device", "batch_size")


def parse_arm(item: str) -> tuple[str, list[str]]:
    """``--arm NAME=RUN[,RUN...]`` as (NAME, [RUN, ...]).

    >>> parse_arm("heatmap=v6-hm-s1,v6-hm-s2")
    ('heatmap', ['v6-hm-s1', 'v6-hm-s2'])
    """
    name, _, runs = item.partition("=")
    names = [r.strip() for r in runs.split(",") if r.strip()]
    if not name.strip() or not names:
        raise SystemExit(f"--arm {item!r}: expected NAME=RUN[,RUN...]")
    return name.strip(), names


def arm_run_row(run: Run) -> dict | None:
    """One run's columns for ``arms``, from its ``data/eval/metrics.json``, its eval section
    (K: the largest of ``eval.rotations``) and its ledger: ``dev_real`` (``summary_real``, the
    real captures' mean but ``real_exclude_from_mean``), each crop and ``ballPNG`` from all
    their images, ``crops_10`` (``summary_real_subsets["10"]``), ``nonconvex_N`` (CNN over
    least squares at N lights), in degrees or ratios, None where the file has no such
    number; ``cpu_hours`` (the train and eval stages) and ``cpu_hours_all`` (every stage
    in the ledger); ``seed`` (``train.seed``, else the top-level ``seed``) and ``eval``
    (the section). None: not scored yet (no metrics file). A run with no ``params.yaml``
    (a misspelt name) or an unreadable metrics file stops with one line naming the file."""
    if not run.params.is_file():
        raise SystemExit(f"{run.params}: no such file: {run.name!r} is not a run under {run.dir.parent}")
    params = yaml.safe_load(run.params.read_text()) or {}
    file = run.data / "eval" / "metrics.json"
    if not file.is_file():
        return None
    try:
        em = json.loads(file.read_text())
    except ValueError as e:
        raise SystemExit(f"{file}: not a metrics file ({e})")
    ev = params.get("eval") or {}
    k = f"cnn_k{max(ev.get('rotations') or [1, 10])}"  # as metric_columns

    def mean(summary):
        return ((summary or {}).get(k) or {}).get("mean_deg")

    cols = metric_columns(em, ev)
    totals = run.totals()
    return {"run": run.name, "seed": (params.get("train") or {}).get("seed", params.get("seed", 0)), "k": k,
            "dev_real": mean(em.get("summary_real")), **{c: cols.get(f"{c}_deg") for c in (*ARM_CROPS, BALL)},
            "crops_10": mean((em.get("summary_real_subsets") or {}).get("10")),
            **{f"nonconvex_{n}": cols.get(f"nonconvex_{n}_vs_ls") for n in ARM_LIGHTS},
            "cpu_hours": round(sum(totals.get(s, {}).get("cpu_hours", 0.0) for s in ("train", "eval")), 3),
            "cpu_hours_all": round(sum(t["cpu_hours"] for t in totals.values()), 3), "eval": ev}


def arm_summary(rows: list[dict]) -> dict:
    """Per column of :data:`ARM_COLUMNS`: ``mean`` over the seeds (``rows``, one per run)
    that have it and ``spread``, half the range between them (None: fewer than 2 seeds).

    >>> arm_summary([{"dev_real": 5.0}, {"dev_real": 5.5}])["dev_real"]
    {'mean': 5.25, 'spread': 0.25}
    """
    out = {}
    for col in ARM_COLUMNS:
        vals = [r[col] for r in rows if r.get(col) is not None]
        out[col] = {"mean": sum(vals) / len(vals) if vals else None,
                    "spread": (max(vals) - min(vals)) / 2 if len(vals) >= 2 else None}
    return out


def judge_pair(name_a: str, a: dict, name_b: str, b: dict) -> dict:
    """The selection rule on two arms' :func:`arm_summary`: one beats the other only where
    the difference of the dev-real means exceeds the larger of the two spreads (lower is
    better). ``verdict``: the winner's name, ``"inside the spread"`` (the rule keeps the
    cheaper arm) or ``"not judged"`` (an arm with fewer than 2 seeds: no spread)."""
    ma, mb = a["dev_real"]["mean"], b["dev_real"]["mean"]
    sa, sb = a["dev_real"]["spread"], b["dev_real"]["spread"]
    out = {"arms": [name_a, name_b], "difference": None if None in (ma, mb) else ma - mb,
           "bar": None if None in (sa, sb) else max(sa, sb)}
    if out["difference"] is None or out["bar"] is None:
        out["verdict"] = "not judged"
    elif abs(out["difference"]) > out["bar"]:
        out["verdict"] = name_a if out["difference"] < 0 else name_b
    else:
        out["verdict"] = "inside the spread"
    return out


def judge_reference(arm: dict, ref: dict) -> bool | None:
    """Whether the arm's dev-real mean is under the reference run's ``ref`` by more than
    the arm's own spread; None: not judged (fewer than 2 seeds, or a number missing)."""
    m, s, r = arm["dev_real"]["mean"], arm["dev_real"]["spread"], ref.get("dev_real")
    return None if None in (m, s, r) else r - m > s


def ship_gates(arm: dict, ref: dict | None) -> dict:
    """The ship gates on an arm's means (``arm``: :func:`arm_summary`) against the
    reference run's row (``ref``: :func:`arm_run_row`, None: no reference), each True
    (pass), False (fail) or None (a number missing): keys of :data:`GATES`. The gate on
    ``cnnps predict``'s time is not among them (it is timed on one machine, not read
    from the runs)."""
    m = {c: arm[c]["mean"] for c in ARM_COLUMNS}
    ref = ref or {}

    def gate(cols, bound):  # bound(column): the most the arm's mean may be
        pairs = [(m[c], bound(c)) for c in cols]
        return None if any(None in p for p in pairs) else all(v <= b for v, b in pairs)

    return {"dev_real": gate(["dev_real"], lambda c: GATE_DEV_REAL),
            "crops": gate(ARM_CROPS, ref.get),
            "goblet": gate(["gobletPNG"], lambda c: GATE_GOBLET),
            "ball": gate([BALL], lambda c: GATE_BALL),
            "nonconvex": gate(["nonconvex_17", "nonconvex_305"], ref.get),
            "crops_10": gate(["crops_10"], lambda c: None if ref.get(c) is None else ref[c] - GATE_CROPS_10_UNDER)}


def study_arms(study: str, arms: list[tuple[str, list[str]]], reference: str | None, root: Path,
               carried: Path = CARRIED) -> dict:
    """The arms of ``study`` (``[(NAME, [RUN, ...])]``, runs under ``root``) judged by the
    selection rule, written to ``carried/STUDY/arms.json`` and returned: ``arms`` (per arm
    its scored runs' rows, :func:`arm_run_row`; ``seeds``; ``columns``, :func:`arm_summary`;
    CPU-hours per seed and in all; ``vs_reference``, :func:`judge_reference`; ``gates``,
    :func:`ship_gates`), ``reference`` (its row), ``pairs`` (:func:`judge_pair` of every
    two arms), ``best`` (the lowest dev-real mean among arms of 2 seeds or more),
    ``not_scored`` (runs with no metrics yet, left out) and ``notes`` (runs scored on
    another eval section, arms whose runs share a seed). A reference with no metrics
    stops with one line naming its file: every gate compares to it."""
    names = [n for n, _ in arms]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise SystemExit(f"--arm {twice[0]}=...: an arm named twice")
    ref = None
    if reference:
        ref_run = Run(reference, root, carried)
        ref = arm_run_row(ref_run)
        if ref is None:
            raise SystemExit(f"{ref_run.data / 'eval' / 'metrics.json'}: no such file: the reference run {reference!r} "
                             "is not scored yet (resume it with --stages eval)")
    out = {"study": study, "reference": ref, "arms": [], "not_scored": [], "notes": []}
    for name, runs in arms:
        rows = []
        for r in runs:
            row = arm_run_row(Run(r, root, carried))
            if row is None:
                out["not_scored"].append({"arm": name, "run": r})
            else:
                rows.append(row)
        seeds = [r["seed"] for r in rows]
        same = sorted({str(s) for s in seeds if seeds.count(s) > 1})
        if same:
            out["notes"].append(f"arm {name}: runs of the same train.seed ({', '.join(same)}) are not independent seeds")
        cols = arm_summary(rows)
        out["arms"].append({"name": name, "runs": rows, "seeds": len(rows), "columns": cols,
                            "cpu_hours_total": round(sum(r["cpu_hours"] for r in rows), 3),
                            "cpu_hours_all": round(sum(r["cpu_hours_all"] for r in rows), 3),
                            "vs_reference": None if ref is None else judge_reference(cols, ref),
                            "gates": ship_gates(cols, ref)})
    scored = ([ref] if ref else []) + [r for arm in out["arms"] for r in arm["runs"]]
    for r in scored[1:]:
        diff = sorted(k for k in set(r["eval"]) | set(scored[0]["eval"])
                      if k not in _EVAL_MACHINE_KEYS and r["eval"].get(k) != scored[0]["eval"].get(k))
        if diff:
            out["notes"].append(f"run {r['run']} is scored on another eval section than {scored[0]['run']} "
                                f"({', '.join(diff)} differ)")
    for r in scored:
        r.pop("eval")
    cols = {a["name"]: a["columns"] for a in out["arms"]}
    out["pairs"] = [judge_pair(a, cols[a], b, cols[b]) for i, a in enumerate(names) for b in names[i + 1:]]
    judged = [a for a in out["arms"] if a["columns"]["dev_real"]["spread"] is not None]
    out["best"] = min(judged, key=lambda a: a["columns"]["dev_real"]["mean"])["name"] if judged else None
    write_json(Path(carried) / study / "arms.json", out)
    return out


def _cell(col: dict | float | None, fmt: str = "{:.2f}") -> str:
    """``mean ± spread`` of :func:`arm_summary`'s column (``± ?``: one seed), or a number."""
    if not isinstance(col, dict):
        return "n/a" if col is None else fmt.format(col)
    if col["mean"] is None:
        return "n/a"
    return fmt.format(col["mean"]) + " ± " + ("?" if col["spread"] is None else fmt.format(col["spread"]))


def format_arms(out: dict) -> str:
    """:func:`study_arms`' result as Markdown: the arms' table (the reference's row last),
    the verdicts of the selection rule and the ship gates."""
    head = ("| arm | seeds | CPU-h per seed | dev-real mean ± spread | cow / goblet / pot1 / pot2 | BALL | crops @10 "
            "| non-convex 10 / 17 / 305 (x LS) |")
    lines = [head, "|" + " --- |" * 8]
    rows = [(a["name"], a["seeds"], a["columns"]) for a in out["arms"]]
    if out["reference"]:
        rows.append((f"reference: {out['reference']['run']}", 1, out["reference"]))
    for name, seeds, c in rows:
        crops = " / ".join(_cell(c[k]) for k in ARM_CROPS)
        ratios = " / ".join(_cell(c[f"nonconvex_{n}"], "{:.3f}") for n in ARM_LIGHTS)
        lines.append(f"| {name} | {seeds} | {_cell(c['cpu_hours'])} | {_cell(c['dev_real'])} | {crops} "
                     f"| {_cell(c[BALL])} | {_cell(c['crops_10'])} | {ratios} |")
    lines += ["", "Degrees at K as scored, every image (BALL: 96); spread: half the range between an arm's seeds; "
              "± ?: one seed, spread unknown: an arm needs at least 2 seeds to be judged."]
    lines += [f"Not scored yet, left out: run {n['run']} of arm {n['arm']} (no data/eval/metrics.json)"
              for n in out["not_scored"]]
    lines += ["", "Pairs (one arm beats another only where the dev-real means differ by more than the larger spread):"]
    for p in out["pairs"]:
        a, b = p["arms"]
        if p["verdict"] == "not judged":
            lines.append(f"- {a} vs {b}: not judged (an arm with fewer than 2 seeds)")
        elif p["verdict"] == "inside the spread":
            lines.append(f"- {a} vs {b}: {abs(p['difference']):.2f} apart, inside the larger spread {p['bar']:.2f}: "
                         "neither beats the other (the rule keeps the cheaper arm: fewer multiply-adds per sample)")
        else:
            lines.append(f"- {a} vs {b}: {p['verdict']} beats {b if p['verdict'] == a else a} by "
                         f"{abs(p['difference']):.2f}, more than the larger spread {p['bar']:.2f}")
    if not out["pairs"]:
        lines.append("- none: one arm")
    if out["reference"]:
        ref = out["reference"]
        lines += ["", f"Against the reference {ref['run']} (dev-real {_cell(ref['dev_real'])}; "
                      "beaten by more than the arm's own spread):"]
        words = {True: "beats it", False: "does not beat it", None: "not judged (fewer than 2 seeds)"}
        lines += [f"- {a['name']}: {words[a['vs_reference']]}" for a in out["arms"]]
    lines += ["", "| arm | " + " | ".join(GATES.values()) + " |", "|" + " --- |" * (len(GATES) + 1)]
    words = {True: "pass", False: "FAIL", None: "n/a"}
    lines += [f"| {a['name']} | " + " | ".join(words[a["gates"][g]] for g in GATES) + " |" for a in out["arms"]]
    lines += ["", "Gates on the arms' means (n/a: a number or the reference missing); the gate on `cnnps predict`'s "
                  "time on BALL (at most 1.5 x the reference's, one machine) is timed apart, not read from the runs.",
              f"Best arm by the dev-real mean (arms of 2 seeds or more): {out['best'] or 'none yet'}.",
              f"CPU-hours of the arms' runs: {sum(a['cpu_hours_total'] for a in out['arms']):.2f} (train and eval), "
              f"{sum(a['cpu_hours_all'] for a in out['arms']):.2f} (every stage in their ledgers; renders linked "
              "from another run are in that run's ledger)."]
    lines += [f"Note: {n}" for n in out["notes"]]
    return "\n".join(lines)
