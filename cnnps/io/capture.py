"""Reading a capture folder (the DiLiGenT layout; see docs/ARCHITECTURE.md).

A capture folder holds:

- ``filenames.txt``: one image name a line, in light order;
- ``light_directions.txt``: m lines ``lx ly lz`` (camera frame: x right, y up, z toward
  the camera); normalised to unit length on load;
- ``light_intensities.txt``: m lines ``r g b``; each image channel is divided by it;
- or, for point lights near the object, ``light_positions.txt`` in place of
  ``light_directions.txt``: m lines ``x y z`` in the capture frame with the origin at the
  camera's optical centre, any length unit (the intensities are then radiant
  intensities: irradiance I / r^2 on a surface facing the light at distance r). It needs
  ``intrinsics.txt`` (a pinhole camera's K, read by :func:`cnnps.api.prediction.predict_folder`);
  when both light files are there, the positions are used (a note says so);
- ``mask.png``: non-zero = object;
- optional ground truth ``Normal_gt.mat`` (variable ``Normal_gt``) or ``normal_gt.npy``,
  both H x W x 3.

Images may be 8/16-bit PNG, 8-bit JPEG, 8/16-bit TIFF, float32 EXR or camera RAW photos
(:func:`cnnps.io.images.read_image_raw`). Integer images are scaled to [0, 1] by their
type's maximum and, with ``linearize="srgb"``, decoded with the sRGB EOTF
(:mod:`cnnps.io.srgb`); ``linearize=None`` or ``"none"`` takes them as linear (right
for DiLiGenT's 16-bit PNGs and raw-converted linear files, wrong for ordinary camera
JPEGs). Float images are always linear. RAW photos are demosaiced linearly
(:mod:`cnnps.io.raw`, uint16, pixel type ``"raw-uint16"``) and always taken as linear;
``linearize="srgb"`` with a RAW photo in the folder is an InputError naming it. Each
image is turned into one grey float32 image: the mean of its intensity-normalised
channels (``grey="mean"``), or their luminance 0.2989 R + 0.5870 G + 0.1140 B
(``grey="luminance"``, MATLAB's rgb2gray weights, used by published least-squares
numbers). A one-channel image is divided by the same combination of the three light
intensities.

Two ways to read the images:

- :func:`load_capture` reads the whole stack into ``Capture.images`` (m x H x W float32):
  simple, for small captures (training renders, tests, benchmarks);
- :func:`scan_capture` validates the folder and reads only the mask, lights and ground
  truth; :meth:`Capture.read_pixels` then gives one image's masked pixels at a time
  (what ``cnnps predict`` streams into a :class:`cnnps.io.pixel_store.PixelStack`),
  with saturated observations (any channel >= ``SATURATION_LEVEL`` of an integer type's
  maximum, before linearization) flagged.

Both compute every value with the same float32 operations, so they agree bit for bit.
Every problem is reported as one :class:`cnnps.infra.errors.InputError` naming the bad file.
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, NamedTuple

import numpy as np

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.options import check_arguments
from cnnps.io.images import max_code, pixel_kind, read_image_raw, read_mask
from cnnps.io.raw import RAW_KIND, check_linearize
from cnnps.io.srgb import Linearize, linear_table

Grey = Literal["mean", "luminance"]  # how RGB becomes grey (``--grey``)
GREY_WEIGHTS = {
    "mean": np.array([1.0, 1.0, 1.0]) / 3.0,
    "luminance": np.array([0.2989, 0.5870, 0.1140]),
}

# Benchmark rules: DiLiGenT BEAR's first 20 images are corrupted and dropped by everyone.
DEFAULT_DROPS = {"bearPNG": list(range(20))}

MIN_IMAGES = 3

# An observation is saturated when any channel is >= this fraction of the integer type's
# maximum (253 of 255, 64880 of 65535), judged on the stored codes before linearization.
SATURATION_LEVEL = 0.99

# Decoded images in flight at once while reading (threads): at most this many bytes of
# raw pixels, so a 12-megapixel stack does not hold 8 decoded frames at a time.
DECODE_BUDGET_BYTES = 512 * 2**20
MAX_READ_WORKERS = 8


class ImagePixels(NamedTuple):
    """One image's masked pixels (:meth:`Capture.read_pixels`)."""

    values: np.ndarray  # (P,) float32 grey, intensity-normalised, as stored (saturated ones too)
    saturated: np.ndarray | None  # (P,) bool, True = saturated (a missing observation); None: none
    kind: str  # the stored pixel type: "uint8", "uint16", "float32" or "raw-uint16" (a RAW photo)

    @property
    def n_saturated(self) -> int:
        return 0 if self.saturated is None else int(self.saturated.sum())


@dataclass
class Capture:
    """One capture: grey images, lights, mask and optional ground truth."""

    name: str
    root: Path
    filenames: list[str]
    images: np.ndarray | None  # (m, H, W) float32 grey, intensity-normalised; None from scan_capture
    lights: np.ndarray  # (m, 3) float64 unit directions (point lights: seen from the optical axis at their median distance)
    intensities: np.ndarray  # (m, 3) float64 RGB light intensities (already divided out)
    mask: np.ndarray  # (H, W) bool
    normal_gt: np.ndarray | None = None  # (H, W, 3) float32 or None
    dropped: list[int] = field(default_factory=list)  # indices into the original filenames.txt
    notes: list[str] = field(default_factory=list)  # messages for the user
    grey: str = "mean"
    paths: list[Path] = field(default_factory=list)  # the image files, in light order
    linearize: str | None = None  # "srgb" | "none" | None (not chosen: integer images taken as linear)
    first_kind: str | None = None  # stored pixel type of the first image (ImagePixels.kind)
    light_positions: np.ndarray | None = None  # (m, 3) float64 point-light positions (light_positions.txt), or None

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
        """(P, m) float32 values of the mask pixels, row-major pixel order (needs
        :func:`load_capture`; a scanned capture streams them with :meth:`read_pixels`)."""
        if self.images is None:
            raise ValueError("this capture was scanned, not loaded: use read_pixels(k) per image")
        return np.ascontiguousarray(self.images[:, self.mask].T, dtype=np.float32)

    def read_grey(self, k: int) -> np.ndarray:
        """Image ``k`` as one (H, W) float32 grey image (no saturation test)."""
        raw = self.read_raw(k)
        return _grey(linear_values(raw, self.linearize), self.intensities[k], GREY_WEIGHTS[self.grey])

    def read_pixels(self, k: int, saturation: float | None = SATURATION_LEVEL) -> ImagePixels:
        """Image ``k``'s mask pixels (row-major order, like :meth:`pixel_intensities`).

        ``values`` are exactly those of :meth:`read_grey` at the mask pixels;
        ``saturated`` flags the observations with any channel >= ``saturation`` x the
        integer type's maximum (None when there is none). Float images have no maximum
        and are never flagged; ``saturation`` None flags nothing. Works in bands of rows,
        so the temporaries stay small next to the decoded image.
        """
        raw = self.read_raw(k)
        pix = masked_pixels(raw, self.mask, self.intensities[k], self.grey, self.linearize, saturation)
        return pix._replace(kind=pixel_kind(self.paths[k], raw))

    def read_raw(self, k: int) -> np.ndarray:
        """Image ``k`` as stored ((H, W, C) uint8, uint16 or float32), its size and finite
        values checked (an :class:`InputError` naming the file)."""
        path = self.paths[k]
        H, W = self.shape
        raw = read_image_raw(path)
        ref = None if k == 0 else (H, W, self.paths[0].name)
        return _check_image(path, raw, ref)

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


def read_filenames(root: Path) -> list[str]:
    """The image names of ``root/filenames.txt`` (one a line, light order; '#' comments
    and blank lines skipped); an InputError when it is missing or lists nothing."""
    path = Path(root) / "filenames.txt"
    names = [line for _, line in _read_lines(path)]
    if not names:
        raise InputError(path, "file is empty")
    return names


POSITIONS_FILE = "light_positions.txt"
INTRINSICS_FILE = "intrinsics.txt"


def read_intrinsics(path: Path) -> np.ndarray | None:
    """K (3, 3) from an intrinsics.txt (three rows of three numbers), None when the file
    does not exist; an InputError naming it when it is not a valid pinhole matrix
    (:func:`cnnps.ps.camera.check_intrinsics`)."""
    from cnnps.ps.camera import check_intrinsics

    path = Path(path)
    if not path.is_file():
        return None
    try:
        return check_intrinsics(np.loadtxt(path, dtype=np.float64, ndmin=2))
    except ValueError as exc:
        raise InputError(path, str(exc)) from None


def _read_positions(root: Path, m: int, notes: list[str]) -> np.ndarray | None:
    """Point-light positions from light_positions.txt (None without one); InputError
    naming the file for a wrong count, a light behind the camera, or no intrinsics.txt."""
    from cnnps.ps.near_lights import check_positions

    path = root / POSITIONS_FILE
    if not path.is_file():
        return None
    pos, lines = _read_vectors(path, "x y z")
    if len(pos) != m:
        raise InputError(path, f"has {len(pos)} light positions but filenames.txt lists {m} images")
    try:
        pos = check_positions(pos)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    if not (root / INTRINSICS_FILE).is_file():
        raise InputError(path, f"point lights need a perspective camera: add {INTRINSICS_FILE} (K, 3 x 3) to the folder")
    if (root / "light_directions.txt").is_file():
        notes.append(f"{POSITIONS_FILE} and light_directions.txt are both present: the point lights are used")
    return pos


def _read_lights(root: Path, m: int, positions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    dpath = root / "light_directions.txt"
    ipath = root / "light_intensities.txt"
    if positions is not None:
        from cnnps.ps.near_lights import directions_from_positions

        return directions_from_positions(positions), _read_intensities(ipath, m)
    dirs, dlines = _read_vectors(dpath, "lx ly lz")
    if len(dirs) != m:
        raise InputError(dpath, f"has {len(dirs)} light directions but filenames.txt lists {m} images")
    norms = np.linalg.norm(dirs, axis=1)
    bad = np.flatnonzero(norms < 1e-8)
    if bad.size:
        raise InputError(dpath, f"line {dlines[bad[0]]}: zero-length light direction")
    dirs = dirs / norms[:, None]
    return dirs, _read_intensities(ipath, m)


def _read_intensities(ipath: Path, m: int) -> np.ndarray:
    ints, ilines = _read_vectors(ipath, "r g b")
    if len(ints) != m:
        raise InputError(ipath, f"has {len(ints)} light intensities but filenames.txt lists {m} images")
    bad = np.flatnonzero(np.any(ints <= 0, axis=1))
    if bad.size:
        raise InputError(ipath, f"line {ilines[bad[0]]}: light intensities must be > 0, got {ints[bad[0]].tolist()}")
    return ints


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
    """(..., C) float32 linear values -> (...) float32 grey, intensity divided out."""
    if img.shape[-1] == 1:
        return img[..., 0] / np.float32(weights @ intensity)
    w = (weights / intensity).astype(np.float32)  # per-channel weight / intensity
    return img[..., 0] * w[0] + img[..., 1] * w[1] + img[..., 2] * w[2]


@functools.lru_cache(maxsize=8)
def _table(top: int, linearize: str) -> np.ndarray:
    table = linear_table(top, linearize)
    table.flags.writeable = False
    return table


def linear_values(raw: np.ndarray, linearize: str | None) -> np.ndarray:
    """Stored values (:func:`cnnps.io.images.read_image_raw`) -> float32 linear values
    in [0, 1] (floats: as stored); ``linearize`` as :func:`scan_capture`.

    Integers go through a look-up table: with ``"none"`` (or None) it holds
    float32(code) / float32(max), exactly what :func:`cnnps.io.images.read_image` gives."""
    top = max_code(raw.dtype)
    if top is None:
        return raw if raw.dtype == np.float32 else raw.astype(np.float32)
    return _table(top, linearize or "none")[raw]


def saturation_code(dtype, saturation: float | None = SATURATION_LEVEL) -> int | None:
    """The smallest stored code counted as saturated: ``ceil(saturation x maximum)`` of an
    integer pixel type (253 for uint8, 64880 for uint16 at 0.99); None for float types
    (no maximum) or ``saturation`` None."""
    top = max_code(dtype)
    if saturation is None or top is None:
        return None
    return int(np.ceil(float(saturation) * top))


def masked_pixels(raw: np.ndarray, mask: np.ndarray, intensity, grey: Grey = "mean",
                  linearize: Linearize | None = None, saturation: float | None = SATURATION_LEVEL) -> ImagePixels:
    """One image's mask pixels as ``cnnps predict`` uses them (row-major order).

    raw: (H, W, C) stored values (uint8, uint16 or float32; C = 1 or 3), as
    :func:`cnnps.io.images.read_image_raw` returns them; mask: (H, W) bool; intensity:
    the light's (3,) RGB intensity, divided out of each channel before the grey
    combination; grey, linearize: as :func:`scan_capture`. ``saturated`` flags the
    observations with any channel >= ``saturation`` x the integer type's maximum (None
    when there is none; float images are never flagged). Works in bands of rows, so the
    temporaries stay small next to the decoded image.
    """
    H, W = mask.shape
    weights = GREY_WEIGHTS[grey]
    intensity = np.asarray(intensity, dtype=np.float64)
    level = saturation_code(raw.dtype, saturation)
    P = int(mask.sum())
    values = np.empty(P, dtype=np.float32)
    saturated = None
    o = 0
    band = max(1, (1 << 20) // max(1, W))  # about a megapixel of rows at a time
    for r0 in range(0, H, band):
        sub = raw[r0 : r0 + band][mask[r0 : r0 + band]]  # (n, C) stored values
        n = sub.shape[0]
        if n == 0:
            continue
        values[o : o + n] = _grey(linear_values(sub, linearize), intensity, weights)
        if level is not None:
            sat = (sub >= level).any(axis=-1)
            if sat.any():
                if saturated is None:
                    saturated = np.zeros(P, dtype=bool)
                saturated[o : o + n] = sat
        o += n
    return ImagePixels(values, saturated, str(raw.dtype))


def _check_image(path: Path, img: np.ndarray, ref) -> np.ndarray:
    if ref is not None and img.shape[:2] != ref[:2]:
        H, W, name = ref
        raise InputError(path, f"image is {img.shape[1]}x{img.shape[0]} but {name} is {W}x{H}")
    if np.issubdtype(img.dtype, np.floating) and not np.all(np.isfinite(img)):
        raise InputError(path, "image contains NaN or infinite pixels")
    return img


def read_workers(capture: Capture, workers: int | None = None) -> int:
    """Threads to decode images with: ``workers`` (default: the CPU count, at most
    ``MAX_READ_WORKERS``), fewer when that many decoded images would pass
    ``DECODE_BUDGET_BYTES`` (judged on the first image's size and type), at least 1."""
    if workers is None:
        workers = min(MAX_READ_WORKERS, os.cpu_count() or 1)
    H, W = capture.shape
    kind = capture.first_kind
    item = 2 if kind in ("uint16", RAW_KIND) else (1 if kind == "uint8" else 4)
    # the decoded frame plus the float32 grey/band temporaries of one image; a RAW photo
    # adds LibRaw's buffers while it decodes (the sensor values and a 4-channel uint16 frame)
    per_image = H * W * (3 * item + 8 + (10 if kind == RAW_KIND else 0))
    return max(1, min(int(workers), DECODE_BUDGET_BYTES // max(1, per_image)))


def for_each_image(
    capture: Capture,
    work: Callable[[int], None],
    workers: int | None = None,
    progress: bool = False,
    desc: str | None = None,
) -> None:
    """Run ``work(k)`` for every image k of ``capture`` on a few threads (decoding with
    OpenCV, OpenEXR and zlib releases the GIL), with a progress bar. Results are
    consumed in order, so the first bad file (in list order) is the one reported, and
    at most ``workers`` images are in flight (see :func:`read_workers`)."""
    from cnnps.infra.progress import progress_bar

    n = capture.n_images
    workers = read_workers(capture, workers)
    bar = progress_bar(total=n, desc=desc or f"reading {capture.name}", unit="img", disable=not progress, leave=False)
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            pending: list = []
            nxt = 0
            try:
                while nxt < n or pending:
                    while nxt < n and len(pending) < 2 * workers:
                        pending.append(pool.submit(work, nxt))
                        nxt += 1
                    pending.pop(0).result()
                    bar.update(1)
            except BaseException:
                for f in pending:
                    f.cancel()
                raise
    finally:
        bar.close()


def _normalise_drop(drop, m: int, path: Path) -> list[int]:
    try:
        idx = sorted({int(i) for i in drop})
    except (TypeError, ValueError):
        raise ConfigError(f"drop must be a list of image indices, got {drop!r}") from None
    bad = [i for i in idx if i < 0 or i >= m]
    if bad:
        raise ConfigError(f"drop index {bad[0]} is out of range: {path} lists {m} images (0..{m - 1})")
    return idx


def subset_drop(path: str | Path, n: int, seed: int = 0) -> list[int]:
    """Indices (0-based, filenames.txt order) to drop so that ``n`` images of a capture
    remain, drawn by one seeded rule: the same for every capture, so held-back objects get
    their sparse subsets the same way.

    The candidates are the images left after the benchmark default drops
    (:data:`DEFAULT_DROPS`: ``bearPNG`` loses its first 20); of those m, ``n`` are drawn
    uniformly without replacement by ``numpy.random.default_rng([seed, m, n]).choice(m, n,
    replace=False)``. Pass the result as ``drop`` to :func:`scan_capture` /
    :func:`load_capture`. A ConfigError unless ``MIN_IMAGES <= n <= m``.

    Example: ``load_capture(d, drop=subset_drop(d, 10))``: 10 of ballPNG's 96 images.
    """
    root = Path(path)
    names = read_filenames(root)
    default = set(DEFAULT_DROPS.get(root.name, ()))
    usable = [i for i in range(len(names)) if i not in default]
    m = len(usable)
    if not MIN_IMAGES <= n <= m:
        raise ConfigError(f"{root}: cannot keep {n} images of {m} (need {MIN_IMAGES} <= n <= {m})")
    keep = {usable[int(i)] for i in np.random.default_rng([seed, m, n]).choice(m, n, replace=False)}
    return [i for i in range(len(names)) if i not in keep]


def scan_capture(
    path: str | Path,
    drop=None,
    grey: Grey = "mean",
    linearize: Linearize | None = None,
) -> Capture:
    """Validate a capture folder and read everything but the image stack.

    Reads the text files, the mask, the ground truth and the first image (for the size
    and pixel type); checks that every listed image exists. The returned Capture has
    ``images = None``; read images one at a time with :meth:`Capture.read_pixels` /
    :meth:`Capture.read_grey` (each checks size and finite values of its file).

    drop: indices (0-based, in filenames.txt order) of images to leave out. None applies
        the benchmark default for known objects (``bearPNG``: the first 20), recorded in
        ``Capture.notes``; an empty list drops nothing.
    grey: "mean" or "luminance" (see the module docstring).
    linearize: "srgb" | "none" | None for integer images (see the module docstring;
        "srgb" with a RAW photo is an InputError naming it).
    """
    root = Path(path)
    check_arguments(scan_capture, {"grey": grey, "linearize": linearize})
    if not root.exists():
        raise InputError(root, "capture folder not found")
    if not root.is_dir():
        raise InputError(root, "not a folder (expected a capture folder with filenames.txt)")
    notes: list[str] = []

    names = read_filenames(root)
    m_all = len(names)
    positions = _read_positions(root, m_all, notes)
    lights, intensities = _read_lights(root, m_all, positions)

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
    if positions is not None:
        positions = positions[keep]

    paths = []
    for n in names:
        p = root / n
        if not p.is_file():
            raise InputError(p, "image listed in filenames.txt not found")
        paths.append(p)
    check_linearize(paths, linearize)

    mask_path = root / "mask.png"
    if not mask_path.is_file():
        raise InputError(mask_path, "file not found (every capture needs an object mask)")

    first = _check_image(paths[0], read_image_raw(paths[0]), None)
    H, W = first.shape[:2]
    kind = pixel_kind(paths[0], first)
    del first
    mask = read_mask(mask_path)
    if mask.shape != (H, W):
        raise InputError(mask_path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the images are {W}x{H}")
    if not mask.any():
        raise InputError(mask_path, "mask is empty (no non-zero pixel)")
    normal_gt = _read_normal_gt(root, (H, W))

    return Capture(
        name=root.name,
        root=root,
        filenames=names,
        images=None,
        lights=lights,
        intensities=intensities,
        mask=mask,
        normal_gt=normal_gt,
        dropped=list(map(int, dropped)),
        notes=notes,
        grey=grey,
        paths=paths,
        linearize=linearize,
        first_kind=kind,
        light_positions=positions,
    )


def load_capture(
    path: str | Path,
    drop=None,
    grey: Grey = "mean",
    progress: bool = False,
    workers: int | None = None,
    linearize: Linearize | None = None,
) -> Capture:
    """Load and validate a capture folder, the whole image stack into ``Capture.images``.

    drop, grey, linearize: as :func:`scan_capture`. No saturation test (the stack holds
    every value as stored); ``cnnps predict`` streams with :meth:`Capture.read_pixels`.
    """
    capture = scan_capture(path, drop=drop, grey=grey, linearize=linearize)
    H, W = capture.shape
    images = np.empty((capture.n_images, H, W), dtype=np.float32)

    def load(k: int) -> None:
        images[k] = capture.read_grey(k)

    for_each_image(capture, load, workers=workers, progress=progress)
    capture.images = images
    return capture
