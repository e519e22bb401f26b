"""Peak memory and time of ``cnnps predict`` against image size (tiled prediction).

Writes a synthetic capture per size itself (a textured Lambertian sphere, 16-bit RGB PNGs,
a disk mask, DiLiGenT layout: filenames.txt, light_directions.txt, light_intensities.txt,
mask.png) into a temporary folder, runs ``cnnps predict`` on it in a subprocess and
records the subprocess's peak resident memory (``os.wait4`` rusage ``ru_maxrss``) and
wall time (Linux starts a child's ``ru_maxrss`` at its parent's peak, so the captures are
written and scored in helper processes, keeping this launcher small; its own peak is
recorded beside each figure as ``launcher_peak_rss_mb``), plus the mean angular error against the analytic normals
(a check that the big run is right, not only small). Results go to
``benchmarks/results/predict/peak_memory.json``.

    # the measurement the README quotes (12 MP: ~5 GB of disk, minutes of CPU)
    .venv/bin/python -m benchmarks.predict.peak_memory --sizes 1,12 --cnn-size 1

    # a quick proof that it works
    .venv/bin/python -m benchmarks.predict.peak_memory --sizes 1 --out /tmp/peak_memory.json

Sizes are megapixels of a 4:3 frame (1 MP = 866 x 1155, 12 MP = 3000 x 4000); the disk
mask covers ~48 % of the frame. ``--method lambertian`` at every size (the least-squares
path streams exactly like the network's), and with ``--cnn-size S`` also the CNN (K=1) at
S megapixels. The claim checked: the peaks at the smallest and largest size differ by
less than 1 GB (``peak_difference_mb``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.harness import ROOT, Stopwatch, result_path, write_result

ALBEDO = np.array([0.85, 0.65, 0.45])


def frame(megapixels: float) -> tuple[int, int]:
    H = int(round(np.sqrt(megapixels * 1e6 * 3 / 4)))
    return H, int(round(H * 4 / 3))


def sphere(H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) float32 normals of a sphere filling a disk of radius 0.45 min(H, W) and its
    mask; row 0 on top (+y)."""
    R = 0.45 * min(H, W)
    y = (H / 2 - (np.arange(H, dtype=np.float32) + 0.5))[:, None] / R
    x = ((np.arange(W, dtype=np.float32) + 0.5) - W / 2)[None, :] / R
    r2 = x * x + y * y
    mask = r2 < 1.0
    n = np.zeros((H, W, 3), np.float32)
    n[..., 0] = np.where(mask, x, 0)
    n[..., 1] = np.where(mask, y, 0)
    n[..., 2] = np.sqrt(np.clip(1.0 - r2, 0, None)) * mask
    return n, mask


def lights(m: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.cos(np.radians(55)), 1.0, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)


def write_capture(root: Path, megapixels: float, m: int) -> dict:
    """A DiLiGenT-layout capture of a textured Lambertian sphere, 16-bit PNG."""
    import cv2

    root.mkdir(parents=True)
    H, W = frame(megapixels)
    normals, mask = sphere(H, W)
    L = lights(m)
    rows = np.arange(H, dtype=np.float32)[:, None]
    cols = np.arange(W, dtype=np.float32)[None, :]
    texture = (0.75 + 0.25 * np.sin(cols / 37.0) * np.cos(rows / 53.0)).astype(np.float32)  # albedo pattern
    names = [f"{j:03d}.png" for j in range(m)]

    def one(j: int) -> None:
        shade = np.maximum(normals @ L[j].astype(np.float32), 0) * texture * 0.9
        img = np.round(shade[..., None] * ALBEDO[::-1].astype(np.float32) * 65535).astype(np.uint16)  # BGR
        if not cv2.imwrite(str(root / names[j]), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write {root / names[j]}")

    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        list(pool.map(one, range(m)))
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", L, fmt="%.9f")
    np.savetxt(root / "light_intensities.txt", np.ones((m, 3)), fmt="%.1f")
    cv2.imwrite(str(root / "mask.png"), mask.astype(np.uint8) * 255)
    return {"H": H, "W": W, "mask_pixels": int(mask.sum()), "images": m,
            "png_bytes": sum((root / n).stat().st_size for n in names)}


def run_predict_rss(capture: Path, out: Path, method: str, rotations: int, tile_pixels: int | None) -> dict:
    """``cnnps predict`` in a child process: its own peak RSS (``os.wait4``) and wall time."""
    cmd = [sys.executable, "-m", "cnnps", "predict", str(capture), "--out", str(out), "--method", method,
           "--no-progress"]
    if method == "cnn":
        cmd += ["--rotations", str(rotations), "--device", "cpu"]
    else:
        cmd += ["--shadow-threshold", "0"]  # attached shadows out: the mean error checks the answers
    if tile_pixels:
        cmd += ["--tile-pixels", str(tile_pixels)]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se:
        with Stopwatch() as sw:
            launcher_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            proc = subprocess.Popen(cmd, env=env, stdout=so, stderr=se, text=True)
            _pid, status, usage = os.wait4(proc.pid, 0)
        wall = sw.seconds
        proc.returncode = os.waitstatus_to_exitcode(status)
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {stderr.strip()[-2000:]}")
    kb = usage.ru_maxrss if sys.platform != "darwin" else usage.ru_maxrss / 1024
    # Linux starts a child's ru_maxrss at its parent's peak (exec keeps the old mm's high-water
    # mark), so the figure is max(this process's peak, the child's): this process stays small
    # (captures are written and scored in helper processes) and its peak is recorded beside it
    launcher_mb = round((launcher_kb if sys.platform != "darwin" else launcher_kb / 1024) / 1024, 1)
    return {"peak_rss_mb": round(kb / 1024, 1), "launcher_peak_rss_mb": launcher_mb, "wall_s": round(wall, 2),
            "summary_line": stdout.strip().splitlines()[-1] if stdout.strip() else "",
            "command": " ".join(["cnnps", *cmd[3:]])}


def mean_error_deg(out: Path, megapixels: float) -> float:
    H, W = frame(megapixels)
    truth, mask = sphere(H, W)
    pred = np.load(out / "normal.npy", mmap_mode="r")
    err = []
    for r in range(0, H, 256):  # in bands: the parent's memory is not measured, but be kind
        m = mask[r : r + 256]
        p = np.asarray(pred[r : r + 256][m], np.float64)
        t = truth[r : r + 256][m].astype(np.float64)
        cos = np.clip(np.sum(p * t, axis=1) / np.linalg.norm(p, axis=1) / np.linalg.norm(t, axis=1), -1, 1)
        err.append(np.degrees(np.arccos(cos)))
    return float(np.concatenate(err).mean())


def in_helper(fn, *args):
    """``fn(*args)`` in a fresh (spawned) helper process, so the memory it needs (a 12 MP
    capture's arrays) never raises this process's peak, which the next child inherits."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1,12", help="megapixels, comma-separated (default 1,12)")
    ap.add_argument("--images", type=int, default=96)
    ap.add_argument("--cnn-size", type=float, default=None, help="also run the CNN (K=1) at this many megapixels")
    ap.add_argument("--tile-pixels", type=int, default=None, help="--tile-pixels for cnnps predict (default: its own)")
    ap.add_argument("--workdir", type=Path, default=None, help="where the captures go (default: a temporary folder)")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()

    sizes = [float(s) for s in args.sizes.split(",") if s.strip()]
    work = Path(tempfile.mkdtemp(prefix="cnnps-bench-mem-", dir=args.workdir))
    runs = []
    try:
        jobs = [(s, "lambertian") for s in sizes]
        if args.cnn_size:
            jobs.append((args.cnn_size, "cnn"))
        captures: dict[float, tuple[Path, dict]] = {}
        for size, method in jobs:
            if size not in captures:
                cap = work / f"cap_{size:g}mp"
                with Stopwatch() as sw:
                    info = in_helper(write_capture, cap, size, args.images)
                info["write_s"] = round(sw.seconds, 1)
                captures[size] = (cap, info)
                print(f"{size:g} MP: wrote {args.images} images {info['W']}x{info['H']} "
                      f"({info['png_bytes'] / 2**30:.2f} GiB) in {info['write_s']} s", flush=True)
            cap, info = captures[size]
            out = work / f"out_{size:g}mp_{method}"
            row = {"megapixels": size, "method": method, "rotations": 1 if method == "cnn" else None, **info}
            row.update(run_predict_rss(cap, out, method, 1, args.tile_pixels))
            pred = json.loads((out / "prediction.json").read_text())
            row.update(
                mask_pixels=pred["pixels"],
                pixel_stack=pred["pixel_stack"],
                tile_pixels=pred["tile_pixels"],
                stack_bytes=pred["pixels"] * pred["n_images"] * 4,
                predict_seconds=pred["seconds"],
                read_seconds=pred["load_seconds"],
                mean_error_deg=round(in_helper(mean_error_deg, out, size), 4),
            )
            runs.append(row)
            print(f"{size:g} MP {method}: peak RSS {row['peak_rss_mb']:.0f} MB, wall {row['wall_s']:.1f} s "
                  f"(read {row['read_seconds']:.1f} s), stack {row['stack_bytes'] / 2**30:.2f} GiB on "
                  f"{row['pixel_stack']}, mean error {row['mean_error_deg']:.3f} deg", flush=True)
            shutil.rmtree(out)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    lam = [r for r in runs if r["method"] == "lambertian"]
    result = {
        "what": "cnnps predict peak memory vs image size (pixel stack + tiles)",
        "images": args.images,
        "load_average_after": os.getloadavg(),
        "runs": runs,
    }
    if len(lam) >= 2:
        small, big = min(lam, key=lambda r: r["megapixels"]), max(lam, key=lambda r: r["megapixels"])
        diff = big["peak_rss_mb"] - small["peak_rss_mb"]
        result["peak_difference_mb"] = round(diff, 1)
        result["peak_difference_under_1gb"] = bool(diff < 1000)
        result["whole_stack_would_need_mb"] = round(big["mask_pixels"] * args.images * 4 / 1e6, 1)
        print(f"peak difference {small['megapixels']:g} -> {big['megapixels']:g} MP: {diff:.0f} MB "
              f"(the whole masked stack would be {result['whole_stack_would_need_mb']:.0f} MB)")
    write_result(args.out, __spec__.name, args, result)


if __name__ == "__main__":
    main()
