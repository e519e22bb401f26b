"""The :class:`Capture` type and the capture folder read and written as a whole.

Reading (:func:`scan_capture`, :func:`load_capture`, :func:`scan_images`) checks the folder
and gives one :class:`Capture`; writing (:func:`write_capture`) makes a folder from one,
all at once. The files themselves are :mod:`cnnps.io.capture.files`'s; stored values
become grey observations by :mod:`cnnps.io.capture.pixels`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from cnnps.infra.errors import ConfigError, InputError
from cnnps.infra.options import check_arguments
from cnnps.io.capture.benchmark import MIN_IMAGES
from cnnps.io.capture.files import (
    FILENAMES_FILE,
    read_depth_gt,
    read_filenames,
    read_light_files,
    read_mask_file,
    read_normal_gt,
    require_mask,
    write_depth_gt,
    write_filenames,
    write_image,
    write_intrinsics,
    write_light_directions,
    write_light_intensities,
    write_light_positions,
    write_mask,
    write_normal_gt,
    write_scene,
)
from cnnps.io.capture.pixels import (
    GREY_WEIGHTS,
    SATURATION_LEVEL,
    Grey,
    ImagePixels,
    grey_values,
    linear_values,
    masked_pixels,
)
from cnnps.io.images import pixel_kind, read_image_raw
from cnnps.io.raw import RAW_KIND, check_linearize
from cnnps.io.srgb import Linearize

# Decoded images in flight at once while reading (threads): at most this many bytes of
# raw pixels, so a 12-megapixel stack does not hold 8 decoded frames at a time.
DECODE_BUDGET_BYTES = 512 * 2**20
MAX_READ_WORKERS = 8


@dataclass(kw_only=True)
class Capture:
    """One capture: its images (in memory, or read from their files on demand), lights,
    camera, mask and ground truth. Frame: x right, y up, z toward the camera; row 0 on top.

    filenames: the m image names, in light order.
    lights: (m, 3) float64 unit light directions (point lights: seen from the optical axis
        at their median distance, made from ``light_positions`` when not given).
    intensities: (m, 3) float64 RGB light intensities, as stored (divided out of each
        channel when grey values are made).
    mask: (H, W) bool, True = object.
    images: (m, H, W, C) the stored pixel values (uint8, uint16 or float32; C = 3, or 1
        for grey files), or None: each image is read from its file when needed.
    normal_gt: (H, W, 3) float32 ground-truth normals, or None.
    depth_gt: (H, W) float32 ground-truth depth along the optical axis (NaN outside), or None.
    light_positions: (m, 3) float64 point-light positions (origin at the camera's optical
        centre), or None (distant lights).
    intrinsics: (3, 3) a pinhole camera's K (OpenCV convention), or None (orthographic).
    root: the folder read, or None (made in memory); paths: its image files, light order.
    dropped: indices into the folder's filenames.txt left out; notes: messages for the user.
    grey, linearize: how stored values become grey (:mod:`cnnps.io.capture.pixels`).
    first_kind: stored pixel type of the first image (:attr:`ImagePixels.kind`), or None.

    A folder of photos without lights (:func:`scan_images`, a calibration ball) has
    ``lights``, ``intensities`` and ``mask`` None.

    Example::

        cap = Capture(filenames=["0.png", "1.png", "2.png"], lights=L, intensities=np.ones((3, 3)),
                      mask=mask, images=stack)          # stack (3, H, W, 3) uint16
        write_capture("out/cap", cap)
        load_capture("out/cap").images                   # the same stack
    """

    filenames: list[str]
    lights: np.ndarray | None = None
    intensities: np.ndarray | None = None
    mask: np.ndarray | None = None
    images: np.ndarray | None = None
    normal_gt: np.ndarray | None = None
    depth_gt: np.ndarray | None = None
    light_positions: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    root: Path | None = None
    paths: list[Path] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    grey: str = "mean"
    linearize: str | None = None  # "srgb" | "none" | None (not chosen: integer images taken as linear)
    first_kind: str | None = None
    frame: tuple[int, int] | None = None  # (H, W) of the files' images (scan_capture): the size without a mask

    def __post_init__(self):
        self.filenames = list(self.filenames)
        m = len(self.filenames)
        if self.lights is None and self.light_positions is not None:
            from cnnps.ps.near_lights import directions_from_positions

            self.lights = directions_from_positions(self.light_positions)
        for name in ("lights", "intensities", "light_positions"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != (m, 3):
                raise ValueError(f"Capture.{name} must be ({m}, 3) for {m} images, got {np.shape(v)}")
        if self.images is not None and len(self.images) != m:
            raise ValueError(f"Capture.images holds {len(self.images)} images but there are {m} filenames")

    @property
    def name(self) -> str:
        return self.root.name if self.root is not None else ""

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W): the mask's, else the images' (a capture still without a mask)."""
        if self.mask is not None:
            return self.mask.shape
        if self.images is not None:
            return tuple(self.images.shape[1:3])
        return self.frame

    @property
    def n_images(self) -> int:
        return len(self.filenames)

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())

    def pixel_intensities(self) -> np.ndarray:
        """(P, m) float32 grey values of the mask pixels, row-major pixel order (needs the
        images in memory, :func:`load_capture`; a scanned capture streams them with
        :meth:`read_pixels`)."""
        if self.images is None:
            raise ValueError("this capture was scanned, not loaded: use read_pixels(k) per image")
        values = np.empty((self.n_images, self.n_pixels), dtype=np.float32)
        for k in range(self.n_images):
            values[k] = self.read_pixels(k, saturation=None).values
        return np.ascontiguousarray(values.T)

    def grey_images(self) -> np.ndarray:
        """(m, H, W) float32 grey images, intensity-normalised (:meth:`read_grey` of each)."""
        out = np.empty((self.n_images,) + self.shape, dtype=np.float32)
        for k in range(self.n_images):
            out[k] = self.read_grey(k)
        return out

    def read_grey(self, k: int) -> np.ndarray:
        """Image ``k`` as one (H, W) float32 grey image (no saturation test)."""
        raw = self.read_raw(k)
        return grey_values(linear_values(raw, self.linearize), self.intensities[k], GREY_WEIGHTS[self.grey])

    def read_pixels(self, k: int, saturation: float | None = SATURATION_LEVEL, colour: bool = False) -> ImagePixels:
        """Image ``k``'s mask pixels (row-major order, like :meth:`pixel_intensities`).

        ``values`` are exactly those of :meth:`read_grey` at the mask pixels;
        ``saturated`` flags the observations with any channel >= ``saturation`` x the
        integer type's maximum (None when there is none). Float images have no maximum
        and are never flagged; ``saturation`` None flags nothing. Works in bands of rows,
        so the temporaries stay small next to the decoded image. ``colour=True`` also
        gives ``colour`` (P, 3) float32: the linear R, G, B divided by the light's
        intensity in each channel (a grey image's value in all three), from the same read
        (:func:`cnnps.io.capture.pixels.colour_values`); the rest is unchanged.
        """
        raw = self.read_raw(k)
        pix = masked_pixels(raw, self.mask, self.intensities[k], self.grey, self.linearize, saturation, colour)
        return pix if not self.paths else pix._replace(kind=pixel_kind(self.paths[k], raw))

    def read_raw(self, k: int) -> np.ndarray:
        """Image ``k`` as stored ((H, W, C) uint8, uint16 or float32): from memory, or from
        its file with its size and finite values checked (an :class:`InputError` naming it)."""
        if self.images is not None:
            return self.images[k]
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


# ----------------------------------------------------------------------------- reading


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


def _check_folder(root: Path, what: str) -> None:
    if not root.exists():
        raise InputError(root, f"{what} folder not found")
    if not root.is_dir():
        expected = "a capture folder" if what == "capture" else f"the {what} photos"
        raise InputError(root, f"not a folder (expected {expected}: its images, listed in light order in "
                               f"{FILENAMES_FILE} or named in that order)")


def _image_paths(root: Path, names: list[str]) -> list[Path]:
    paths = [root / n for n in names]
    for p in paths:
        if not p.is_file():
            raise InputError(p, f"image listed in {FILENAMES_FILE} not found")
    return paths


def scan_images(path: str | Path, what: str = "capture") -> Capture:
    """A folder of photos in light order without lights (a calibration ball folder):
    ``filenames.txt`` read (without it, the photos in name order, said in ``notes``) and
    every listed image present. ``lights``, ``intensities`` and
    ``mask`` are None (a ball's optional ``mask.png``: :func:`cnnps.io.capture.files.read_mask_file`
    once the image size is known); ``what`` names the folder in errors ("chrome ball").

    Example: ``scan_images("chrome", "chrome ball").paths`` -> the photos, light order.
    """
    root = Path(path)
    _check_folder(root, what)
    notes: list[str] = []
    names = read_filenames(root, notes)
    return Capture(filenames=names, root=root, paths=_image_paths(root, names), notes=notes)


def scan_capture(
    path: str | Path,
    drop=None,
    grey: Grey = "mean",
    linearize: Linearize | None = None,
    missing_ok: tuple[str, ...] = (),
    lights_dir: str | Path | None = None,
) -> Capture:
    """Validate a capture folder and read everything but the image stack.

    Reads the text files, the camera, the mask, the ground truth and the first image (for
    the size and pixel type); checks that every listed image exists. The returned Capture
    has ``images = None``; read images one at a time with :meth:`Capture.read_pixels` /
    :meth:`Capture.read_grey` (each checks size and finite values of its file).

    drop: indices (0-based, in filenames.txt order) of images to leave out; None or an
        empty list drops nothing. A benchmark's rule is the caller's to pass
        (:func:`cnnps.io.capture.benchmark_drop`).
    grey: "mean" or "luminance" (see :mod:`cnnps.io.capture.pixels`).
    linearize: "srgb" | "none" | None for integer images ("srgb" with a RAW photo is an
        InputError naming it).
    missing_ok: files the capture may lack, ``"mask"`` (mask.png), ``"intensities"``
        (light_intensities.txt) and ``"lights"`` (the directions or positions file): a
        missing one leaves ``mask`` / ``intensities`` / ``lights`` None for the caller to
        make (:mod:`cnnps.api.capture_estimates`); a file that is there is read as always.
    lights_dir: the folder holding the light files (``cnnps calibrate``'s output), when
        not ``path`` (:func:`cnnps.io.capture.files.read_light_files`).

    Example: ``scan_capture("ballPNG").n_images`` -> 96.
    """
    root = Path(path)
    check_arguments(scan_capture, {"grey": grey, "linearize": linearize})
    _check_folder(root, "capture")
    notes: list[str] = []

    names = read_filenames(root, notes)
    m_all = len(names)
    unknown = sorted(set(missing_ok) - {"lights", "mask", "intensities"})
    if unknown:
        raise ValueError(f"missing_ok: unknown file kind {unknown[0]!r} (lights, mask, intensities)")
    positions, lights, intensities, intrinsics = read_light_files(root, m_all, notes, lights_dir, missing_ok)

    dropped = _normalise_drop([] if drop is None else drop, m_all, root / FILENAMES_FILE)
    keep = np.setdiff1d(np.arange(m_all), dropped)
    if keep.size < MIN_IMAGES:
        raise ConfigError(f"{root}: only {keep.size} images left after dropping {len(dropped)}; need at least {MIN_IMAGES}")
    names = [names[i] for i in keep]
    lights, intensities, positions = (None if a is None else a[keep] for a in (lights, intensities, positions))

    paths = _image_paths(root, names)
    check_linearize(paths, linearize)
    if "mask" not in missing_ok:
        require_mask(root)  # before any image is decoded

    first = _check_image(paths[0], read_image_raw(paths[0]), None)
    H, W = first.shape[:2]
    kind = pixel_kind(paths[0], first)
    del first
    mask = read_mask_file(root, (H, W), required="mask" not in missing_ok)
    normal_gt = read_normal_gt(root, (H, W))
    depth_gt = read_depth_gt(root, (H, W))

    return Capture(
        filenames=names,
        lights=lights,
        intensities=intensities,
        mask=mask,
        normal_gt=normal_gt,
        depth_gt=depth_gt,
        light_positions=positions,
        intrinsics=intrinsics,
        root=root,
        paths=paths,
        dropped=list(map(int, dropped)),
        notes=notes,
        grey=grey,
        linearize=linearize,
        first_kind=kind,
        frame=(H, W),
    )


def load_capture(
    path: str | Path,
    drop=None,
    grey: Grey = "mean",
    progress: bool = False,
    workers: int | None = None,
    linearize: Linearize | None = None,
) -> Capture:
    """Load and validate a capture folder, every image as stored into ``Capture.images``
    ((m, H, W, C): one pixel type and channel count for all, else an InputError naming
    the first image that differs).

    drop, grey, linearize: as :func:`scan_capture` (grey and linearize: how
    :meth:`Capture.pixel_intensities`, :meth:`Capture.grey_images` and
    :meth:`Capture.read_pixels` convert the stored values).

    Example: ``load_capture("ballPNG").images.shape`` -> (96, 512, 612, 3), uint16.
    """
    capture = scan_capture(path, drop=drop, grey=grey, linearize=linearize)
    first = capture.read_raw(0)
    images = np.empty((capture.n_images,) + first.shape, dtype=first.dtype)
    images[0] = first
    del first

    def load(k: int) -> None:
        raw = capture.read_raw(k)
        if raw.dtype != images.dtype or raw.shape != images.shape[1:]:
            raise InputError(capture.paths[k], f"image is {raw.dtype} with {raw.shape[-1]} channels but "
                                               f"{capture.paths[0].name} is {images.dtype} with {images.shape[-1]}")
        images[k] = raw

    for_each_image(capture, lambda k: None if k == 0 else load(k), workers=workers, progress=progress)
    capture.images = images
    return capture


# ----------------------------------------------------------------------------- writing


def write_capture_files(folder: str | Path, capture: Capture) -> None:
    """Write every file of ``capture`` but its images and the renderer's record into the
    existing ``folder``, each atomically: ``filenames.txt``; ``light_positions.txt`` (point
    lights) or ``light_directions.txt``; ``light_intensities.txt``; and, when set,
    ``intrinsics.txt``, ``mask.png``, ``normal_gt.npy``, ``depth_gt.npy``."""
    folder = Path(folder)
    write_filenames(folder, capture.filenames)
    if capture.light_positions is not None:
        write_light_positions(folder, capture.light_positions)
    elif capture.lights is not None:
        write_light_directions(folder, capture.lights)
    if capture.intensities is not None:
        write_light_intensities(folder, capture.intensities)
    if capture.intrinsics is not None:
        write_intrinsics(folder, capture.intrinsics)
    if capture.mask is not None:
        write_mask(folder, capture.mask)
    if capture.normal_gt is not None:
        write_normal_gt(folder, capture.normal_gt)
    if capture.depth_gt is not None:
        write_depth_gt(folder, capture.depth_gt)


def write_capture(
    folder: str | Path,
    capture: Capture,
    images: Iterable[np.ndarray] | None = None,
    *,
    scene: dict | Callable[[], dict] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``capture`` as the capture folder ``folder``, all at once: built in a
    temporary folder beside it, renamed into place at the end (nothing is left by a
    failure). Returns ``folder``.

    images: the images in light order, each (H, W, C) as it is to be stored (float32 for
        a ``.exr`` name, uint8 / uint16 for ``.png``), e.g. a generator that renders them
        one at a time; default ``capture.images``.
    scene: the renderer's record, written last as ``scene.json``: a dict, or a function
        returning one, called once the images are written.
    overwrite: replace an existing ``folder``; otherwise an existing one is an InputError.

    Example: ``write_capture("out/cap", Capture(filenames=names, lights=L, intensities=E,
    mask=mask, images=stack))``; ``load_capture("out/cap")`` then reads the same arrays.
    """
    from cnnps.infra.atomic import atomic_dir

    folder = Path(folder)
    if images is None:
        images = capture.images
    if images is None:
        raise ValueError("write_capture needs the images: capture.images or the images argument")
    if folder.exists() and not overwrite:
        raise InputError(folder, "exists; choose a new folder (or overwrite=True)")
    with atomic_dir(folder, overwrite=overwrite) as tmp:
        written = 0
        for name, image in zip(capture.filenames, images):
            write_image(tmp / name, image)
            written += 1
        if written != capture.n_images:
            raise ValueError(f"write_capture got {written} images for {capture.n_images} filenames")
        write_capture_files(tmp, capture)
        if scene is not None:
            write_scene(tmp, scene() if callable(scene) else scene)
    return folder
