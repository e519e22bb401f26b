"""Reading and writing images of a capture: 8/16-bit PNG, 16-bit TIFF, float32 OpenEXR.

Every reader returns float32 H x W x C in RGB channel order (C = 1 or 3), with integer
images scaled to [0, 1] by their type's maximum and EXR left linear as stored.
Errors are :class:`cnnps.core.errors.InputError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cnnps.core.atomic import atomic_path
from cnnps.core.errors import InputError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".exr")


def _scale_integer(img: np.ndarray, path: Path) -> np.ndarray:
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if np.issubdtype(img.dtype, np.floating):
        return img.astype(np.float32)
    raise InputError(path, f"unsupported pixel type {img.dtype}")


def read_exr(path: str | Path, channels: str | None = None) -> np.ndarray:
    """Read an OpenEXR image as float32, row 0 on top, values linear as stored.

    ``channels``: the channel names to return, in that order (e.g. ``"RGBA"`` gives
    (H, W, 4)); a missing one is an InputError. ``None`` (what :func:`read_image` uses):
    RGB when the file has R, G and B, else Y (grey), else its first channel (group).
    """
    import OpenEXR

    path = Path(path)
    try:
        with OpenEXR.File(str(path), separate_channels=channels is not None) as f:
            found = f.channels()
            if channels is not None:
                missing = [c for c in channels if c not in found]
                if missing:
                    raise InputError(path, f"EXR file has no channel {missing[0]!r} (has {', '.join(sorted(found))})")
                img = np.stack([np.asarray(found[c].pixels) for c in channels], axis=-1)
            elif "RGB" in found:
                img = np.asarray(found["RGB"].pixels)
            elif all(c in found for c in "RGB"):
                img = np.stack([np.asarray(found[c].pixels) for c in "RGB"], axis=-1)
            elif "Y" in found:
                img = np.asarray(found["Y"].pixels)
            elif len(found) >= 1:
                img = np.asarray(next(iter(found.values())).pixels)
            else:
                raise InputError(path, "EXR file has no channels")
    except InputError:
        raise
    except Exception as exc:  # OpenEXR raises plain exceptions with varying types
        raise InputError(path, f"unreadable EXR image ({exc})") from exc
    return img.astype(np.float32)


def _read_tiff(path: Path) -> np.ndarray:
    import tifffile

    try:
        img = tifffile.imread(str(path))
    except Exception as exc:
        raise InputError(path, f"unreadable TIFF image ({exc})") from exc
    return _scale_integer(np.asarray(img), path)


def _read_png(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "unreadable image")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        img = img[:, :, ::-1]  # OpenCV gives BGR
    return _scale_integer(np.ascontiguousarray(img), path)


def read_image(path: str | Path) -> np.ndarray:
    """Read one image as float32 H x W x C, RGB order, C in {1, 3}."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = read_exr(path)
    elif suffix in (".tif", ".tiff"):
        img = _read_tiff(path)
    elif suffix == ".png":
        img = _read_png(path)
    else:
        raise InputError(path, f"unsupported image format {suffix!r} (use PNG, TIFF or EXR)")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise InputError(path, f"unexpected image shape {img.shape}")
    if img.shape[2] == 4:
        img = img[:, :, :3]
    return img


def read_mask(path: str | Path) -> np.ndarray:
    """Read a mask image: True where any channel is non-zero."""
    img = read_image(path)
    return np.any(img > 0, axis=-1)


def write_exr(path: str | Path, img: np.ndarray) -> None:
    """Write float32 linear RGB (H x W x 3) or grey (H x W) as OpenEXR, atomically."""
    import OpenEXR

    img = np.ascontiguousarray(img, dtype=np.float32)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    channels = {"RGB": img} if img.ndim == 3 else {"Y": img}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write an 8-bit (uint8) or 16-bit (uint16) RGB / grey PNG atomically."""
    import cv2

    img = np.asarray(img)
    if img.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"write_png needs uint8 or uint16, got {img.dtype}")
    if img.ndim == 3:
        img = img[:, :, ::-1]  # RGB -> BGR for OpenCV
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: could not write PNG")
