"""A capture folder read into memory as stored: what :func:`cnnps.load_capture` returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class CaptureData:
    """One capture folder in memory, its images as stored (nothing converted).

    images: (m, H, W, C) the stored pixel values (uint8, uint16 or float32; C = 3, or 1 for
        grey files), in light order; ``cnnps.predict`` converts them exactly as
        ``cnnps predict`` converts the files.
    lights: (m, 3) float64 unit light directions (x right, y up, z toward the camera).
    intensities: (m, 3) float64 RGB light intensities (not yet divided out).
    mask: (H, W) bool object mask. normal_gt: (H, W, 3) float32 ground truth, or None.
    filenames: the image names, in light order; dropped: indices into the folder's
    filenames.txt that were left out; notes: messages for the user (e.g. a benchmark
    rule applied).
    """

    root: Path
    images: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    normal_gt: np.ndarray | None = None
    filenames: list[str] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.root.name


def read_capture(path, drop=None, progress: bool = False) -> CaptureData:
    """Check the capture folder ``path`` (:func:`cnnps.io.capture.scan_capture`: text
    files, mask, ground truth, every image present) and read every image as stored."""
    from cnnps.io.capture import for_each_image, scan_capture

    capture = scan_capture(path, drop=drop)
    first = capture.read_raw(0)
    images = np.empty((capture.n_images,) + first.shape, dtype=first.dtype)
    images[0] = first
    del first

    def load(k: int) -> None:
        raw = capture.read_raw(k)
        if raw.dtype != images.dtype or raw.shape != images.shape[1:]:
            from cnnps.infra.errors import InputError

            raise InputError(capture.paths[k], f"image is {raw.dtype} with {raw.shape[-1]} channels but "
                                               f"{capture.paths[0].name} is {images.dtype} with {images.shape[-1]}")
        images[k] = raw

    for_each_image(capture, lambda k: None if k == 0 else load(k), progress=progress)
    return CaptureData(capture.root, images, capture.lights, capture.intensities, capture.mask, capture.normal_gt,
                       list(capture.filenames), list(capture.dropped), list(capture.notes))
