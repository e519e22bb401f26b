"""Two or more `cnnps score --out` files side by side: per capture, and averaged per group of
captures and image count.

    .venv/bin/python -m benchmarks.predict.score_groups before=A.json after=B.json \\
        --group ball='ballPNG*' --group crops='*PNG*' --group synthetic='*' \\
        [--method cnn_k10] [--out benchmarks/results/predict/score_groups_<name>.json] [--name NAME]

Each capture (and image subset, ``ballPNG-6``) of the first file goes to the first group whose
glob its name matches (``fnmatch``, in the order given); the files must hold the same
captures. The groups' means are of ``--method``'s mean angular error over their captures at
each image count (``n_images``), least squares of the first file beside them. Prints the
table and writes it with the files' models, options and SHA-256 in the result schema
(benchmarks/README.md; the harness records the machine and the commit).

Example: ``group_means({"a": score_a}, [("ball", "ball*"), ("rest", "*")])["a"]["ball"]["96"]``.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
from pathlib import Path

from benchmarks.harness import result_path, write_result

LAMBERTIAN = "lambertian"


def group_of(name: str, groups: list[tuple[str, str]]) -> str | None:
    """The first group whose glob matches ``name``; None if none does.

    >>> group_of("ballPNG-6", [("ball", "ball*"), ("crops", "*PNG*")])
    'ball'
    """
    return next((g for g, pattern in groups if fnmatch.fnmatchcase(name, pattern)), None)


def group_means(scores: dict[str, dict], groups: list[tuple[str, str]], method: str = "cnn_k10") -> dict:
    """{label: {group: {n_images: mean of the captures' mean_deg}}} for each ``cnnps score``
    record in ``scores`` ({label: record}), plus the label ``lambertian`` (least squares, from
    the first record). A ValueError names a capture one record lacks or a method it has not."""
    labels = list(scores)
    first = scores[labels[0]]["captures"]
    out: dict[str, dict] = {label: {} for label in [*labels, LAMBERTIAN]}
    for name, cap in first.items():
        g = group_of(name, groups)
        if g is None:
            continue
        n = str(cap["n_images"])
        for label in [*labels, LAMBERTIAN]:
            rec = scores[labels[0] if label == LAMBERTIAN else label]["captures"]
            if name not in rec:
                raise ValueError(f"{label}: no capture {name!r} (the files must hold the same captures)")
            m = LAMBERTIAN if label == LAMBERTIAN else method
            if m not in rec[name]["methods"]:
                raise ValueError(f"{label}: capture {name!r} has no method {m!r}")
            out[label].setdefault(g, {}).setdefault(n, []).append(rec[name]["methods"][m]["mean_deg"])
    return {label: {g: {n: sum(v) / len(v) for n, v in by_n.items()} for g, by_n in gs.items()}
            for label, gs in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", metavar="LABEL=FILE", help="cnnps score --out files, each with a label")
    ap.add_argument("--group", action="append", default=[], metavar="NAME=GLOB", help="in order; the first match wins")
    ap.add_argument("--method", default="cnn_k10")
    ap.add_argument("--name", default=None, help="names the default --out file")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    scores, files = {}, {}
    for item in args.files:
        label, sep, path = item.partition("=")
        if not sep or not label:
            ap.error(f"{item!r}: give LABEL=FILE")
        try:
            scores[label] = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            sys.exit(f"{path}: not a readable cnnps score file ({e})")
        files[label] = {"file": path, "model": scores[label].get("model"),
                        "model_sha256": scores[label].get("model_sha256"), "options": scores[label].get("options")}
    groups = [tuple(g.split("=", 1)) for g in args.group] or [("all", "*")]
    if any(len(g) != 2 for g in groups):
        ap.error("--group takes NAME=GLOB")
    try:
        means = group_means(scores, groups, args.method)
    except ValueError as e:
        sys.exit(str(e))
    labels = [*scores, LAMBERTIAN]
    width = max(len("group"), *(len(g) for g, _ in groups))
    print(f"{'group':{width}s} {'images':>6s}" + "".join(f"{lab[:12]:>13s}" for lab in labels))
    for g, _ in groups:
        for n in sorted(means[labels[0]].get(g, {}), key=int, reverse=True):
            print(f"{g:{width}s} {n:>6s}" + "".join(f"{means[lab][g][n]:13.2f}" for lab in labels))
    first = labels[0]
    captures = {}
    for name in scores[first]["captures"]:
        if group_of(name, groups):
            row = {lab: scores[lab]["captures"][name]["methods"][args.method]["mean_deg"] for lab in scores}
            row[LAMBERTIAN] = scores[first]["captures"][name]["methods"][LAMBERTIAN]["mean_deg"]
            captures[name] = row
    out = args.out or result_path(__spec__.name, args.name)
    write_result(out, __spec__.name, {"files": files, "groups": dict(groups), "method": args.method},
                 {"group_means": means, "captures": captures})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
