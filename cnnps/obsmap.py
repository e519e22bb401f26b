"""Observation maps (Ikehata, ECCV 2018, Eq. 2), vectorised over all pixels.

Each light j with unit direction (lx, ly, lz) falls into one cell of a w x w map:

    col = int(w * (lx + 1) / 2)      # x index, left to right
    row = int(w * (ly + 1) / 2)      # y index: row 0 holds ly = -1 (the BOTTOM of the
                                     # hemisphere), the last row ly = +1 (its top)

(values equal to w, at lx or ly = 1 exactly, are clipped to w - 1). So maps are indexed
``map[..., row, col] = map[..., y_cell, x_cell]``; note that rows grow with +y, the
opposite of image rows. The cell holds I_j / L_j (intensity divided by the light's
intensity). When several lights fall into one cell, the cell holds the MEAN of their
values: the result is independent of the order of the images, and averaging nearby lights
lowers noise. Each pixel's map is then divided by its largest cell, so the largest used
value is 1 (a pixel dark under every light keeps an all-zero map). Cells hit by no light
stay 0, exactly as cells hit by a light that casts a shadow.
"""

from __future__ import annotations

import numpy as np

DEFAULT_WIDTH = 32


def light_cells(lights: np.ndarray, w: int = DEFAULT_WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """Return (row, col) cell indices, each shape (m,), of unit light directions (m, 3)."""
    lights = np.asarray(lights, dtype=np.float64)
    col = np.clip((w * (lights[:, 0] + 1.0) / 2.0).astype(np.int64), 0, w - 1)
    row = np.clip((w * (lights[:, 1] + 1.0) / 2.0).astype(np.int64), 0, w - 1)
    return row, col


def observation_maps(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Build observation maps for P pixels.

    intensities: (P, m) measured values already divided by each light's intensity.
        Negative values (sensor noise below black) are clipped to 0.
    lights: (m, 3) unit light directions in the camera frame.
    light_mask: optional (P, m) bool; False drops that light for that pixel (per-pixel
        light subsets used for training data).
    Returns (P, w, w) maps indexed [pixel, row=y_cell, col=x_cell], each scaled so its
    largest cell is 1.
    """
    intensities = np.asarray(intensities)
    if intensities.ndim != 2:
        raise ValueError(f"intensities must be (P, m), got {intensities.shape}")
    P, m = intensities.shape
    lights = np.asarray(lights)
    if lights.shape != (m, 3):
        raise ValueError(f"lights must be ({m}, 3) to match intensities, got {lights.shape}")
    row, col = light_cells(lights, w)
    cell = row * w + col  # (m,)

    values = np.maximum(intensities.astype(np.float32, copy=False), 0.0)
    if light_mask is not None:
        light_mask = np.asarray(light_mask, dtype=bool)
        if light_mask.shape != (P, m):
            raise ValueError(f"light_mask must be {(P, m)}, got {light_mask.shape}")
        values = np.where(light_mask, values, 0.0)

    # Work on the (at most m) occupied cells only: group lights by cell, sum each group
    # with one reduceat over the light axis, divide by the group's light count (the mean),
    # then scatter the compact result into the w*w map once.
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
    used_cells = sorted_cells[starts]
    sums = np.add.reduceat(values[:, order], starts, axis=1)  # (P, n_used)
    if light_mask is None:
        counts = np.diff(np.r_[starts, m]).astype(np.float32)[None, :]
    else:
        counts = np.add.reduceat(light_mask[:, order].astype(np.float32), starts, axis=1)
    compact = sums / np.maximum(counts, 1.0)

    peak = compact.max(axis=1, keepdims=True)
    np.divide(compact, peak, out=compact, where=peak > 0)
    compact[(peak <= 0)[:, 0]] = 0.0
    maps = np.zeros((P, w * w), dtype=dtype)
    maps[:, used_cells] = compact
    return maps.reshape(P, w, w)
