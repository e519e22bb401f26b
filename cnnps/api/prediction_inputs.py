"""The arrays :func:`cnnps.predict` takes, checked: each bad one is a one-line
:class:`cnnps.infra.errors.ConfigError` naming it and the shape it must have."""

from __future__ import annotations

import numpy as np

from cnnps.infra.errors import ConfigError


def check_arrays(images, lights, mask, intensities, normal_gt):
    """(images (m, H, W[, C]) uint8, uint16 or float32; lights (m, 3) unit; mask (H, W)
    bool; intensities (m, 3); normal_gt (H, W, 3) float32 or None). Lights are made unit
    (unit rows are used exactly as given); a mask of None is every pixel; intensities of
    None are all 1, (m,) is repeated over the channels."""
    images = np.asarray(images)
    if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[3] not in (1, 3)):
        raise ConfigError(f"images must be (m, H, W) or (m, H, W, 3), got shape {images.shape}")
    if images.dtype not in (np.uint8, np.uint16, np.float32):
        if not np.issubdtype(images.dtype, np.floating):
            raise ConfigError(f"images must be uint8, uint16 or float, got {images.dtype}")
        images = images.astype(np.float32)
    if images.dtype == np.float32 and not np.all(np.isfinite(images)):
        raise ConfigError("images contain NaN or infinite values")
    m, H, W = images.shape[:3]
    if m < 3:
        raise ConfigError(f"at least 3 images are needed, got {m}")
    lights = np.asarray(lights, dtype=np.float64)
    if lights.shape != (m, 3):
        raise ConfigError(f"lights must be ({m}, 3) for {m} images, got shape {lights.shape}")
    norms = np.linalg.norm(lights, axis=1)
    if np.any(norms < 1e-8) or not np.all(np.isfinite(norms)):
        raise ConfigError("lights must be finite, non-zero directions")
    off = np.abs(norms - 1.0) > 1e-12
    if off.any():
        lights = lights.copy()
        lights[off] /= norms[off, None]
    if mask is None:
        mask = np.ones((H, W), dtype=bool)
    mask = np.asarray(mask).astype(bool)
    if mask.shape != (H, W):
        raise ConfigError(f"mask must be ({H}, {W}) like the images, got shape {mask.shape}")
    if not mask.any():
        raise ConfigError("mask is empty (no pixel is True)")
    intensities = np.ones((m, 3)) if intensities is None else np.asarray(intensities, dtype=np.float64)
    if intensities.shape == (m,):
        intensities = np.repeat(intensities[:, None], 3, axis=1)
    if intensities.shape != (m, 3) or np.any(~(intensities > 0)):
        raise ConfigError(f"intensities must be ({m}, 3) (or ({m},)) positive values, got shape {intensities.shape}")
    if normal_gt is not None:
        normal_gt = np.asarray(normal_gt, dtype=np.float32)
        if normal_gt.shape != (H, W, 3):
            raise ConfigError(f"normal_gt must be ({H}, {W}, 3), got shape {normal_gt.shape}")
    return images, lights, mask, intensities, normal_gt


def check_intrinsics(K) -> np.ndarray:
    """K as a (3, 3) pinhole matrix (:func:`cnnps.ps.camera.check_intrinsics`)."""
    from cnnps.ps.camera import check_intrinsics as check

    try:
        return check(K)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def check_positions(positions, intrinsics, m: int) -> np.ndarray:
    """(m, 3) point-light positions in front of the camera; they need ``intrinsics``."""
    from cnnps.ps.near_lights import check_positions as check

    if intrinsics is None:
        raise ConfigError("light_positions need intrinsics (point lights are placed relative to a pinhole camera)")
    try:
        positions = check(positions)
    except ValueError as exc:
        raise ConfigError(f"light_positions: {exc}") from None
    if positions.shape[0] != m:
        raise ConfigError(f"light_positions must be ({m}, 3) for {m} images, got shape {positions.shape}")
    return positions


def stack_from_arrays(images, mask: np.ndarray, intensities: np.ndarray, grey: str, linearize,
                      saturation: float | None):
    """A :class:`cnnps.io.pixel_store.PixelStack` in memory of (m, H, W[, C]) images'
    mask pixels, each made exactly as a capture folder's image file would be
    (:func:`cnnps.io.capture.masked_pixels`)."""
    from cnnps.io.capture import masked_pixels
    from cnnps.io.pixel_store import PixelStack

    m = images.shape[0]
    stack = PixelStack(m, int(mask.sum()))
    for k in range(m):
        raw = images[k] if images.ndim == 4 else images[k][..., None]
        pix = masked_pixels(raw, mask, intensities[k], grey, linearize, saturation)
        stack.write(k, pix.values, pix.saturated)
        stack.kinds[pix.kind] = stack.kinds.get(pix.kind, 0) + 1
    return stack
