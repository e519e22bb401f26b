"""How well each image's light intensity is found from the object itself (semi-calibrated).

    .venv/bin/python -m benchmarks.predict.intensity_estimate [--captures DIR ...]
        [--pixels 10000] [--seed 0] [--factor-seed 20261207] [--dequantise half|none|both] [--out FILE]

For each real capture (default: DiLiGenT BALL, 16-bit, and the four 8-bit crops COW,
GOBLET, POT1, POT2 in ``../shared``), read with the project's reader
(:func:`cnnps.io.capture.load_capture`; grey = mean of the linear channels, *not* divided by
the light intensities; saturated observations flagged not valid),
:func:`cnnps.ps.intensity_estimate.estimate_intensities` gets the grey observations of the
mask pixels and the light directions; its intensities are compared with the capture's own
``light_intensities.txt`` (per image, the mean of the three channels): the relative error
``|e_est / e_true - 1|`` after normalising both to mean 1, its mean and max over the
images. Two cases:

- ``as is``: the capture as stored;
- ``rescaled``: every image multiplied by a seeded random factor in 0.5-2x (a phone's
  auto exposure; ``--factor-seed``), the truth multiplied by the same factors.

``--dequantise half`` adds half a code step of the stored type to every observation first
(the crops are the 16-bit originals divided by 256 and truncated, so a stored 8-bit code v
stands for v + 0.5 on average: at their median of 3-12 counts, a 4-15 % offset that is no
scale); ``none`` takes the codes as they are; ``both`` (default) reports each. The
rescaling comes after it (a phone's exposure acts before its quantisation). Also: the
seconds each estimate took, its rounds and whether they converged. Printed as a Markdown
table; the record (harness schema) goes to ``--out`` or
``benchmarks/results/predict/intensity_estimate_<cpu kind>.json``. The network is not run.
Without ``../shared`` it says so and exits 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.harness import Stopwatch, cpu_kind, result_path, write_result
from benchmarks.predict.bf16_agreement import DEFAULT_CAPTURES

FACTOR_SEED = 20261207  # the exposure factors of the "rescaled" case
CASES = ("as_is", "rescaled")


def observations(path: Path) -> dict:
    """The capture's grey observations ``I`` (m, P) float64 (channels averaged, intensities
    not divided out), ``valid`` (m, P) (not saturated), unit ``lights`` (m, 3), ``truth``
    (m,) (the mean of the channel intensities), the stored type's code ``step`` (0 for
    floats), its ``dtype`` and the mask's ``pixels``."""
    from cnnps.io.capture import load_capture, masked_pixels
    from cnnps.io.images import max_code

    cap = load_capture(path)
    m, P = cap.n_images, cap.n_pixels
    I = np.empty((m, P), np.float64)
    valid = np.ones((m, P), bool)
    for k in range(m):
        pix = masked_pixels(cap.images[k], cap.mask, np.ones(3), cap.grey, cap.linearize)
        I[k] = pix.values
        if pix.saturated is not None:
            valid[k] = ~pix.saturated
    top = max_code(cap.images.dtype)
    return {"I": I, "valid": valid, "lights": cap.lights, "truth": cap.intensities.mean(1),
            "step": 0.0 if top is None else 1.0 / top, "dtype": str(cap.images.dtype), "pixels": P}


def relative_errors(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``|est / truth - 1|`` per image after normalising both to mean 1."""
    est, truth = np.asarray(est, np.float64), np.asarray(truth, np.float64)
    return np.abs((est / est.mean()) / (truth / truth.mean()) - 1)


def measure(obs: dict, dequantise: bool, factors: np.ndarray, pixels: int, seed: int) -> dict:
    """Both cases of one capture: errors (%), seconds, rounds and the estimate's diagnostics."""
    from cnnps.ps.intensity_estimate import estimate_intensities

    I = obs["I"] + (0.5 * obs["step"] if dequantise else 0.0)
    out = {}
    for case in CASES:
        f = factors if case == "rescaled" else np.ones(len(I))
        with Stopwatch() as sw:
            est = estimate_intensities(I * f[:, None], obs["lights"], valid=obs["valid"], max_pixels=pixels,
                                       seed=seed)
        err = relative_errors(est.intensities, obs["truth"] * f)
        out[case] = {"mean_error_pct": round(100 * float(err.mean()), 3),
                     "max_error_pct": round(100 * float(err.max()), 3), "worst_image": int(err.argmax()),
                     "seconds": round(sw.seconds, 2), "iterations": est.iterations, "converged": est.converged,
                     "pixels": est.pixels, "residual": round(est.residual, 4), "used": est.used,
                     "shadows": est.shadows, "highlights": est.highlights, "outliers": est.outliers}
    return out


def table(rows: dict) -> str:
    """:func:`main`'s rows as a Markdown table."""
    lines = ["| capture | stored | codes | as is: mean / max % | rescaled: mean / max % | seconds | rounds |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, row in rows.items():
        for mode, r in row["results"].items():
            a, b = r["as_is"], r["rescaled"]
            codes = "+ half a step" if mode == "half" else "as stored"
            lines.append(f"| {name} | {row['dtype']} | {codes} | {a['mean_error_pct']:.2f} / {a['max_error_pct']:.2f} "
                         f"| {b['mean_error_pct']:.2f} / {b['max_error_pct']:.2f} "
                         f"| {a['seconds']:.1f} / {b['seconds']:.1f} | {a['iterations']} / {b['iterations']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", type=Path, nargs="*", default=None)
    ap.add_argument("--pixels", type=int, default=10000, help="estimate_intensities' max_pixels (0: all)")
    ap.add_argument("--seed", type=int, default=0, help="estimate_intensities' pixel-sample seed")
    ap.add_argument("--factor-seed", type=int, default=FACTOR_SEED)
    ap.add_argument("--dequantise", choices=("half", "none", "both"), default="both")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    captures = args.captures or [c for c in DEFAULT_CAPTURES if c.is_dir()]
    if not captures:
        print("no captures (../shared/data absent): nothing to measure")
        return 0
    modes = {"half": ["half"], "none": ["none"], "both": ["none", "half"]}[args.dequantise]
    rows = {}
    for path in captures:
        obs = observations(path)
        factors = np.random.default_rng(args.factor_seed).uniform(0.5, 2.0, len(obs["I"]))
        rows[path.name] = {"dtype": obs["dtype"], "images": len(obs["I"]), "mask_pixels": obs["pixels"],
                           "results": {mode: measure(obs, mode == "half", factors, args.pixels, args.seed)
                                       for mode in modes}}
        print(path.name, rows[path.name]["results"], flush=True)
    means = {mode: {case: round(float(np.mean([r["results"][mode][case]["mean_error_pct"] for r in rows.values()])), 3)
                    for case in CASES} for mode in modes}
    print()
    print(table(rows))
    print(f"\nmean over the captures of the mean error (%): {means}")
    out = args.out or result_path(__spec__.name, cpu_kind())
    write_result(out, __spec__.name, args, {"captures": rows, "mean_error_pct": means}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
