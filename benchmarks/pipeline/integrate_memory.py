"""Peak memory of the whole `cnnps integrate` command per mask pixel.

    .venv/bin/python -m benchmarks.pipeline.integrate_memory [--megapixels 2.5] [--small-side 100] [--repeat 3]
        [--repo PATH] [--before JSON] [--out benchmarks/results/pipeline/integrate_memory.json]

Inputs: a sphere's normals (float32 ``normal.npy``, zeros outside the mask, as ``cnnps
predict`` writes them) over a disc holding ``--megapixels`` million mask pixels in a square
frame (62 % of it), and its ``mask.png``; the same at ``--small-side`` x ``--small-side``
pixels. Each is integrated by the command line, ``python -m cnnps.pipeline integrate
normal.npy --mask mask.png --out OUT`` (what the ``cnnps`` script runs), in a child process
per run, ``--repeat`` times.

Measured per run: the child's peak resident memory (``ru_maxrss`` from ``os.wait4``: the
whole process, interpreter and imports included) and its wall time. Bytes a pixel = (peak
of the large map - peak of the small map) / mask pixels of the large map, which leaves
out the fixed cost of the interpreter and the imports. Target: at most 150.

Recorded with the results: the git commit of ``--repo`` (or ``--commit``) and whether its
``cnnps`` differs from it (``measured``: the harness records this checkout's). ``--repo``
measures another checkout's ``cnnps``; ``--before`` keeps such a run's result file under
``"before"``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, SCHEMA, Stopwatch, result_path, write_result
from cnnps.io.images import write_png

TARGET_BYTES_PER_PIXEL = 150


def write_inputs(folder: Path, side: int) -> int:
    """normal.npy and mask.png of a sphere over a disc in a side x side frame; the mask
    pixel count."""
    folder.mkdir(parents=True, exist_ok=True)
    r, c = np.mgrid[0:side, 0:side]
    x = (c - side / 2) / (side * 0.45)
    y = -(r - side / 2) / (side * 0.45)
    del r, c
    mask = x * x + y * y < 0.97
    normals = np.dstack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, None))]).astype(np.float32)
    del x, y
    normals[~mask] = 0.0
    np.save(folder / "normal.npy", normals)
    write_png(folder / "mask.png", (mask * 255).astype(np.uint8))
    return int(mask.sum())


def run_command(argv: list[str], repo: Path, log: Path) -> dict:
    """Run ``argv`` with ``repo`` first on the path; its peak RSS (MB), wall time (s) and
    the last line it printed."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    with open(log, "wb") as out:
        with Stopwatch() as sw:
            proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=repo)
            _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage
        seconds = sw.seconds
    proc.returncode = os.waitstatus_to_exitcode(status)
    text = log.read_text(errors="replace").strip()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({proc.returncode}):\n{text}")
    return {"peak_rss_mb": round(usage.ru_maxrss / 1024, 1), "seconds": round(seconds, 2),
            "output": text.splitlines()[-1] if text else ""}


def git_commit(repo: Path, commit: str | None = None) -> dict:
    """The checkout's commit and whether its cnnps/ differs from it (``commit`` and None
    outside a git checkout, e.g. for a ``git archive`` export)."""
    def git(*args):
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=False)

    head = git("rev-parse", "--short", "HEAD")
    if head.returncode != 0:
        return {"commit": commit, "cnnps_modified": None}
    return {"commit": head.stdout.strip(), "cnnps_modified": git("diff", "--quiet", "HEAD", "--", "cnnps").returncode != 0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--megapixels", type=float, default=2.5, help="mask pixels of the large map, in millions")
    ap.add_argument("--small-side", type=int, default=100, help="frame side of the small map, pixels")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--repo", type=Path, default=ROOT, help="the checkout whose cnnps is measured")
    ap.add_argument("--commit", help="the commit to record when --repo is not a git checkout")
    ap.add_argument("--before", type=Path, help="a result file of this benchmark to keep under 'before'")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args()
    repo = a.repo.resolve()
    sides = {"small": a.small_side, "large": int(np.sqrt(a.megapixels * 1e6 / 0.62))}
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bench_integrate_memory.") as tmp:
        tmp = Path(tmp)
        for name, side in sides.items():
            pixels = write_inputs(tmp / name, side)
            argv = [sys.executable, "-m", "cnnps.pipeline", "integrate", str(tmp / name / "normal.npy"),
                    "--mask", str(tmp / name / "mask.png"), "--out", str(tmp / name / "out")]
            runs = [run_command(argv, repo, tmp / f"{name}.log") for _ in range(a.repeat)]
            rows[name] = {"size": [side, side], "pixels": pixels,
                          "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
                          "peak_rss_mb_runs": [r["peak_rss_mb"] for r in runs],
                          "seconds_median": round(statistics.median(r["seconds"] for r in runs), 2),
                          "seconds_runs": [r["seconds"] for r in runs],
                          "output": runs[-1]["output"].replace(str(tmp), "TMP")}
            print(json.dumps({name: rows[name]}), flush=True)
    large, small = rows["large"], rows["small"]
    per_pixel = (large["peak_rss_mb"] - small["peak_rss_mb"]) * 1024 * 1024 / large["pixels"]
    res = {
        "ran": "python -m cnnps.pipeline integrate TMP/normal.npy --mask TMP/mask.png --out TMP/out",
        "measured": git_commit(repo, a.commit),
        "numpy": np.__version__,
        "target_bytes_per_pixel": TARGET_BYTES_PER_PIXEL,
        "bytes_per_pixel": round(per_pixel, 1),
        "rows": rows,
        "note": "peak_rss_mb: the largest ru_maxrss (MiB) of the command over the runs; bytes_per_pixel: "
                "(large - small) / mask pixels of the large map",
    }
    if a.before is not None:
        before = json.loads(a.before.read_text())
        if all(k in before for k in SCHEMA):  # this schema: the measured checkout and the date apart
            before = {**before["results"], **before["results"]["measured"], "date": before["date"]}
        res["before"] = {k: before.get(k) for k in ("commit", "cnnps_modified", "bytes_per_pixel", "rows", "date")}
    print(f"{large['pixels']} mask pixels peak {large['peak_rss_mb']:.0f} MiB "
          f"({large['seconds_median']:.1f} s), {small['pixels']} pixels {small['peak_rss_mb']:.0f} MiB: "
          f"{per_pixel:.0f} bytes a pixel (target {TARGET_BYTES_PER_PIXEL})")
    write_result(a.out, __spec__.name, a, res)


if __name__ == "__main__":
    main()
