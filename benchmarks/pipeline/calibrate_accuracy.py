"""Accuracy of `cnnps calibrate` against the ball's size in pixels, on rendered balls.

    .venv/bin/python -m benchmarks.pipeline.calibrate_accuracy [--radii 20 40 80 160] [--lights 30] [--seeds 2]
        [--object-size 64] [--work DIR] [--threads 0] [--out benchmarks/results/pipeline/calibrate_accuracy.json]

For every seed, one set of jittered hemisphere lights (5 deg jitter, 5 deg minimum
elevation) with random RGB intensities (uniform in [0.7, 1.3] per channel), and for
every ball radius (pixels) a chrome ball and a matte ball rendered under them by
:func:`cnnps.synth.calibration_scenes.render_calibration_set` (Cycles, 1 sample per
pixel: the balls' shading is direct light from a delta sun, exact per sample; the chrome
ball's dim environment has some noise). The chrome ball's material is fixed (roughness
0.2), so its highlight's width in pixels grows with the radius, as a real ball's does.
Each set is calibrated twice, with the rendered ``mask.png`` and without it (the ball
found in the median / maximum image), and compared with the truth:

- light directions: angle to the true direction (mean, median, worst over the lights);
- intensities: both normalised to mean 1, relative error (mean, worst);
- the ball's centre and radius found, in pixels;
- end to end: the object (``procedural:blob:0``, white-ish Lambertian, ``--object-size``
  pixels, 8 samples) predicted by Lambertian least squares (shadow threshold 0.05) with
  the true and with the calibrated lights; the mean angular errors and their difference.

Renders are cached in ``--work`` (default: a temporary folder, removed at the end); the
results go to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import Stopwatch, result_path, write_result


def _angles(a, b) -> np.ndarray:
    a = np.asarray(a, float) / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.asarray(b, float) / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1)))


def _predict_mean(capture: Path, out: Path) -> float:
    from cnnps.api.prediction import predict_folder

    res = predict_folder(capture, out, method="lambertian", shadow_threshold=0.05, progress=False)
    return float(res["mean_deg"])


def _one(work: Path, radius: float, seed: int, L, E, args, object_means: dict) -> dict:
    from cnnps.api.calibration import calibrate
    from cnnps.synth.calibration_scenes import render_calibration_set

    root = work / f"seed{seed}_r{radius:g}"
    parts = ("chrome", "matte", "object") if args.object_size else ("chrome", "matte")
    with Stopwatch() as sw:
        sets = render_calibration_set(root, L, E, size=args.object_size or 32, ball_radius_px=radius, samples=8,
                                      seed=seed, threads=args.threads, progress=False, parts=parts)
    render_s = sw.seconds
    truth = sets["truth"]
    row: dict = {"radius_px": radius, "seed": seed, "image_size": truth["chrome_ball"]["size"],
                 "render_seconds": round(render_s, 2)}
    for masks in (True, False):
        chrome, matte = sets["chrome"], sets["matte"]
        if not masks:
            nm = root / "nomask"
            for part in ("chrome", "matte"):
                shutil.rmtree(nm / part, ignore_errors=True)
                shutil.copytree(sets[part], nm / part)
                (nm / part / "mask.png").unlink()
            chrome, matte = nm / "chrome", nm / "matte"
        with Stopwatch() as sw:
            cal = calibrate(chrome, matte)
        secs = sw.seconds
        err = _angles(cal.directions, L)
        En = E / E.mean()
        rel = np.abs(cal.intensities / En - 1.0)
        tc, tm = truth["chrome_ball"], truth["matte_ball"]
        rec = {
            "direction_error_deg": {"mean": float(err.mean()), "median": float(np.median(err)),
                                    "max": float(err.max())},
            "intensity_error": {"mean": float(rel.mean()), "max": float(rel.max())},
            "chrome_centre_error_px": float(np.hypot(cal.ball.cx - tc["centre_px"][0],
                                                     cal.ball.cy - tc["centre_px"][1])),
            "chrome_radius_error_px": float(cal.ball.radius - radius),
            "matte_centre_error_px": float(np.hypot(cal.matte_ball.cx - tm["centre_px"][0],
                                                    cal.matte_ball.cy - tm["centre_px"][1])),
            "matte_radius_error_px": float(cal.matte_ball.radius - radius),
            "highlight_area_px_median": float(np.median([h.area_px for h in cal.highlights])),
            "calibrate_seconds": round(secs, 3),
        }
        if args.object_size:
            if seed not in object_means:
                object_means[seed] = _predict_mean(sets["object"], root / "pred_true")
            cap = root / ("object_cal_mask" if masks else "object_cal_nomask")
            shutil.rmtree(cap, ignore_errors=True)
            shutil.copytree(sets["object"], cap)
            np.savetxt(cap / "light_directions.txt", cal.directions, fmt="%.9f")
            np.savetxt(cap / "light_intensities.txt", cal.intensities, fmt="%.9g")
            mean_cal = _predict_mean(cap, root / ("pred_cal_mask" if masks else "pred_cal_nomask"))
            rec["object_mean_deg"] = {"true_lights": object_means[seed], "calibrated_lights": mean_cal,
                                      "difference": mean_cal - object_means[seed]}
        row["with_masks" if masks else "without_masks"] = rec
        print(f"r={radius:6g} px seed {seed} {'mask   ' if masks else 'no mask'}: direction error mean "
              f"{err.mean():.3f} median {np.median(err):.3f} max {err.max():.3f} deg, intensities max "
              f"{100 * rel.max():.2f} %, radius error {cal.ball.radius - radius:+.3f} px"
              + (f", object {rec['object_mean_deg']['calibrated_lights']:.3f} vs {object_means[seed]:.3f} deg"
                 if args.object_size else ""), flush=True)
    return row


def _summary(rows: list[dict], radii) -> list[dict]:
    out = []
    for r in radii:
        sel = [x for x in rows if x["radius_px"] == r]
        rec = {"radius_px": r, "image_size": sel[0]["image_size"]}
        for key in ("with_masks", "without_masks"):
            rec[key] = {
                "direction_mean_deg": float(np.mean([x[key]["direction_error_deg"]["mean"] for x in sel])),
                "direction_max_deg": float(np.max([x[key]["direction_error_deg"]["max"] for x in sel])),
                "intensity_max_error": float(np.max([x[key]["intensity_error"]["max"] for x in sel])),
                "radius_error_px_mean_abs": float(np.mean([abs(x[key]["chrome_radius_error_px"]) for x in sel])),
            }
            if "object_mean_deg" in sel[0][key]:
                rec[key]["object_difference_deg_max_abs"] = float(
                    np.max([abs(x[key]["object_mean_deg"]["difference"]) for x in sel]))
        out.append(rec)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radii", type=float, nargs="+", default=[20, 40, 80, 160])
    ap.add_argument("--lights", type=int, default=30)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--object-size", type=int, default=64, help="0: no object, no end-to-end numbers")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--work", default=None, help="render cache (default: a temporary folder, removed)")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()

    from cnnps.synth.blender import blender_version
    from cnnps.synth.calibration_scenes import (
        CHROME_ENVIRONMENT,
        CHROME_ROUGHNESS,
        random_intensities,
    )
    from cnnps.synth.lights import hemisphere_lights

    tmp = None
    if args.work is None:
        tmp = tempfile.mkdtemp(prefix="bench_calibrate_")
        work = Path(tmp)
    else:
        work = Path(args.work)
    whole = Stopwatch().begin()
    rows: list[dict] = []
    object_means: dict = {}
    try:
        for seed in range(args.seeds):
            L = hemisphere_lights(args.lights, jitter_deg=5.0, seed=1000 + seed)
            E = random_intensities(args.lights, seed=2000 + seed, spread=0.3)
            for r in args.radii:
                rows.append(_one(work, r, seed, L, E, args, object_means))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    result = {
        "blender_version": blender_version(),
        "scene": {"chrome_roughness": CHROME_ROUGHNESS, "chrome_environment": CHROME_ENVIRONMENT,
                  "ball_samples": 1, "light_jitter_deg": 5.0, "min_elevation_deg": 5.0,
                  "intensity_spread": 0.3},
        "summary": _summary(rows, args.radii),
        "runs": rows,
        "seconds": round(whole.elapsed, 1),
        "load_average_after": os.getloadavg(),
    }
    print(f"{result['seconds']:.0f} s")
    write_result(args.out, __spec__.name, args, result)


if __name__ == "__main__":
    main()
