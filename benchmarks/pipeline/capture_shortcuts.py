"""What the phone-and-lamp shortcuts cost against the fully calibrated capture: the mask made
from the photos, the light intensities estimated from the object, and each image's exposure
changed 0.5-2x as a phone's auto exposure does.

    .venv/bin/python -m benchmarks.pipeline.capture_shortcuts [--rotations 10] [--seed 0]
        [--method cnn] [--captures ballPNG cowPNG ...] [--without mask intensities] [--rescale]
        [--rescaled-twin] [--shared ../shared] [--out benchmarks/results/pipeline/capture_shortcuts.json]

For each real capture with ground truth (DiLiGenT BALL and the four 8-bit crops under
``../shared/data``): ``cnnps.predict_folder`` on the capture as it is (``calibrated``), then
on a copy that lacks the files of ``--without`` (``shortcuts``: ``mask.png``, made from the
photos; ``light_intensities.txt``, estimated from the object), with ``--rescale`` every
image of the copy multiplied by a seeded factor log-uniform in 0.5-2 (rounded and clipped
to the format's range; a copy that keeps its intensities file keeps it unchanged, as a
capture whose exposure was not locked does). ``--rescaled-twin`` adds a third run
(``rescaled_twin``): the same rescaled photos with their true intensities times the factors
and the true mask, so what rescaling and re-quantising the photos cost alone is apart from
what the shortcuts cost. Reported per capture: the made mask's IoU
with the true one; the estimated intensities' relative error against the true ones times
the factors (``|e / e_true - 1|`` with both at mean 1; mean and max over the images); the
mean angular error of each run on the true mask's pixels the made mask also holds, and the
share of true-mask pixels it leaves out; and the times. The dev-real mean (the crops, BALL
beside) of each run closes the table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result
from cnnps.io.capture import LIGHT_INTENSITIES_FILE, MASK_FILE

CAPTURES = {"ballPNG": "diligent", "cowPNG": "diligent-crop8", "gobletPNG": "diligent-crop8",
            "pot1PNG": "diligent-crop8", "pot2PNG": "diligent-crop8"}
REFERENCE = "ballPNG"  # beside the dev-real mean, not in it
FACTORS = (0.5, 2.0)  # a phone's auto exposure: each image x a factor log-uniform in this range


WITHOUT = {"mask": MASK_FILE, "intensities": LIGHT_INTENSITIES_FILE}  # what the copy may lack


def phone_copy(src: Path, dst: Path, seed: int, rescale: bool, without=("mask",)) -> np.ndarray:
    """``src`` copied to ``dst`` without the files of ``without`` (:data:`WITHOUT`'s keys),
    with ``rescale`` each image multiplied by its factor (rounded, clipped); returns the
    factors, light order (ones without)."""
    from cnnps.io.capture import read_filenames
    from cnnps.io.images import read_image_raw, write_png

    shutil.copytree(src, dst)
    for kind in without:
        (dst / WITHOUT[kind]).unlink()
    names = read_filenames(dst)
    rng = np.random.default_rng(seed)
    factors = np.exp(rng.uniform(np.log(FACTORS[0]), np.log(FACTORS[1]), len(names)))
    if not rescale:
        return np.ones(len(names))
    for name, f in zip(names, factors):
        raw = read_image_raw(dst / name)
        top = np.iinfo(raw.dtype).max
        write_png(dst / name, np.clip(np.round(raw.astype(np.float64) * f), 0, top).astype(raw.dtype))
    return factors


def angular_mean(normal: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    dot = np.clip(np.sum(normal[where] * truth[where], axis=1), -1.0, 1.0)
    return float(np.degrees(np.arccos(dot)).mean())


def relative_errors(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``|est / truth - 1|`` per image after normalising both to mean 1."""
    est, truth = np.asarray(est, np.float64), np.asarray(truth, np.float64)
    return np.abs((est / est.mean()) / (truth / truth.mean()) - 1)


def one_capture(name: str, src: Path, work: Path, options: dict, seed: int, rescale: bool,
                without=("mask",), rescaled_twin: bool = False) -> dict:
    from cnnps.api.prediction import predict_folder
    from cnnps.io.capture.files import read_light_intensities, read_normal_gt
    from cnnps.io.images import read_mask

    truth_mask = read_mask(src / "mask.png")
    normal_gt = read_normal_gt(src, truth_mask.shape)
    row: dict = {"capture": name}
    clock = Stopwatch()
    with clock:
        predict_folder(src, work / f"{name}-calibrated", report=False, progress=False, **options)
    row["calibrated_s"] = round(clock.seconds, 1)
    factors = phone_copy(src, work / f"{name}-phone", seed, rescale, without)
    clock = Stopwatch()
    with clock:
        made = predict_folder(work / f"{name}-phone", work / f"{name}-shortcuts", report=False, progress=False,
                              **options)
    row["shortcuts_s"] = round(clock.seconds, 1)
    if rescale and rescaled_twin:  # the same rescaled photos, told their true intensities and mask
        from cnnps.io.capture.files import write_light_intensities

        phone_copy(src, work / f"{name}-rescaled", seed, rescale, without=())
        write_light_intensities(work / f"{name}-rescaled", read_light_intensities(src, len(factors)) * factors[:, None])
        clock = Stopwatch()
        with clock:
            predict_folder(work / f"{name}-rescaled", work / f"{name}-rescaled-twin", report=False, progress=False,
                           **options)
        row["rescaled_twin_s"] = round(clock.seconds, 1)
    mask = read_mask(work / f"{name}-shortcuts" / MASK_FILE) if "mask" in without else truth_mask
    row["mask_iou"] = round(float((mask & truth_mask).sum() / (mask | truth_mask).sum()), 4)
    if "intensities" in without:
        truth = read_light_intensities(src, len(factors)).mean(axis=1) * factors
        err = relative_errors(np.array(made["estimated"]["intensities"]["values"]), truth)
        row["intensity_error_pct"] = {"mean": round(100 * float(err.mean()), 3),
                                      "max": round(100 * float(err.max()), 3)}
    if normal_gt is not None:
        has_gt = truth_mask & (np.linalg.norm(normal_gt, axis=-1) > 0.5)
        both = has_gt & mask
        for run in ("calibrated", "shortcuts") + (("rescaled-twin",) if "rescaled_twin_s" in row else ()):
            normal = np.load(work / f"{name}-{run}" / "normal.npy")
            row[f"{run.replace('-', '_')}_deg"] = round(angular_mean(normal, normal_gt, both), 3)
        row["true_pixels_left_out"] = round(float((has_gt & ~mask).sum() / has_gt.sum()), 4)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--method", default="cnn")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rescale", action="store_true", help="change each image's exposure 0.5-2x in the copy")
    ap.add_argument("--rescaled-twin", action="store_true",
                    help="with --rescale, also the rescaled copy told its true intensities (times the factors) and mask")
    ap.add_argument("--captures", nargs="+", default=list(CAPTURES), choices=list(CAPTURES))
    ap.add_argument("--without", nargs="+", default=list(WITHOUT), choices=list(WITHOUT),
                    help="what the copy lacks (made from the photos)")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args(argv)
    data = a.shared / "data"
    present = [n for n in a.captures if (data / CAPTURES[n] / n).is_dir()]
    if not present:
        print(f"{data}: none of the captures is here; nothing to measure", file=sys.stderr)
        return 0
    options = {"method": a.method, **({"rotations": a.rotations} if a.method == "cnn" else {})}
    rows = []
    with tempfile.TemporaryDirectory(prefix="cnnps-shortcuts-") as tmp:
        for i, name in enumerate(present):
            rows.append(one_capture(name, data / CAPTURES[name] / name, Path(tmp), options, a.seed + i, a.rescale,
                                    a.without, a.rescaled_twin))
            print(json.dumps(rows[-1]), flush=True)
    crops = [r for r in rows if r["capture"] != REFERENCE and "calibrated_deg" in r]
    runs = ("calibrated", "shortcuts") + (("rescaled_twin",) if any("rescaled_twin_deg" in r for r in crops) else ())
    summary = {run: round(float(np.mean([r[f"{run}_deg"] for r in crops])), 3) if crops else None for run in runs}
    print("| capture | mask IoU | intensities: mean / max error % | calibrated deg | shortcuts deg "
          "| true pixels left out |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        ie = r.get("intensity_error_pct")
        ie = "" if ie is None else f"{ie['mean']:.2f} / {ie['max']:.2f}"
        print(f"| {r['capture']} | {r['mask_iou']:.4f} | {ie} "
              f"| {r.get('calibrated_deg')} | {r.get('shortcuts_deg')} | {r.get('true_pixels_left_out', 0):.2%} |")
    print("dev-real (the crops' mean): " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    write_result(a.out, __spec__.name, vars(a), {"captures": rows, "dev_real": summary})
    print(f"(saved {a.out})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
