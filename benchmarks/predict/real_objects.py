"""A weights file on the real objects: BALL and the four 8-bit crops, least squares beside.

    .venv/bin/python -m benchmarks.predict.real_objects [--model shipped|PATH] [--name v4]
        [--rotations 10] [--subsets 10,6] [--shared ../shared]
        [--out benchmarks/results/predict/real_objects_<name>.json]

Runs `cnnps score` (the eval stage's scoring, `cnnps predict`'s default options) on
../shared/data/diligent/ballPNG and ../shared/data/diligent-crop8/{cow,goblet,pot1,pot2}PNG
with the image subsets of benchmarks/image_lists/ (the same seeded rule), BALL left out of
the mean: "dev-real" is the mean over the four crops. Writes the command's --out JSON under
``score`` in the results, with the command it ran, ``lscpu``'s model name, the load
averages and the wall time (the harness records the machine and the commit). Captures
missing from --shared are left out with a line on stderr; none present is an error.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result

REFERENCE = "ballPNG"  # reported beside the dev-real mean, not in it
CAPTURES = (("diligent", "ballPNG"), ("diligent-crop8", "cowPNG"), ("diligent-crop8", "gobletPNG"),
            ("diligent-crop8", "pot1PNG"), ("diligent-crop8", "pot2PNG"))


def lscpu_model() -> str | None:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    for line in out.splitlines():
        if line.startswith("Model name:"):
            return line.split(":", 1)[1].strip()
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="shipped", help="checkpoint, or 'shipped' (default)")
    ap.add_argument("--name", default="v4", help="names the default --out file")
    ap.add_argument("--rotations", default="10")
    ap.add_argument("--subsets", default="10,6")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or result_path(__spec__.name, args.name)

    dirs = []
    for group, name in CAPTURES:
        d = args.shared / "data" / group / name
        if d.is_dir():
            dirs.append(d)
        else:
            print(f"real_objects: {d} not found; left out", file=sys.stderr)
    if not dirs:
        raise SystemExit(f"real_objects: no capture found under {args.shared / 'data'}")
    rel = [os.path.relpath(d, ROOT) for d in dirs]
    with tempfile.TemporaryDirectory() as tmp:
        score_file = Path(tmp) / "score.json"
        cmd = ["cnnps", "score", args.model, *rel, "--rotations", args.rotations, "--subsets", args.subsets,
               *(["--exclude-from-mean", REFERENCE] if any(d.name == REFERENCE for d in dirs) else []),
               "--out", str(score_file)]
        record = {"ran": shlex.join(cmd[:-1] + ["FILE.json"]), "lscpu_model_name": lscpu_model(),
                  "load_average_before": list(os.getloadavg())}
        with Stopwatch() as sw:
            proc = subprocess.run([sys.executable, "-m", "cnnps", *cmd[1:]], cwd=ROOT)
        if proc.returncode:
            raise SystemExit(f"real_objects: cnnps score exited with {proc.returncode}")
        record["wall_seconds"] = round(sw.seconds, 1)
        record["load_average_after"] = list(os.getloadavg())
        record["score"] = json.loads(score_file.read_text())
    write_result(out, __spec__.name, args, record)


if __name__ == "__main__":
    main()
