"""A rendered phone-and-lamp capture end to end, against its fully calibrated twin, and what
each shortcut costs on its own.

    .venv/bin/python -m benchmarks.pipeline.phone_capture [--seeds 0 1 2] [--size 128]
        [--lights 40] [--rotations 10] [--mesh procedural:blob:0] [--samples 16] [--table]
        [--work DIR] [--out benchmarks/results/pipeline/phone_capture.json]

Per seed, :func:`cnnps.synth.phone_capture.render_phone_capture` renders the object beside a
chrome ball (8-bit sRGB JPEGs, a random 0.5-2x exposure per shot, sensor noise), then
``cnnps calibrate`` finds the ball in the photos (``--linearize srgb``, no mask) and
``cnnps.predict_folder`` (``linearize="srgb"``, the shipped model, K rotations) runs on five
versions of the same photos, each with the light files in a calibration folder
(``lights_dir``):

- ``twin``: the true directions, intensities and object mask;
- ``ball_lights``: the directions calibrate found, the rest true;
- ``estimated_intensities``: no intensities file (estimated from the object), the rest true;
- ``made_mask``: no mask (made from the photos, the ball left out), the rest true;
- ``phone``: all three shortcuts, what a user with a phone runs;
- ``exif_intensities``: the intensities from each JPEG's EXIF exposure
  (``--intensities exif``: right when the lamp keeps its power and distance), the rest true;
- ``phone_exif``: the ball's directions, the EXIF intensities and the made mask.

``--table``: the object stands on a lit matt table that fills the rest of the frame (the ball
then darker than the table around it; the made mask must leave the table out); its record is
``phone_capture_table.json`` (64 samples: fewer leave fireflies on the dark ball).

Each is scored against the rendered normals on the object's pixels that the made mask
also holds (the same pixels for every version). Reported: per seed and as mean ± spread
(sample standard deviation) over seeds; the directions' error against the truth; the
made mask's IoU; the estimated intensities' relative error (both at mean 1).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result

VERSIONS = {  # name: (directions, intensities, mask): "true" from the twin, or the shortcut
    "twin": ("true", "true", "true"),
    "ball_lights": ("ball", "true", "true"),
    "estimated_intensities": ("true", "estimated", "true"),
    "made_mask": ("true", "true", "made"),
    "phone": ("ball", "estimated", "made"),
    "exif_intensities": ("true", "exif", "true"),
    "phone_exif": ("ball", "exif", "made"),
}


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def version_folders(root: Path, photos: Path, twin: Path, cal: Path, version: str) -> tuple[Path, Path]:
    """(capture folder, lights folder) of ``version`` under ``root``: the photos (named
    ``photos``, as calibrate saw them) and a copy of the calibration folder with the chosen
    light files."""
    from cnnps.io.capture import LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE, MASK_FILE

    directions, intensities, mask = VERSIONS[version]
    capture, lights = root / version / "photos", root / version / "lights"
    shutil.copytree(photos, capture)
    shutil.copytree(cal, lights)
    if directions == "true":
        shutil.copyfile(twin / LIGHT_DIRECTIONS_FILE, lights / LIGHT_DIRECTIONS_FILE)
    if intensities == "true":
        shutil.copyfile(twin / LIGHT_INTENSITIES_FILE, lights / LIGHT_INTENSITIES_FILE)
    if mask == "true":
        shutil.copyfile(twin / MASK_FILE, capture / MASK_FILE)
    return capture, lights


def one_seed(work: Path, seed: int, a) -> dict:
    from cnnps.api.calibration import calibrate, write_calibration
    from cnnps.api.prediction import predict_folder
    from cnnps.io.images import read_mask
    from cnnps.synth.phone_capture import render_phone_capture

    root = work / f"seed-{seed}"
    with Stopwatch() as t_render:
        made = render_phone_capture(root / "capture", mesh=a.mesh, size=a.size, lights=a.lights, seed=seed,
                                    samples=a.samples, table=a.table, threads=a.threads)
    truth = made["truth"]
    cal_dir = root / "cal"
    shutil.rmtree(cal_dir, ignore_errors=True)
    cal = calibrate(made["photos"], linearize="srgb")
    write_calibration(cal, cal_dir)
    L_true = np.asarray(truth["lights"])
    light_err = _angles(cal.directions, L_true)
    gt = np.load(made["twin"] / "normal_gt.npy")
    true_mask = read_mask(made["twin"] / "mask.png")
    runs, outs = {}, {}
    for version in VERSIONS:
        shutil.rmtree(root / "versions" / version, ignore_errors=True)
        capture, lights = version_folders(root / "versions", made["photos"], made["twin"], cal_dir, version)
        out = root / "versions" / version / "out"
        with Stopwatch() as t:
            runs[version] = predict_folder(capture, out, lights_dir=lights, linearize="srgb", rotations=a.rotations,
                                           intensities="exif" if VERSIONS[version][1] == "exif" else "auto",
                                           report=False, progress=False)
        outs[version] = (out, t.seconds)
    made_mask = read_mask(outs["phone"][0] / "mask.png")
    common = true_mask & made_mask
    row: dict = {"seed": seed, "render_s": round(t_render.seconds, 1), "pixels": int(common.sum()),
                 "ball_shadowed_lights": int(np.sum(np.asarray(truth["ball_shadow"]) > 0)),
                 "directions_deg": {"mean": round(float(light_err.mean()), 3), "max": round(float(light_err.max()), 3)},
                 "mask_iou": round(float((true_mask & made_mask).sum() / (true_mask | made_mask).sum()), 4)}
    est = runs["phone"].get("estimated", {}).get("intensities")
    if est is not None:
        e = np.asarray(est["values"]) / np.mean(est["values"])
        e_true = np.asarray(truth["intensities"]).mean(axis=1)
        rel = np.abs(e / (e_true / e_true.mean()) - 1.0)
        row["intensities_pct"] = {"mean": round(100 * float(rel.mean()), 2), "max": round(100 * float(rel.max()), 2),
                                  "converged": est["converged"]}
    row["mean_deg"] = {}
    for version, (out, seconds) in outs.items():
        n = np.load(out / "normal.npy")
        row["mean_deg"][version] = round(float(_angles(n[common], gt[common]).mean()), 3)
    row["seconds"] = {v: round(s, 1) for v, (_, s) in outs.items()}
    print(json.dumps(row), flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--lights", type=int, default=40)
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--mesh", default="procedural:blob:0")
    ap.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel")
    ap.add_argument("--table", action="store_true", help="the object on a lit table")
    ap.add_argument("--threads", type=int, default=0, help="Cycles threads (0: all cores)")
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "bench-phone-capture")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args(argv)
    rows = [one_seed(a.work, seed, a) for seed in a.seeds]
    summary = {}
    for version in VERSIONS:
        v = np.array([r["mean_deg"][version] for r in rows])
        summary[version] = {"mean": round(float(v.mean()), 3), "sd": round(float(v.std(ddof=1)), 3) if len(v) > 1 else None}
    for version in ("phone", "phone_exif"):
        gap = np.array([r["mean_deg"][version] - r["mean_deg"]["twin"] for r in rows])
        summary[f"{version}_minus_twin"] = {"mean": round(float(gap.mean()), 3),
                                            "sd": round(float(gap.std(ddof=1)), 3) if len(gap) > 1 else None}
    print(json.dumps(summary, indent=1))
    write_result(a.out, __spec__.name, vars(a), {"seeds": rows, "summary": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
