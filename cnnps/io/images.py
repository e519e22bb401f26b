"""Reading and writing images of a capture: 8/16-bit PNG, 8-bit JPEG, 8/16-bit TIFF,
float32 OpenEXR, and reading camera RAW photos (DNG, CR2, CR3, NEF, ARW, ...).

:func:`read_image` returns float32 H x W x C in RGB channel order (C = 1 or 3), with
integer images scaled to [0, 1] by their type's maximum and EXR left linear as stored.
:func:`read_image_raw` returns the same pixels in the file's own type (uint8, uint16 or
float32), which is what saturation tests and look-up-table decoding (sRGB, see
:mod:`cnnps.io.srgb`) need; :func:`max_code` is the largest value of an integer type.
RAW photos (:data:`cnnps.io.raw.RAW_SUFFIXES`) are demosaiced linearly by LibRaw into
uint16 RGB, black level at 0 and white level at 65535 (:func:`cnnps.io.raw.read_raw`);
:func:`pixel_kind` tells them from 16-bit PNG/TIFF files.
JPEG files are read as stored: the EXIF orientation tag is NOT applied, so the pixel
grid is the sensor's (a mask drawn on a rotated view will not match in size).
An alpha channel is dropped. Errors are :class:`cnnps.infra.errors.InputError` naming
the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cnnps.infra.atomic import atomic_path
from cnnps.infra.errors import InputError
from cnnps.io.raw import RAW_KIND, RAW_SUFFIXES, is_raw, read_raw

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr") + RAW_SUFFIXES


def max_code(dtype) -> int | None:
    """The largest value of an integer pixel type (255, 65535); None for float images."""
    dtype = np.dtype(dtype)
    if dtype == np.uint8:
        return 255
    if dtype == np.uint16:
        return 65535
    return None


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
    return np.asarray(img)


def _read_opencv(path: Path) -> np.ndarray:
    """PNG and JPEG through OpenCV, in the file's own type; RGB(A) order."""
    import cv2

    # IMREAD_UNCHANGED keeps 16 bits and ignores the EXIF orientation (the stored grid)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "unreadable image")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        img = img[:, :, ::-1]  # OpenCV gives BGR
    return np.ascontiguousarray(img)


def pixel_kind(path: str | Path, img: np.ndarray) -> str:
    """The pixel type recorded for an image read by :func:`read_image_raw`: ``"uint8"``,
    ``"uint16"`` or ``"float32"``, and ``"raw-uint16"`` for a RAW photo."""
    return RAW_KIND if is_raw(path) else str(img.dtype)


def read_image_raw(path: str | Path) -> np.ndarray:
    """Read one image as H x W x C (C in {1, 3}, RGB order) in the file's own pixel type:
    uint8 or uint16 for PNG, JPEG and TIFF, float32 for EXR (float TIFFs as float32),
    uint16 linear RGB for RAW photos (:func:`cnnps.io.raw.read_raw`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = read_exr(path)
    elif suffix in (".tif", ".tiff"):
        img = _read_tiff(path)
    elif suffix in (".png", ".jpg", ".jpeg"):
        img = _read_opencv(path)
    elif suffix in RAW_SUFFIXES:
        img = read_raw(path)
    else:
        raise InputError(path, f"unsupported image format {suffix!r} (use PNG, JPEG, TIFF, EXR or a camera RAW file)")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise InputError(path, f"unexpected image shape {img.shape}")
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if not (img.dtype in (np.uint8, np.uint16) or np.issubdtype(img.dtype, np.floating)):
        raise InputError(path, f"unsupported pixel type {img.dtype}")
    if np.issubdtype(img.dtype, np.floating) and img.dtype != np.float32:
        img = img.astype(np.float32)
    return img


def read_image(path: str | Path) -> np.ndarray:
    """Read one image as float32 H x W x C, RGB order, C in {1, 3}; integer images
    scaled to [0, 1] by their type's maximum (no sRGB decoding: see :mod:`cnnps.io.srgb`)."""
    path = Path(path)
    return _scale_integer(read_image_raw(path), path)


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
