"""Does a model tilt normals away from (or toward) the view? BALL against a Lambertian sphere.

    .venv/bin/python -m benchmarks.predict.tilt_bias NAME=WEIGHTS [NAME=WEIGHTS ...]
        [--rotations 10] [--pixels N] [--inputs ball lambert_ball_lights ...] [--out FILE]

For each model (``NAME=WEIGHTS``; ``shipped`` for the shipped file), predicted through
:func:`cnnps.predict` with K rotations in fp32 on three inputs that share DiLiGenT BALL's
mask and ground-truth normals:

- ``ball``: the real capture (``../shared/data/diligent/ballPNG``, 96 images);
- ``lambert_ball_lights``: a Lambertian sphere, ``0.6 * max(n . l, 0)``, under BALL's 96
  lights (all within 44 degrees of the view);
- ``lambert_hemisphere``: the same sphere under 305 lights spread over the hemisphere
  (:func:`cnnps.synth.lights.uniform_lights`: equal area, above 5 degrees of elevation).

Per input: the mean angular error, and the mean of (predicted tilt - true tilt) in bands of
the true tilt (the angle from +z, degrees): positive means the model leans normals away from
the view. A bias that the Lambertian sphere under BALL's lights shows and the hemisphere
does not comes from the light cone; one that only BALL shows, from what real captures hold
that the training data does not. ``--pixels N`` scores a seeded sample of N of BALL's mask
pixels (the same for every model and input; 0 = all), ``--inputs`` a subset of the three
(``lambert_ball_lights`` alone is the v7 study's fast proxy). Results go to
``benchmarks/results/predict/tilt_bias_<cpu kind>.json`` (the harness's record: CPU model,
command, commit). Without ``../shared`` it says so and exits 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.harness import cpu_kind, result_path, write_result
from benchmarks.predict.bf16_agreement import DEFAULT_CAPTURES

BALL = DEFAULT_CAPTURES[0]  # DiLiGenT BALL in ../shared
BANDS = ((0, 20), (20, 40), (40, 55), (55, 70), (70, 90))  # true tilt, degrees
INPUTS = ("ball", "lambert_ball_lights", "lambert_hemisphere")
SAMPLE_SEED = 0  # the pixel sample of --pixels


def sample_mask(mask: np.ndarray, pixels: int, seed: int = SAMPLE_SEED) -> np.ndarray:
    """``mask`` with only a seeded sample of ``pixels`` of its pixels left on (all when
    ``pixels`` is 0 or at least their count): the same sample for the same mask and seed."""
    idx = np.flatnonzero(mask)
    if pixels <= 0 or pixels >= idx.size:
        return mask.copy()
    keep = np.random.default_rng(seed).choice(idx, size=pixels, replace=False)
    out = np.zeros(mask.size, bool)
    out[keep] = True
    return out.reshape(mask.shape)


def tilt_rows(normals: np.ndarray, gt: np.ndarray) -> dict:
    """``{"mean_deg", "tilt_bias_deg": {"a-b": mean (tilt - true tilt)}}`` of (P, 3) unit
    normals against (P, 3) ground truth; a band without pixels is left out."""
    err = np.degrees(np.arccos(np.clip((normals * gt).sum(1), -1.0, 1.0)))
    tn = np.degrees(np.arccos(np.clip(normals[:, 2], -1.0, 1.0)))
    tg = np.degrees(np.arccos(np.clip(gt[:, 2], -1.0, 1.0)))
    bias = {}
    for a, b in BANDS:
        sel = (tg >= a) & (tg < b)
        if sel.any():
            bias[f"{a}-{b}"] = round(float(np.mean(tn[sel] - tg[sel])), 3)
    return {"mean_deg": round(float(err.mean()), 3), "tilt_bias_deg": bias}


def lambert_images(gt: np.ndarray, mask: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """(m, H, W) float32 images of albedo 0.6 Lambertian shading of the (H, W, 3) normals
    ``gt`` under unit ``lights`` (m, 3), zero outside ``mask``."""
    shade = np.clip(np.einsum("hwc,mc->mhw", gt.astype(np.float64), lights), 0.0, None) * 0.6
    return (shade * mask[None]).astype(np.float32)


def main(argv=None) -> int:
    import cnnps
    from cnnps.models.shipped import shipped_model_path
    from cnnps.synth.lights import uniform_lights

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="+", metavar="NAME=WEIGHTS")
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--pixels", type=int, default=0, help="a seeded sample of BALL's mask pixels (0 = all)")
    ap.add_argument("--inputs", nargs="+", choices=INPUTS, default=list(INPUTS))
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if not BALL.is_dir():
        print(f"{BALL}: not here (../shared absent): nothing to measure")
        return 0
    cap = cnnps.load_capture(BALL)
    gt, full, mask = cap.normal_gt, cap.mask, sample_mask(cap.mask, args.pixels)
    ball_lights = cap.lights / np.linalg.norm(cap.lights, axis=1, keepdims=True)
    hemi = uniform_lights(305, min_elevation_deg=5.0)
    inputs = {
        "ball": dict(images=cap.images, lights=cap.lights, intensities=cap.intensities),
        "lambert_ball_lights": dict(images=lambert_images(gt, full, ball_lights), lights=ball_lights),
        "lambert_hemisphere": dict(images=lambert_images(gt, full, hemi), lights=hemi),
    }
    rows = {}
    for item in args.models:
        name, sep, weights = item.partition("=")
        if not sep:
            raise SystemExit(f"{item}: expected NAME=WEIGHTS")
        weights = shipped_model_path() if weights == "shipped" else Path(weights)
        rows[name] = {"weights": str(weights)}
        for what in args.inputs:
            kw = inputs[what]
            p = cnnps.predict(kw["images"], kw["lights"], mask, intensities=kw.get("intensities"), model=weights,
                              rotations=args.rotations, precision="fp32")
            rows[name][what] = tilt_rows(p.normals[mask].astype(np.float64), gt[mask].astype(np.float64))
            print(name, what, rows[name][what], flush=True)
    out = args.out or result_path(__spec__.name, cpu_kind())
    write_result(out, __spec__.name, args, {"models": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
