"""Analytic chrome-ball and matte-ball photos (no Blender) for the calibration tests.

Chrome: a disc of uniform brightness ``body`` (the room's reflection) on a black
background, plus a Gaussian highlight of ``sigma`` pixels centred exactly where the
sphere's normal is the half vector of the light and the view, i.e. at
``(cx + r h_x, cy - r h_y)`` (rows grow downward). Matte: ``E[j, c] * max(n.l_j, 0)``.
Every pixel is the mean of ``ss x ss`` point samples over its area (a camera's pixel
integration, anti-aliased edges).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cnnps.io.images import write_exr, write_png
from cnnps.io.srgb import linear_to_srgb
from cnnps.ps.ball import Ball

SHAPE = (72, 80)  # H, W
BALL = Ball(41.3, 35.6, 29.4)  # x = column, y = row, radius (px)


def highlight_position(light, ball: Ball) -> tuple[float, float]:
    """Pixel (x, y) of the mirror point of ``light`` on ``ball`` (orthographic view +z)."""
    h = np.asarray(light, dtype=np.float64) + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h)
    return ball.cx + ball.radius * h[0], ball.cy - ball.radius * h[1]


def _subsamples(shape, ss):
    o = (np.arange(ss) + 0.5) / ss - 0.5
    rows, cols = np.indices(shape, dtype=np.float64)
    for a in o:
        for b in o:
            yield cols + a, rows + b


def chrome_image(light, ball: Ball = BALL, shape=SHAPE, sigma: float = 1.2, body: float = 0.05,
                 peak: float = 4.0, ss: int = 4, extra_spots=()) -> np.ndarray:
    """(H, W) grey chrome-ball photo under one light; ``extra_spots``: more (x, y) highlights."""
    x0, y0 = highlight_position(light, ball)
    spots = [(x0, y0), *extra_spots]
    img = np.zeros(shape)
    for X, Y in _subsamples(shape, ss):
        inside = np.hypot(X - ball.cx, Y - ball.cy) < ball.radius
        val = np.full(shape, body)
        for sx, sy in spots:
            val = val + peak * np.exp(-((X - sx) ** 2 + (Y - sy) ** 2) / (2 * sigma**2))
        img += np.where(inside, val, 0.0)
    return img / ss**2


def matte_image(light, E, ball: Ball = BALL, shape=SHAPE, ss: int = 4) -> np.ndarray:
    """(H, W, 3) matte white ball photo: E (3,) * max(n.l, 0)."""
    l = np.asarray(light, dtype=np.float64)
    l = l / np.linalg.norm(l)
    img = np.zeros(shape)
    for X, Y in _subsamples(shape, ss):
        nx, ny = (X - ball.cx) / ball.radius, -(Y - ball.cy) / ball.radius
        rho2 = nx**2 + ny**2
        nz = np.sqrt(np.clip(1 - rho2, 0, None))
        img += np.where(rho2 < 1, np.maximum(nx * l[0] + ny * l[1] + nz * l[2], 0.0), 0.0)
    img /= ss**2
    return img[:, :, None] * np.asarray(E, dtype=np.float64)[None, None, :]


def write_ball_folder(folder: Path, images, fmt: str = "exr", mask: np.ndarray | None = None,
                      scale: float = 1.0, srgb: bool = False) -> list[str]:
    """Write (m, H, W) or (m, H, W, 3) linear images as a ball folder (filenames.txt, images,
    optional mask.png). Integer formats store ``scale * image`` clipped to [0, 1], sRGB-encoded
    (as a camera's JPEG/PNG) when ``srgb``; ``dng``: its RGGB mosaic as a camera RAW file."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for j, img in enumerate(images):
        img = np.asarray(img, dtype=np.float64)
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        if fmt == "exr":
            name = f"{j:03d}.exr"
            write_exr(folder / name, img.astype(np.float32))
        elif fmt == "dng":
            from tests.support.dng import mosaic, write_dng

            name = f"{j:03d}.dng"
            write_dng(folder / name, mosaic(np.clip(img * scale, 0, 1)))
        else:
            top = {"png8": 255, "png16": 65535}[fmt]
            name = f"{j:03d}.png"
            v = np.clip(img * scale, 0, 1)
            q = np.round((linear_to_srgb(v) if srgb else v) * top).astype(np.uint8 if top == 255 else np.uint16)
            write_png(folder / name, q)
        names.append(name)
    (folder / "filenames.txt").write_text("".join(n + "\n" for n in names))
    if mask is not None:
        write_png(folder / "mask.png", mask.astype(np.uint8) * 255)
    return names


def angles_deg(a, b) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def disc_mask(ball, shape=SHAPE, ss: int = 4) -> np.ndarray:
    """Pixel-coverage >= 1/2 mask of a disc (supersampled ``ss`` x ``ss`` per pixel)."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    rows, cols = np.indices(shape, dtype=float)
    cov = sum((np.hypot(cols + a - ball.cx, rows + b - ball.cy) < ball.radius).astype(float) for a in o for b in o)
    return cov / ss**2 >= 0.5
