"""Normal integration (`cnnps integrate`): speed on a 1-megapixel mask, accuracy on
analytic height fields.

    .venv/bin/python benchmarks/bench_integrate.py [--megapixels 1.0] [--repeat 3] [--discontinuities]
                                                   [--compare-direct] [--out benchmarks/results/integrate.json]

Speed: a Gaussian bump on a tilted plane over an elliptical mask with two holes and a
notch holding ``--megapixels`` million pixels; wall time of
``cnnps.ps.integrate.integrate`` (best and median of ``--repeat``) and of one whole
``write_surface_outputs`` (integration + depth.npy/png + surface.ply).
``--discontinuities`` also times one robust (``discontinuities=True``) integration;
``--compare-direct`` also times a sparse direct solve (SuperLU, minimum-degree ordering)
of the same system, for reference (slow and memory-hungry at 1 MP).

Accuracy: RMS height error after removing the mean offset, as a fraction of the true
height range, for a sphere cap, a Gaussian bump + tilt and a sinusoid on a 240 x 320
mask with holes and a notch (normals are exact, so the errors are the discretisation's);
and for a surface with a depth jump ending inside the mask, with and without
``discontinuities=True``, the fraction of neighbour pairs away from the jump whose
height difference is off by more than 0.05 px (the distortion least squares spreads).

The machine may be shared: the load average before and after is recorded.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_info  # noqa: E402
from cnnps.infra.atomic import write_text  # noqa: E402
from cnnps.io.surface import write_surface_outputs  # noqa: E402
from cnnps.ps.grid_poisson import MaskGraph  # noqa: E402
from cnnps.ps.integrate import gradients, integrate  # noqa: E402
from tests.support.surfaces import (  # noqa: E402
    analytic_fields,
    distorted_fraction,
    field_normals,
    holey_mask,
    rel_rms,
    step_field,
)


def accuracy(H: int = 240, W: int = 320) -> dict:
    mask = holey_mask(H, W)
    out = {"size": [H, W], "pixels": int(mask.sum())}
    for name, fn in analytic_fields(H, W).items():
        z, n = field_normals(fn, H, W)
        res = integrate(n, mask)
        out[name] = {"rel_rms": rel_rms(res.depth, z, mask), "depth_range": float(np.ptp(z[mask])),
                     "cg_iterations": res.iterations}
    z, n = field_normals(step_field(H, W), H, W)
    out["step"] = {
        "least_squares_distorted": distorted_fraction(integrate(n, mask).depth, z, n, mask),
        "discontinuities_distorted": distorted_fraction(integrate(n, mask, discontinuities=True).depth, z, n, mask),
        "least_squares_rel_rms": rel_rms(integrate(n, mask).depth, z, mask),
        "discontinuities_rel_rms": rel_rms(integrate(n, mask, discontinuities=True).depth, z, mask),
    }
    return out


def direct_seconds(n: np.ndarray, mask: np.ndarray) -> float:
    import scipy.sparse.linalg as spla
    from scipy import ndimage

    t0 = time.perf_counter()
    p, q, conf, _ = gradients(n, mask)
    graph = MaskGraph.of_mask(mask)
    labels = ndimage.label(mask)[0][mask]
    wr = np.minimum(conf, np.r_[conf[1:], 0.0])
    wd = np.minimum(conf, conf[graph.below])
    weighted = graph.with_weights(wr, wd, np.unique(labels, return_index=True)[1])
    gh = 0.5 * (p + np.r_[p[1:], 0.0])
    gv = -0.5 * (q + q[graph.below])
    rhs = weighted.transpose_differences(weighted.wr * gh, weighted.wd * gv)
    spla.splu(weighted.to_sparse(), permc_spec="MMD_AT_PLUS_A").solve(rhs)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--megapixels", type=float, default=1.0, help="mask pixels, in millions")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--compare-direct", action="store_true", help="also time SuperLU on the same system")
    ap.add_argument("--discontinuities", action="store_true", help="also time one integrate(discontinuities=True)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "integrate.json")
    args = ap.parse_args()

    load_before = os.getloadavg()
    # size the frame so the holey ellipse holds about the requested number of pixels
    H = round(float(np.sqrt(args.megapixels * 1e6 / 0.645 / 1.25)))
    W = round(1.25 * H)
    mask = holey_mask(H, W)
    z, n = field_normals(analytic_fields(H, W)["gauss_tilt"], H, W)
    times, res = [], None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = integrate(n, mask)
        times.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        report = write_surface_outputs(Path(tmp), n, mask)
        t_all = time.perf_counter() - t0
        sizes = {f.name: f.stat().st_size for f in Path(tmp).iterdir()}
    speed = {
        "size": [H, W],
        "pixels": int(mask.sum()),
        "integrate_best_s": round(min(times), 3),
        "integrate_median_s": round(float(np.median(times)), 3),
        "cg_iterations": res.iterations,
        "rel_rms": rel_rms(res.depth, z, mask),
        "write_surface_outputs_s": round(t_all, 3),
        "faces": report["faces"],
        "file_bytes": sizes,
    }
    if args.discontinuities:
        t0 = time.perf_counter()
        robust = integrate(n, mask, discontinuities=True)
        speed["discontinuities_s"] = round(time.perf_counter() - t0, 3)
        speed["discontinuities_cg_iterations"] = robust.iterations
    if args.compare_direct:
        speed["direct_superlu_s"] = round(direct_seconds(n, mask), 3)

    result = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "cpu": cpu_info(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": __import__("scipy").__version__,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "speed": speed,
        "accuracy": accuracy(),
        "note": "wall times on a possibly shared machine, see load averages; accuracy is RMS error / height range",
    }
    write_text(args.out, json.dumps(result, indent=2) + "\n")

    print(f"{result['cpu']['model']}, load {load_before[0]:.2f} -> {result['load_average_after'][0]:.2f}")
    print(f"{speed['pixels']} px: integrate best {speed['integrate_best_s']:.2f} s (median {speed['integrate_median_s']:.2f}), "
          f"CG {speed['cg_iterations']}, rel RMS {speed['rel_rms']:.2e}; all outputs {speed['write_surface_outputs_s']:.2f} s")
    if "discontinuities_s" in speed:
        print(f"discontinuities=True: {speed['discontinuities_s']:.2f} s, CG {speed['discontinuities_cg_iterations']}")
    if "direct_superlu_s" in speed:
        print(f"SuperLU direct solve of the same system: {speed['direct_superlu_s']:.2f} s")
    acc = result["accuracy"]
    for name in analytic_fields(1, 1):
        print(f"{name:12s} rel RMS {acc[name]['rel_rms']:.2e} (range {acc[name]['depth_range']:.1f} px)")
    st = acc["step"]
    print(f"step: pairs distorted by > 0.05 px: least squares {st['least_squares_distorted']:.3f}, "
          f"discontinuities {st['discontinuities_distorted']:.4f} (height rel RMS "
          f"{st['least_squares_rel_rms']:.3f} vs {st['discontinuities_rel_rms']:.3f}: the offset across a cut is unknowable)")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
