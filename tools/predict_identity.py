"""Fingerprints of ``cnnps predict`` and ``cnnps.predict`` outputs, to prove a change of
code leaves the normals bit for bit as they were.

Run it once on the code before a change and once after, on the same machine, then compare::

    .venv/bin/python tools/predict_identity.py make-captures /tmp/identity/captures
    PYTHONPATH=<old checkout> .venv/bin/python tools/predict_identity.py run /tmp/identity/captures --out before.json
    .venv/bin/python tools/predict_identity.py run /tmp/identity/captures --out after.json
    .venv/bin/python tools/predict_identity.py compare before.json after.json

``make-captures`` writes two synthetic capture folders (seeded, numpy only): a glossy
sphere under directional lights through a wide pinhole lens (``perspective``) and the same
sphere under near point lights (``point``). ``run`` predicts BALL, the fossil (from
``../shared``, skipped when absent) and the two synthetic captures with the command line,
both methods (the network and least squares), and the two synthetic ones with
:func:`cnnps.predict` as well, and records the SHA-256 of every ``normal.npy`` (and
``depth.npy``) and of the returned arrays. ``compare`` exits 1 on any difference.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REAL = {"ball": SHARED / "diligent" / "ballPNG", "fossil": SHARED / "captures" / "fossil"}
ROTATIONS = {"ball": 10, "fossil": 1, "perspective": 10, "point": 4}  # the fossil's 307k pixels: K=1


def _sphere(K: np.ndarray, size: int, centre: np.ndarray, radius: float):
    """Mask (size, size), unit normals (P, 3) and surface points (P, 3) of a sphere seen
    through the pinhole K (x right, y up, z toward the camera; row 0 on top)."""
    rows, cols = (a.ravel().astype(float) for a in np.mgrid[0:size, 0:size])
    d = np.stack([(cols - K[0, 2]) / K[0, 0], -(rows - K[1, 2]) / K[1, 1], -np.ones_like(rows)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d @ centre
    disc = b**2 - (centre @ centre - radius**2)
    hit = disc > 0
    X = d[hit] * (b[hit] - np.sqrt(disc[hit]))[:, None]
    return hit.reshape(size, size), (X - centre) / radius, X


def _shade(n, lights, views, rng):
    """(m, P) Lambertian + Blinn-Phong values of normals n (P, 3) under per-pixel lights
    (P, m, 3) or shared lights (m, 3), seen from views (P, 3)."""
    L = np.broadcast_to(lights, (n.shape[0],) + lights.shape[-2:]) if lights.ndim == 2 else lights
    ndl = np.einsum("pk,pmk->pm", n, L)
    h = L + views[:, None, :]
    h /= np.linalg.norm(h, axis=2, keepdims=True)
    spec = np.clip(np.einsum("pk,pmk->pm", n, h), 0, None) ** 40
    albedo = rng.uniform(0.4, 0.8, n.shape[0])[:, None]
    return (np.clip(ndl, 0, None) * (albedo + 0.6 * spec)).T


def _write(root: Path, images: np.ndarray, mask: np.ndarray, files: dict[str, np.ndarray]) -> None:
    from cnnps.io.images import write_png

    root.mkdir(parents=True)
    scale = 0.9 / images.max()
    names = []
    for j, img in enumerate(images):
        names.append(f"{j + 1:03d}.png")
        rgb = np.zeros(mask.shape + (3,), np.uint16)
        rgb[mask] = np.round(np.clip(img * scale, 0, 1) * 65535).astype(np.uint16)[:, None]
        write_png(root / names[-1], rgb)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    for name, values in files.items():
        np.savetxt(root / name, values)
    write_png(root / "mask.png", (mask * 255).astype(np.uint8))


def make_captures(out: Path, size: int = 72, m: int = 48) -> None:
    rng = np.random.default_rng(20261127)
    fov = 50.0
    f = size / 2 / np.tan(np.radians(fov / 2))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    centre = np.array([0.05, -0.03, -1.0 / np.sin(np.radians(fov / 2 * 0.8))])
    mask, n, X = _sphere(K, size, centre, 1.0)
    views = -X / np.linalg.norm(X, axis=1, keepdims=True)
    th = np.arccos(rng.uniform(0.35, 1.0, m))
    ph = rng.uniform(0, 2 * np.pi, m)
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    _write(out / "perspective", _shade(n, dirs, views, rng), mask,
           {"light_directions.txt": dirs, "light_intensities.txt": np.ones((m, 3)), "intrinsics.txt": K})
    pos = centre + 2.5 * dirs
    to_light = pos[None, :, :] - X[:, None, :]
    r2 = np.sum(to_light**2, axis=2)
    per_pixel = to_light / np.sqrt(r2)[..., None]
    _write(out / "point", _shade(n, per_pixel, views, rng) / r2.T * 6.25, mask,
           {"light_positions.txt": pos, "light_intensities.txt": np.ones((m, 3)), "intrinsics.txt": K})


def _sha(path_or_array) -> str:
    data = np.load(path_or_array) if isinstance(path_or_array, Path) else path_or_array
    data = np.ascontiguousarray(data)
    return hashlib.sha256(data.tobytes() + str((data.dtype, data.shape)).encode()).hexdigest()


def _cli(capture: Path, out: Path, method: str, rotations: int, depth: bool) -> dict:
    cmd = [sys.executable, "-m", "cnnps", "predict", str(capture), "--out", str(out), "--method", method,
           "--precision", "fp32", "--device", "cpu", "--no-progress"]
    if method == "cnn":
        cmd += ["--rotations", str(rotations)]
    if depth:
        cmd += ["--depth"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    row = {"normal": _sha(out / "normal.npy")}
    if (out / "depth.npy").is_file():
        row["depth"] = _sha(out / "depth.npy")
    record = json.loads((out / "prediction.json").read_text())
    row["seconds"] = record.get("seconds")
    return row


def _api(capture: Path, method: str, rotations: int) -> dict:
    import cnnps
    from cnnps.io.images import read_image_raw, read_mask

    names = (capture / "filenames.txt").read_text().split()
    images = np.stack([read_image_raw(capture / n) for n in names])
    mask = read_mask(capture / "mask.png")
    K = np.loadtxt(capture / "intrinsics.txt")
    kw = {"method": method, "precision": "fp32", "device": "cpu", "intrinsics": K}
    if method == "cnn":
        kw["rotations"] = rotations
    if (capture / "light_positions.txt").is_file():
        res = cnnps.predict(images, None, mask, light_positions=np.loadtxt(capture / "light_positions.txt"), **kw)
    else:
        res = cnnps.predict(images, np.loadtxt(capture / "light_directions.txt"), mask, **kw)
    row = {"normal": _sha(res.normals)}
    if res.depth is not None:
        row["depth"] = _sha(res.depth)
    return row


def run(captures: Path, out_json: Path, only: list[str] | None) -> None:
    folders = {**{k: v for k, v in REAL.items() if v.is_dir()},
               "perspective": captures / "perspective", "point": captures / "point"}
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder in folders.items():
            if only and name not in only:
                continue
            for method in ("cnn", "lambertian"):
                key = f"cli/{name}/{method}"
                rows[key] = _cli(folder, Path(tmp) / key.replace("/", "_"), method, ROTATIONS[name], name == "point")
                print(key, rows[key], flush=True)
                if name in ("perspective", "point"):
                    key = f"api/{name}/{method}"
                    rows[key] = _api(folder, method, ROTATIONS[name])
                    print(key, rows[key], flush=True)
    import cnnps

    out_json.write_text(json.dumps({"cnnps": str(Path(cnnps.__file__).parent), "rotations": ROTATIONS,
                                    "outputs": rows}, indent=2) + "\n")


def compare(a: Path, b: Path) -> int:
    ra, rb = (json.loads(p.read_text())["outputs"] for p in (a, b))
    bad = 0
    for key in sorted(set(ra) | set(rb)):
        x, y = ra.get(key), rb.get(key)
        same = x is not None and y is not None and all(x.get(f) == y.get(f) for f in ("normal", "depth"))
        bad += not same
        print(f"{'identical' if same else 'DIFFERENT'}  {key}")
    print(f"{len(set(ra) | set(rb)) - bad} identical, {bad} different")
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    mk = sub.add_parser("make-captures")
    mk.add_argument("out", type=Path)
    rn = sub.add_parser("run")
    rn.add_argument("captures", type=Path)
    rn.add_argument("--out", type=Path, required=True)
    rn.add_argument("--only", nargs="+", choices=["ball", "fossil", "perspective", "point"])
    cp = sub.add_parser("compare")
    cp.add_argument("a", type=Path)
    cp.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "make-captures":
        make_captures(args.out)
    elif args.cmd == "run":
        run(args.captures, args.out, args.only)
    else:
        return compare(args.a, args.b)
    return 0


if __name__ == "__main__":
    sys.exit(main())
