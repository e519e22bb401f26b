"""Normal integration (`cnnps integrate`): speed on a 1-megapixel mask, accuracy on
analytic height fields.

    .venv/bin/python -m benchmarks.pipeline.integrate_speed_accuracy [--megapixels 1.0] [--repeat 3]
        [--discontinuities] [--compare-direct] [--out benchmarks/results/pipeline/integrate_speed_accuracy.json]

Speed: a Gaussian bump on a tilted plane over an elliptical mask with two holes and a
notch holding ``--megapixels`` million pixels; wall time of
``cnnps.ps.integrate.integrate`` (best, median and spread of ``--repeat``) and of one whole
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
import os
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import Stopwatch, measure, result_path, write_result
from cnnps.io.surface import write_surface_outputs
from cnnps.ps.grid_poisson import MaskGraph
from cnnps.ps.integrate import gradients, integrate
from tests.support.surfaces import (
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

    sw = Stopwatch().begin()
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
    return sw.elapsed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--megapixels", type=float, default=1.0, help="mask pixels, in millions")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--compare-direct", action="store_true", help="also time SuperLU on the same system")
    ap.add_argument("--discontinuities", action="store_true", help="also time one integrate(discontinuities=True)")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args(argv)

    load_before = os.getloadavg()
    # size the frame so the holey ellipse holds about the requested number of pixels
    H = round(float(np.sqrt(args.megapixels * 1e6 / 0.645 / 1.25)))
    W = round(1.25 * H)
    mask = holey_mask(H, W)
    z, n = field_normals(analytic_fields(H, W)["gauss_tilt"], H, W)
    last = {}

    def run():
        last["result"] = integrate(n, mask)

    times = measure(run, repeat=args.repeat, warmup=0)
    res = last["result"]
    with tempfile.TemporaryDirectory() as tmp:
        with Stopwatch() as sw:
            report = write_surface_outputs(Path(tmp), n, mask)
        t_all = sw.seconds
        sizes = {f.name: f.stat().st_size for f in Path(tmp).iterdir()}
    speed = {
        "size": [H, W],
        "pixels": int(mask.sum()),
        "integrate_best_s": round(times.min, 3),
        "integrate_median_s": round(times.median, 3),
        "integrate_timing": times.as_dict(),
        "cg_iterations": res.iterations,
        "rel_rms": rel_rms(res.depth, z, mask),
        "write_surface_outputs_s": round(t_all, 3),
        "faces": report["faces"],
        "file_bytes": sizes,
    }
    if args.discontinuities:
        with Stopwatch() as sw:
            robust = integrate(n, mask, discontinuities=True)
        speed["discontinuities_s"] = round(sw.seconds, 3)
        speed["discontinuities_cg_iterations"] = robust.iterations
    if args.compare_direct:
        speed["direct_superlu_s"] = round(direct_seconds(n, mask), 3)

    result = {
        "numpy": np.__version__,
        "scipy": __import__("scipy").__version__,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "speed": speed,
        "accuracy": accuracy(),
        "note": "wall times on a possibly shared machine, see load averages; accuracy is RMS error / height range",
    }
    print(f"load {load_before[0]:.2f} -> {result['load_average_after'][0]:.2f}")
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
    write_result(args.out, __spec__.name, args, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
