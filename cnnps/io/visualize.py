"""Pictures of normal maps and angular-error maps (uint8 RGB, no matplotlib)."""

from __future__ import annotations

import math

import numpy as np


def normal_to_rgb(normals: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Colour (H, W, 3) normals as RGB = (n + 1) / 2; black outside ``mask``.

    A normal facing the camera (0, 0, 1) is (128, 128, 255) light blue; +x is red, +y
    green (image up).
    """
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {normals.shape}")
    rgb = np.clip(np.round((normals + 1.0) * 127.5), 0, 255).astype(np.uint8)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != normals.shape[:2]:
            raise ValueError(f"mask shape {mask.shape} does not match normals {normals.shape[:2]}")
        rgb[~mask] = 0
    return rgb


def _nice_ceiling(x: float) -> float:
    """Smallest of 1, 2, 2.5, 5 x 10^k that is >= x (a readable scale end)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = math.floor(math.log10(x))
    for f in (1.0, 2.0, 2.5, 5.0, 10.0):
        if f * 10**e >= x * (1 - 1e-9):
            return f * 10**e
    return 10.0 ** (e + 1)  # pragma: no cover


def error_picture(
    err_deg: np.ndarray,
    mask: np.ndarray | None = None,
    vmax: float | None = None,
    colormap: int | None = None,
) -> np.ndarray:
    """Colour-mapped angular error (H, W) in degrees with a labelled colour bar.

    0 degrees is the low end of the colour map (dark blue with JET), ``vmax`` and above
    the high end (dark red). ``vmax`` defaults to a round number just above the 99th
    percentile of the errors inside the mask. Pixels outside the mask are black. The
    returned uint8 RGB picture is the error map with a bar panel on its right.
    """
    import cv2

    err = np.asarray(err_deg, dtype=np.float64)
    if err.ndim != 2:
        raise ValueError(f"err_deg must be (H, W), got {err.shape}")
    mask = np.isfinite(err) if mask is None else (np.asarray(mask, dtype=bool) & np.isfinite(err))
    if mask.shape != err.shape:
        raise ValueError(f"mask shape {mask.shape} does not match errors {err.shape}")
    if vmax is None:
        vmax = _nice_ceiling(float(np.percentile(err[mask], 99))) if mask.any() else 1.0
    if not (vmax > 0 and np.isfinite(vmax)):
        raise ValueError(f"vmax must be a positive number, got {vmax}")
    cmap = cv2.COLORMAP_JET if colormap is None else colormap
    level = np.clip(np.nan_to_num(err) / vmax, 0.0, 1.0)
    return _with_colour_bar(level, mask, [f"{vmax:g} deg", f"{vmax / 2:g}", "0"], cmap)


def confidence_picture(confidence: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The confidence map (H, W) in [0, 1] as a uint8 RGB picture with a colour bar:
    1 (most trusted) the bright end of VIRIDIS, 0 the dark end; black outside ``mask``."""
    import cv2

    conf = np.asarray(confidence, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool) & np.isfinite(conf)
    return _with_colour_bar(np.clip(np.nan_to_num(conf), 0.0, 1.0), mask, ["1 trusted", "0.5", "0"],
                            cv2.COLORMAP_VIRIDIS)


def _with_colour_bar(level: np.ndarray, mask: np.ndarray, labels: list[str], cmap: int) -> np.ndarray:
    """``level`` (H, W) in [0, 1] colour-mapped (black outside ``mask``) with a bar panel on
    its right labelled ``labels`` (top, middle, bottom); uint8 RGB."""
    import cv2

    H, W = level.shape
    bgr = cv2.applyColorMap(np.round(level * 255).astype(np.uint8), cmap)
    bgr[~mask] = 0

    # Colour bar panel: height = image height (at least 64 px so labels fit).
    ph = max(H, 64)
    scale = max(0.3, min(1.0, ph / 400))
    thick = 1
    font = cv2.FONT_HERSHEY_SIMPLEX
    text_w = max(cv2.getTextSize(t, font, scale, thick)[0][0] for t in labels)
    text_h = cv2.getTextSize("0", font, scale, thick)[0][1]
    margin = max(3, ph // 40)
    bar_w = max(8, ph // 20)
    pw = margin + bar_w + margin + text_w + margin
    panel = np.zeros((ph, pw, 3), dtype=np.uint8)
    top, bottom = margin + text_h, ph - margin - text_h
    ramp = np.linspace(255, 0, bottom - top).astype(np.uint8)[:, None]  # top = the scale's top
    bar = cv2.applyColorMap(np.repeat(ramp, bar_w, axis=1), cmap)
    panel[top:bottom, margin : margin + bar_w] = bar
    x = 2 * margin + bar_w
    for t, y in zip(labels, (top, (top + bottom) // 2, bottom)):
        cv2.putText(panel, t, (x, min(ph - 1, y + text_h // 2)), font, scale, (255, 255, 255), thick, cv2.LINE_AA)

    canvas = np.zeros((ph, W + pw, 3), dtype=np.uint8)
    canvas[:H, :W] = bgr
    canvas[:, W:] = panel
    return np.ascontiguousarray(canvas[:, :, ::-1])  # BGR -> RGB


def score_picture(score, vmax: float | None = None, enlarge: int = 1) -> np.ndarray:
    """The error map of a :class:`cnnps.ps.metrics.GroundTruthScore` as a uint8 RGB picture
    with a colour bar (:func:`error_picture`). ``enlarge``: whole factor, nearest neighbour
    (small captures); ``vmax``: the scale's top (default: from the errors)."""
    err, scored = score.errors, score.scored
    if enlarge > 1:
        err = np.repeat(np.repeat(err, enlarge, axis=0), enlarge, axis=1)
        scored = np.repeat(np.repeat(scored, enlarge, axis=0), enlarge, axis=1)
    return error_picture(err, scored, vmax=vmax)
