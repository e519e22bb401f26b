"""Reading a capture folder (the DiLiGenT layout; see docs/ARCHITECTURE.md).

A capture folder holds:

- ``filenames.txt``: one image name a line, in light order;
- ``light_directions.txt``: m lines ``lx ly lz`` (camera frame: x right, y up, z toward
  the camera); normalised to unit length on load;
- ``light_intensities.txt``: m lines ``r g b``; each image channel is divided by it;
- ``mask.png``: non-zero = object;
- optional ground truth ``Normal_gt.mat`` (variable ``Normal_gt``) or ``normal_gt.npy``,
  both H x W x 3.

Images may be 8/16-bit PNG, 16-bit TIFF or float32 EXR (:func:`cnnps.core.images.read_image`).
Each is turned into one grey float32 image: the mean of its intensity-normalised channels
(``grey="mean"``), or their luminance 0.2989 R + 0.5870 G + 0.1140 B
(``grey="luminance"``, MATLAB's rgb2gray weights, used by published least-squares numbers).
A one-channel image is divided by the same combination of the three light intensities.

Every problem is reported as one :class:`cnnps.core.errors.InputError` naming the bad file.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.core.errors import ConfigError, InputError
from cnnps.core.images import read_image, read_mask

GREY_WEIGHTS = {
    "mean": np.array([1.0, 1.0, 1.0]) / 3.0,
    "luminance": np.array([0.2989, 0.5870, 0.1140]),
}

# Benchmark rules: DiLiGenT BEAR's first 20 images are corrupted and dropped by everyone.
DEFAULT_DROPS = {"bearPNG": list(range(20))}

MIN_IMAGES = 3


@dataclass
class Capture:
    """One capture: grey images, lights, mask and optional ground truth."""

    name: str
    root: Path
    filenames: list[str]
    images: np.ndarray  # (m, H, W) float32 grey, intensity-normalised
    lights: np.ndarray  # (m, 3) float64 unit directions
    intensities: np.ndarray  # (m, 3) float64 RGB light intensities (already divided out)
    mask: np.ndarray  # (H, W) bool
    normal_gt: np.ndarray | None = None  # (H, W, 3) float32 or None
    dropped: list[int] = field(default_factory=list)  # indices into the original filenames.txt
    notes: list[str] = field(default_factory=list)  # messages for the user
    grey: str = "mean"

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    @property
    def n_images(self) -> int:
        return len(self.filenames)

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())

    def pixel_intensities(self) -> np.ndarray:
        """(P, m) float32 values of the mask pixels, row-major pixel order."""
        return np.ascontiguousarray(self.images[:, self.mask].T, dtype=np.float32)

    def to_image(self, values: np.ndarray) -> np.ndarray:
        """Scatter (P, C) (or (P,)) per-pixel values into (H, W, C) (or (H, W)), 0 outside."""
        values = np.asarray(values)
        if values.shape[0] != self.n_pixels:
            raise ValueError(f"expected {self.n_pixels} pixel values, got {values.shape[0]}")
        out = np.zeros(self.mask.shape + values.shape[1:], dtype=values.dtype)
        out[self.mask] = values
        return out


# ----------------------------------------------------------------------------- text files


def _read_lines(path: Path) -> list[tuple[int, str]]:
    """Non-empty lines with their 1-based line numbers (comments with '#' allowed)."""
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"unreadable text file ({exc})") from exc
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if line:
            out.append((i, line))
    return out


def _read_vectors(path: Path, what: str) -> tuple[np.ndarray, list[int]]:
    rows = []
    for lineno, line in _read_lines(path):
        parts = line.replace(",", " ").split()
        if len(parts) != 3:
            raise InputError(path, f"line {lineno}: expected 3 numbers ({what}), got {line!r}")
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise InputError(path, f"line {lineno}: not a number in {line!r}") from None
        if not all(np.isfinite(v)):
            raise InputError(path, f"line {lineno}: non-finite value in {line!r}")
        rows.append((lineno, v))
    if not rows:
        raise InputError(path, "file is empty")
    return np.array([v for _, v in rows], dtype=np.float64), [n for n, _ in rows]


def _read_filenames(root: Path) -> list[str]:
    path = root / "filenames.txt"
    names = [line for _, line in _read_lines(path)]
    if not names:
        raise InputError(path, "file is empty")
    return names


def _read_lights(root: Path, m: int) -> tuple[np.ndarray, np.ndarray]:
    dpath = root / "light_directions.txt"
    ipath = root / "light_intensities.txt"
    dirs, dlines = _read_vectors(dpath, "lx ly lz")
    if len(dirs) != m:
        raise InputError(dpath, f"has {len(dirs)} light directions but filenames.txt lists {m} images")
    norms = np.linalg.norm(dirs, axis=1)
    bad = np.flatnonzero(norms < 1e-8)
    if bad.size:
        raise InputError(dpath, f"line {dlines[bad[0]]}: zero-length light direction")
    dirs = dirs / norms[:, None]

    ints, ilines = _read_vectors(ipath, "r g b")
    if len(ints) != m:
        raise InputError(ipath, f"has {len(ints)} light intensities but filenames.txt lists {m} images")
    bad = np.flatnonzero(np.any(ints <= 0, axis=1))
    if bad.size:
        raise InputError(ipath, f"line {ilines[bad[0]]}: light intensities must be > 0, got {ints[bad[0]].tolist()}")
    return dirs, ints


# ----------------------------------------------------------------------------- ground truth


def _read_normal_gt(root: Path, shape: tuple[int, int]) -> np.ndarray | None:
    mat = root / "Normal_gt.mat"
    npy = root / "normal_gt.npy"
    if mat.is_file():
        import scipy.io

        try:
            data = scipy.io.loadmat(str(mat))
        except Exception as exc:
            raise InputError(mat, f"unreadable MATLAB file ({exc})") from exc
        if "Normal_gt" not in data:
            raise InputError(mat, "has no variable 'Normal_gt'")
        gt, path = data["Normal_gt"], mat
    elif npy.is_file():
        try:
            gt = np.load(npy, allow_pickle=False)
        except Exception as exc:
            raise InputError(npy, f"unreadable .npy file ({exc})") from exc
        path = npy
    else:
        return None
    if gt.shape != shape + (3,):
        raise InputError(path, f"ground truth has shape {gt.shape}, expected {shape + (3,)} (H x W x 3)")
    if not np.issubdtype(gt.dtype, np.number):
        raise InputError(path, f"ground truth has non-numeric type {gt.dtype}")
    gt = gt.astype(np.float32)
    if not np.all(np.isfinite(gt)):
        raise InputError(path, "ground truth contains NaN or infinity")
    return gt


# ----------------------------------------------------------------------------- images


def _grey(img: np.ndarray, intensity: np.ndarray, weights: np.ndarray) -> np.ndarray:
    if img.shape[2] == 1:
        return img[:, :, 0] / np.float32(weights @ intensity)
    w = (weights / intensity).astype(np.float32)  # per-channel weight / intensity
    return img[:, :, 0] * w[0] + img[:, :, 1] * w[1] + img[:, :, 2] * w[2]


def _check_image(path: Path, img: np.ndarray, ref) -> np.ndarray:
    if ref is not None and img.shape[:2] != ref[:2]:
        H, W, name = ref
        raise InputError(path, f"image is {img.shape[1]}x{img.shape[0]} but {name} is {W}x{H}")
    if not np.all(np.isfinite(img)):
        raise InputError(path, "image contains NaN or infinite pixels")
    return img


def _normalise_drop(drop, m: int, path: Path) -> list[int]:
    try:
        idx = sorted({int(i) for i in drop})
    except (TypeError, ValueError):
        raise ConfigError(f"drop must be a list of image indices, got {drop!r}") from None
    bad = [i for i in idx if i < 0 or i >= m]
    if bad:
        raise ConfigError(f"drop index {bad[0]} is out of range: {path} lists {m} images (0..{m - 1})")
    return idx


def load_capture(
    path: str | Path,
    drop=None,
    grey: str = "mean",
    progress: bool = False,
    workers: int | None = None,
) -> Capture:
    """Load and validate a capture folder.

    drop: indices (0-based, in filenames.txt order) of images to leave out. None applies
        the benchmark default for known objects (``bearPNG``: the first 20), recorded in
        ``Capture.notes``; an empty list drops nothing.
    grey: "mean" or "luminance" (see the module docstring).
    """
    root = Path(path)
    if grey not in GREY_WEIGHTS:
        raise ConfigError(f"grey must be one of {sorted(GREY_WEIGHTS)}, got {grey!r}")
    if not root.exists():
        raise InputError(root, "capture folder not found")
    if not root.is_dir():
        raise InputError(root, "not a folder (expected a capture folder with filenames.txt)")
    notes: list[str] = []

    names = _read_filenames(root)
    m_all = len(names)
    lights, intensities = _read_lights(root, m_all)

    if drop is None and root.name in DEFAULT_DROPS:
        dropped = [i for i in DEFAULT_DROPS[root.name] if i < m_all]
        notes.append(
            f"{root.name}: dropped the first {len(dropped)} images (benchmark rule); "
            "pass an explicit drop list to change this"
        )
    else:
        dropped = _normalise_drop([] if drop is None else drop, m_all, root / "filenames.txt")
    keep = np.setdiff1d(np.arange(m_all), dropped)
    if keep.size < MIN_IMAGES:
        raise ConfigError(f"{root}: only {keep.size} images left after dropping {len(dropped)}; need at least {MIN_IMAGES}")
    names = [names[i] for i in keep]
    lights, intensities = lights[keep], intensities[keep]

    paths = []
    for n in names:
        p = root / n
        if not p.is_file():
            raise InputError(p, "image listed in filenames.txt not found")
        paths.append(p)

    mask_path = root / "mask.png"
    if not mask_path.is_file():
        raise InputError(mask_path, "file not found (every capture needs an object mask)")

    weights = GREY_WEIGHTS[grey]
    first = _check_image(paths[0], read_image(paths[0]), None)
    H, W = first.shape[:2]
    mask = read_mask(mask_path)
    if mask.shape != (H, W):
        raise InputError(mask_path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the images are {W}x{H}")
    if not mask.any():
        raise InputError(mask_path, "mask is empty (no non-zero pixel)")
    normal_gt = _read_normal_gt(root, (H, W))

    images = np.empty((len(paths), H, W), dtype=np.float32)
    images[0] = _grey(first, intensities[0], weights)
    del first

    def load(k: int) -> None:
        img = _check_image(paths[k], read_image(paths[k]), (H, W, paths[0].name))
        images[k] = _grey(img, intensities[k], weights)

    if workers is None:
        workers = min(8, os.cpu_count() or 1)
    # Decoding (OpenCV, OpenEXR, zlib) releases the GIL: threads overlap file reading.
    # Results are consumed in order so the first bad file (in list order) is reported.
    from tqdm import tqdm

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        futures = [pool.submit(load, k) for k in range(1, len(paths))]
        try:
            bar = tqdm(futures, desc=f"reading {root.name}", unit="img", total=len(paths), initial=1, disable=not progress, leave=False)
            for f in bar:
                f.result()
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    return Capture(
        name=root.name,
        root=root,
        filenames=names,
        images=images,
        lights=lights,
        intensities=intensities,
        mask=mask,
        normal_gt=normal_gt,
        dropped=list(map(int, dropped)),
        notes=notes,
        grey=grey,
    )
