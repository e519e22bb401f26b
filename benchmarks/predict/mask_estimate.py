"""The object mask estimated from the photos against DiLiGenT's masks, and on the fossil.

    .venv/bin/python -m benchmarks.predict.mask_estimate [--captures DIR ...] [--images K ...]
        [--seeds 4] [--png-dir /tmp/mask_estimate] [--out FILE]

For each capture (default: DiLiGenT BALL and the four 8-bit crops in ``../shared``, then
the fossil capture), loaded with :func:`cnnps.load_capture` (its grey images,
intensity-normalised, and the saturation flags ``cnnps predict`` uses),
:func:`cnnps.ps.mask_estimate.estimate_mask` runs on all the images and its mask is set
against the folder's ``mask.png``: IoU, false-positive and false-negative pixels, the
largest false-positive region (and the IoU with it left out: what one region of the
object that the true mask leaves out, such as GOBLET's inner wall, costs), the share of
the frame, the estimate's diagnostics and its time. The fossil has no ground truth (its
``mask.png`` is nearly the whole frame): its numbers say what the estimate does, not how
right it is. ``--images K``: also K-image subsets (:func:`cnnps.io.capture.subset_drop`,
seeds 0..``--seeds``-1), min and mean IoU. ``--png-dir``: per capture, the estimated mask
and an overlay (grey: the 90th-percentile image; red: false positive, blue: false
negative). Results: ``benchmarks/results/predict/mask_estimate_<cpu kind>.json``; a
Markdown table on stdout. Without ``../shared`` it says so and exits 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.harness import Stopwatch, cpu_kind, result_path, write_result
from benchmarks.predict.bf16_agreement import DEFAULT_CAPTURES, SHARED

FOSSIL = SHARED / "captures" / "fossil"


def compare(est: np.ndarray, truth: np.ndarray) -> dict:
    """IoU, false positives and negatives of the (H, W) bool ``est`` against ``truth``;
    the largest 8-connected false-positive region and the IoU with it left out."""
    from scipy import ndimage as ndi

    fp, fn = est & ~truth, ~est & truth
    labels, n = ndi.label(fp, structure=np.ones((3, 3), bool))
    big = np.bincount(labels.ravel())[1:].max() if n else 0
    union = (est | truth).sum()
    return {"iou": round(float((est & truth).sum() / union), 4), "false_positive": int(fp.sum()),
            "false_negative": int(fn.sum()), "largest_fp_region": int(big),
            "iou_without_largest_fp_region": round(float((est & truth).sum() / (union - big)), 4),
            "true_pixels": int(truth.sum()), "fraction": round(float(est.mean()), 4),
            "true_fraction": round(float(truth.mean()), 4)}


def load(capture: Path):
    """(m, H, W) float32 grey images, (m, H, W) saturation flags (or None), the mask."""
    import cnnps
    from cnnps.io.capture.pixels import saturation_code

    cap = cnnps.load_capture(capture)
    level = saturation_code(cap.images.dtype)
    saturated = None if level is None else (cap.images >= level).any(axis=-1)
    return cap.grey_images(), saturated, cap.mask


def save_pngs(folder: Path, name: str, images: np.ndarray, est: np.ndarray, truth: np.ndarray) -> None:
    from skimage.io import imsave

    folder.mkdir(parents=True, exist_ok=True)
    q = np.log(np.maximum(np.quantile(images, 0.9, axis=0), 1e-5))
    lo, hi = np.percentile(q, [1, 99.5])
    grey = np.clip((q - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = np.repeat(0.7 * grey[..., None], 3, axis=-1)
    rgb[est & ~truth] = (1.0, 0.0, 0.0)
    rgb[~est & truth] = (0.0, 0.4, 1.0)
    imsave(folder / f"{name}_estimate.png", (est * 255).astype(np.uint8), check_contrast=False)
    imsave(folder / f"{name}_overlay.png", (np.concatenate([np.repeat(grey[..., None], 3, -1), rgb], 1) * 255)
           .astype(np.uint8), check_contrast=False)


def subsets(capture: Path, images, saturated, truth, k: int, seeds: int) -> dict:
    from cnnps.io.capture import subset_drop
    from cnnps.ps.mask_estimate import estimate_mask

    ious = []
    for seed in range(seeds):
        keep = np.setdiff1d(np.arange(len(images)), subset_drop(capture, k, seed))
        est = estimate_mask(images[keep], None if saturated is None else saturated[keep])
        ious.append(compare(est.mask, truth)["iou"])
    return {"images": k, "seeds": seeds, "iou_min": min(ious), "iou_mean": round(float(np.mean(ious)), 4),
            "iou": ious}


def measure(capture: Path, args) -> dict:
    from cnnps.ps.mask_estimate import estimate_mask

    images, saturated, truth = load(capture)
    with Stopwatch() as sw:
        est = estimate_mask(images, saturated, source=capture)
    row = {"images": len(images), "shape": list(truth.shape), **compare(est.mask, truth),
           "seconds": round(sw.seconds, 2), "threshold": est.threshold, "components": est.components,
           "dropped": est.dropped, "holes_filled": est.holes_filled, "holes_open": est.holes_open,
           "ground_truth": capture != FOSSIL}
    row["subsets"] = [subsets(capture, images, saturated, truth, k, args.seeds) for k in args.images]
    if args.png_dir:
        save_pngs(args.png_dir, capture.name, images, est.mask, truth)
    return row


def table(rows: dict) -> str:
    head = ("| capture | images | IoU | false pos. | false neg. | largest FP region | IoU without it "
            "| frame share (true) | s |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in rows.items():
        iou = f"{r['iou']:.4f}" if r["ground_truth"] else f"({r['iou']:.4f} vs its mask.png)"
        lines.append(f"| {name} | {r['images']} | {iou} | {r['false_positive']} | {r['false_negative']} | "
                     f"{r['largest_fp_region']} | {r['iou_without_largest_fp_region']:.4f} | "
                     f"{r['fraction']:.3f} ({r['true_fraction']:.3f}) | {r['seconds']:.2f} |")
        for s in r["subsets"]:
            lines.append(f"| {name}, {s['images']} images x {s['seeds']} seeds | {s['images']} | "
                         f"min {s['iou_min']:.4f}, mean {s['iou_mean']:.4f} | | | | | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", type=Path, default=None)
    ap.add_argument("--images", nargs="*", type=int, default=[], help="also K-image subsets (each K)")
    ap.add_argument("--seeds", type=int, default=4, help="subsets per K")
    ap.add_argument("--png-dir", type=Path, default=None, help="write the masks and overlays here")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    captures = args.captures or [c for c in [*DEFAULT_CAPTURES, FOSSIL] if c.is_dir()]
    if not captures:
        print(f"{SHARED}: not here (../shared absent): nothing to measure")
        return 0
    rows = {}
    for capture in captures:
        rows[capture.name] = measure(capture, args)
        print(capture.name, {k: v for k, v in rows[capture.name].items() if k != "subsets"}, flush=True)
    print(table(rows))
    out = args.out or result_path(__spec__.name, cpu_kind())
    write_result(out, __spec__.name, args, {"captures": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
