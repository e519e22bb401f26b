"""Peak memory of normal integration per mask pixel, orthographic and perspective.

    .venv/bin/python benchmarks/bench_integrate_memory.py [--megapixels 2.5] [--out benchmarks/results/integrate_memory.json]

A sphere's normals (float32, as ``cnnps predict`` writes them) over a disc holding
``--megapixels`` million mask pixels in a square frame (62 % of it), integrated by
``cnnps.ps.integrate.integrate`` in a fresh process per case. Measured: the peak of the
memory numpy allocates during the call (``tracemalloc``, which numpy reports to), per
mask pixel, over what the inputs already hold; the process's peak resident memory
(``ru_maxrss``) for reference; wall time and CG iterations. Target: under 150 bytes a pixel.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_info  # noqa: E402

CHILD = r"""
import json, resource, sys, time, tracemalloc
import numpy as np
sys.path.insert(0, sys.argv[3])
from cnnps.ps.integrate import integrate
mp, camera = float(sys.argv[1]), sys.argv[2]
side = int(np.sqrt(mp * 1e6 / 0.62))
r, c = np.mgrid[0:side, 0:side]
x = (c - side / 2) / (side * 0.45)
y = -(r - side / 2) / (side * 0.45)
del r, c
mask = x * x + y * y < 0.97
normals = np.dstack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, None))]).astype(np.float32)
del x, y
normals[~mask] = (0.0, 0.0, 1.0)
K = None if camera == "orthographic" else np.array([[1.2 * side, 0, side / 2], [0, 1.2 * side, side / 2], [0, 0, 1.0]])
P = int(mask.sum())
tracemalloc.start()
t0 = time.perf_counter()
res = integrate(normals, mask, intrinsics=K)
seconds = time.perf_counter() - t0
peak = tracemalloc.get_traced_memory()[1]
print(json.dumps({"camera": camera, "size": [side, side], "pixels": P, "seconds": round(seconds, 2),
                  "cg_iterations": res.iterations, "peak_bytes_per_pixel": round(peak / P, 1),
                  "process_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--megapixels", type=float, default=2.5)
    ap.add_argument("--repo", type=Path, default=REPO, help="the checkout whose cnnps is measured")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks/results/integrate_memory.json")
    a = ap.parse_args()
    rows = []
    for camera in ("orthographic", "perspective"):
        out = subprocess.run([sys.executable, "-c", CHILD, str(a.megapixels), camera, str(a.repo)],
                             check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    res = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "command": "benchmarks/bench_integrate_memory.py " + " ".join(sys.argv[1:]), "cpu": cpu_info(),
           "target_bytes_per_pixel": 150, "rows": rows}
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
